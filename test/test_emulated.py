"""Tests of the emulated urban drive (city model, route, IMU, odometry, GNSS, NLOS, faults)."""
import numpy as np
import pytest

from gnsscam_ros.core.frames import LocalFrame, sagnac_corrected
from gnsscam_ros.core.types import GLONASS, GPS
from gnsscam_ros.datasets.city import City, Facades, los_blocked, make_city
from gnsscam_ros.datasets.emulated.config import EmulationConfig, stream_rng
from gnsscam_ros.datasets.emulated.drive import make_emulated_drive
from gnsscam_ros.datasets.emulated.scenario import make_scenario

CFG = EmulationConfig()


@pytest.fixture(scope='module')
def drive():
    return make_emulated_drive(3, faults=0, nlos=True)


@pytest.fixture(scope='module')
def clean():
    return make_emulated_drive(3, faults=0, nlos=False)


@pytest.fixture(scope='module')
def faulty():
    return make_emulated_drive(3, faults=5, bias_m=100.0, nlos=True)


def _enu(d):
    return LocalFrame(*d.origin_llh).ecef_to_enu(d.truth.ecef_m)


def _truth_kinematics(d):
    """Speed [m/s] and yaw rate [rad/s] of the truth by central differences (100 Hz)."""
    enu = _enu(d)
    t = (d.truth.stamp_ns - d.truth.stamp_ns[0]) * 1e-9
    v = np.linalg.norm(np.gradient(enu[:, :2], t, axis=0), axis=1)
    yaw_rate = np.gradient(np.unwrap(d.truth.yaw_rad), t)
    return t, v, yaw_rate


def _hand_city(boxes):
    empty = np.zeros((0, 2))
    fac = Facades(p0_m=empty, p1_m=empty, height_m=np.zeros(0), normal=empty,
                  style_id=np.zeros(0, int), building=np.zeros(0, int))
    return City(blocks=np.asarray(boxes, float), street_width_m=20.0, block_size_m=80.0,
                street_e_m=np.zeros(1), street_n_m=np.zeros(1), facades=fac)


# ---------------------------------------------------------------------------- city / LOS

def test_los_blocked_single_building():
    city = _hand_city([[10.0, -5.0, 20.0, 5.0, 30.0]])
    rx = np.zeros(3)
    dirs = np.array([
        [1.0, 0.0, 0.5],     # hits the west wall at u = 5 m
        [1.0, 0.0, 4.0],     # passes over the roof (u = 40 m at the wall)
        [-1.0, 0.0, 0.1],    # away from the building
        [1.0, 1.0, 0.1],     # passes north of it
        [1.0, 0.4, 0.2],     # hits at (10, 4, 2)
        [0.0, 0.0, 1.0],     # zenith
        [1.0, 0.0, 0.0],     # horizon: counts as blocked
        [1.0, 0.0, 2.9],     # u = 29 m at the near wall: blocked
        [1.0, 0.0, 3.1],     # u = 31 m at the near wall: clear
    ])
    want = [True, False, False, False, True, False, True, True, False]
    assert los_blocked(city, rx, dirs).tolist() == want
    # Zero east component: the ray runs inside / outside the east slab.
    d = np.array([[0.0, 1.0, 0.1]])
    assert los_blocked(city, np.array([15.0, -20.0, 0.0]), d).tolist() == [True]
    assert los_blocked(city, np.array([25.0, -20.0, 0.0]), d).tolist() == [False]
    assert los_blocked(city, np.array([15.0, -20.0, 0.0]), -d * [1, 1, -1]).tolist() == [False]


@pytest.mark.slow
def test_los_blocked_matches_ray_marching():
    city = make_city(np.random.default_rng(7))
    rng = np.random.default_rng(1)
    b = city.blocks
    mism = 0
    for _ in range(6):
        # A point in a street (on a street centre line, between intersections).
        i = rng.integers(1, len(city.street_e_m) - 1)
        rx = np.array([city.street_e_m[i], rng.uniform(-300, 300), 1.8])
        el = rng.uniform(np.radians(10), np.radians(80), 25)
        az = rng.uniform(0, 2 * np.pi, 25)
        dirs = np.column_stack([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)])
        got = los_blocked(city, rx, dirs)
        t = np.arange(0.0, 300.0, 0.05)
        for k, d in enumerate(dirs):
            p = rx + t[:, None] * d
            p = p[p[:, 2] <= city.max_height_m]
            inside = ((p[:, None, 0] >= b[:, 0]) & (p[:, None, 0] <= b[:, 2])
                      & (p[:, None, 1] >= b[:, 1]) & (p[:, None, 1] <= b[:, 3])
                      & (p[:, None, 2] <= b[:, 4]))
            mism += bool(inside.any()) != bool(got[k])
    assert mism <= 1   # grazing corners may differ by one marching step


def test_city_heights_styles_and_facade_orientation():
    city = make_city(np.random.default_rng(5))
    b = city.blocks
    assert len(b) > 300
    assert b[:, 4].min() >= 12.0 and b[:, 4].max() <= 45.0
    assert np.all(b[:, 2] > b[:, 0]) and np.all(b[:, 3] > b[:, 1])
    f = city.facades
    assert len(f) > 500
    shared = f.style_id < 6
    assert 0.2 < shared.mean() < 0.4
    assert len(np.unique(f.style_id[shared])) == 6
    assert len(np.unique(f.style_id[~shared])) == int((~shared).sum())   # others unique
    # Normal = (p1 - p0) turned clockwise, unit length.
    seg = f.p1_m - f.p0_m
    cw = np.column_stack([seg[:, 1], -seg[:, 0]]) / f.width_m[:, None]
    assert np.allclose(cw, f.normal)
    # Outward: 1 m in front of the facade centre is outside every building, 1 m behind
    # it is inside the facade's own building.
    mid = 0.5 * (f.p0_m + f.p1_m)

    def inside(p):
        return ((p[:, None, 0] > b[:, 0]) & (p[:, None, 0] < b[:, 2])
                & (p[:, None, 1] > b[:, 1]) & (p[:, None, 1] < b[:, 3]))

    assert not inside(mid + f.normal).any()
    behind = inside(mid - f.normal)
    assert np.all(behind[np.arange(len(f)), f.building])
    c = f.corners_enu(0)
    assert c.shape == (4, 3) and np.allclose(c[2, 2], f.height_m[0]) and c[0, 2] == 0.0
    assert f.corners_enu(np.arange(3)).shape == (3, 4, 3)


def test_facades_near_faces_the_point():
    city = make_city(np.random.default_rng(5))
    p = np.array([city.street_e_m[6], city.street_n_m[6] + 40.0])
    idx = city.facades_near(p, radius_m=60.0)
    assert len(idx) >= 2
    f = city.facades
    assert np.all(np.einsum('ij,ij->i', p - f.p0_m[idx], f.normal[idx]) > 0)
    d = np.linalg.norm(f.centre_enu_m[idx, :2] - p, axis=1)
    assert d.min() < 60.0


# ---------------------------------------------------------------------------- route / truth

def test_length_speed_and_stops(drive):
    enu = _enu(drive)
    length = np.sum(np.linalg.norm(np.diff(enu[:, :2], axis=0), axis=1))
    assert abs(length - 2300.0) < 230.0
    assert abs(drive.info['route_length_m'] - length) < 5.0
    t, v, _ = _truth_kinematics(drive)
    assert np.all(np.diff(drive.truth.stamp_ns) == 10_000_000)       # 100 Hz
    assert v.max() <= 14.05
    moving = v > 0.5
    assert 5.0 <= np.median(v[moving]) <= 14.0
    assert np.max(v) > 9.0
    # Standstill at the start and at least one stop in the middle of the drive.
    assert v[:100].max() < 0.05
    still = (v < 0.01) & (t > 10.0) & (t < t[-1] - 10.0)
    assert still.sum() >= 300
    # Accelerations bounded (smooth driving).
    a = np.gradient(v, t)
    assert np.abs(a[moving]).max() < 3.0
    # Flat ground at the antenna height.
    assert np.allclose(enu[:, 2], CFG.antenna_height_m, atol=1e-3)


def test_truth_stays_in_the_streets(drive):
    sc = make_scenario(drive.info['seed'])
    enu = _enu(drive)[::20]
    b = sc.city.blocks
    dx = np.maximum(np.maximum(b[:, 0] - enu[:, None, 0], enu[:, None, 0] - b[:, 2]), 0)
    dy = np.maximum(np.maximum(b[:, 1] - enu[:, None, 1], enu[:, None, 1] - b[:, 3]), 0)
    assert np.hypot(dx, dy).min() > 3.0      # never closer than 3 m to a building


def test_pose_sampler_reproduces_truth(drive):
    sc = make_scenario(drive.info['seed'])
    t = (drive.truth.stamp_ns[::50] - sc.t0_ns) * 1e-9
    pose = sc.pose_at(t)
    assert np.allclose(sc.frame.enu_to_ecef(pose.enu_m), drive.truth.ecef_m[::50], atol=1e-6)
    dyaw = (pose.yaw_rad - drive.truth.yaw_rad[::50] + np.pi) % (2 * np.pi) - np.pi
    assert np.abs(dyaw).max() < 1e-9
    # Camera-rate (10 Hz) poses off the truth grid are between their neighbours.
    mid = sc.pose_at(np.array([100.05]))
    a, c = sc.pose_at(np.array([100.0, 100.1])).enu_m
    assert np.linalg.norm(mid.enu_m[0] - 0.5 * (a + c)) < 0.05


# ---------------------------------------------------------------------------- IMU / odometry

def test_imu_integrates_back_to_truth(drive):
    imu, info = drive.imu, drive.info
    t, v, _ = _truth_kinematics(drive)
    yaw = np.unwrap(drive.truth.yaw_rad)
    assert np.array_equal(imu.stamp_ns, drive.truth.stamp_ns)
    gyro = imu.gyro_rps - info['imu_bias']['gyro_rps']
    acc = imu.accel_mps2 - info['imu_bias']['accel_mps2']
    assert abs(np.mean(acc[:, 2]) - info['gravity_mps2']) < 0.01
    assert np.abs(np.mean(gyro[:, :2], axis=0)).max() < 1e-3
    rng = np.random.default_rng(0)
    for i0 in rng.integers(0, len(t) - 1001, 12):
        sl = slice(i0, i0 + 1001)
        dt = np.diff(t[sl])
        dyaw = np.sum(0.5 * (gyro[sl][1:, 2] + gyro[sl][:-1, 2]) * dt)
        assert abs(dyaw - (yaw[i0 + 1000] - yaw[i0])) < 0.03
        vi = v[i0] + np.concatenate(
            [[0], np.cumsum(0.5 * (acc[sl][1:, 0] + acc[sl][:-1, 0]) * dt)])
        assert np.abs(vi - v[sl]).max() < 0.15
        # Dead reckoning over 10 s with the IMU speed and the IMU heading.
        yi = yaw[i0] + np.concatenate(
            [[0], np.cumsum(0.5 * (gyro[sl][1:, 2] + gyro[sl][:-1, 2]) * dt)])
        vel = np.column_stack([vi * np.cos(yi), vi * np.sin(yi)])
        pos = np.sum(0.5 * (vel[1:] + vel[:-1]) * dt[:, None], axis=0)
        enu = _enu(drive)
        assert np.linalg.norm(pos - (enu[i0 + 1000, :2] - enu[i0, :2])) < 1.5
    # Lateral specific force is the centripetal acceleration v * yaw rate.
    _, _, yr = _truth_kinematics(drive)
    assert np.sqrt(np.mean((acc[:, 1] - v * yr) ** 2)) < 0.1


def test_odometry_consistent_with_truth(drive):
    od = drive.odometry
    assert np.all(np.diff(od.stamp_ns) == 100_000_000)               # 10 Hz
    t, v, yr = _truth_kinematics(drive)
    idx = np.searchsorted(drive.truth.stamp_ns, od.stamp_ns)
    assert np.array_equal(drive.truth.stamp_ns[idx], od.stamp_ns)
    moving = v[idx] > 1.0
    ev = od.speed_mps[moving] - v[idx][moving]
    ew = od.yaw_rate_rps - yr[idx]
    assert abs(ev.mean()) < 0.01 and abs(ew.mean()) < 0.002

    # Robust std: the finite-difference truth yaw rate smears the steps at turn entries.
    def mad_std(x):
        return 1.4826 * np.median(np.abs(x - np.median(x)))

    assert 0.8 < mad_std(ev) / np.sqrt(od.speed_var[0]) < 1.2
    assert 0.8 < mad_std(ew) / np.sqrt(od.yaw_rate_var[0]) < 1.2
    assert np.all(od.speed_mps >= 0.0)
    assert np.all(od.speed_mps[v[idx] < 1e-3] == 0.0)                 # standstill reads 0


# ---------------------------------------------------------------------------- GNSS

def test_gnss_epochs_shape_and_geometry(drive):
    n_ep = len(drive.gnss)
    assert abs(n_ep - drive.info['duration_s']) <= 1.0                 # 1 Hz
    stamps = np.array([e.stamp_ns for e in drive.gnss])
    assert np.all(np.diff(stamps) == 1_000_000_000)
    assert stamps[0] % 1_000_000_000 == 0                              # whole seconds
    az_spread = []
    frame = LocalFrame(*drive.origin_llh)
    for e in drive.gnss:
        assert e.n_sv == 12
        assert np.all(e.elevation_deg > 10.0)
        assert len({(s, i) for s, i in zip(e.system, e.sv_id)}) == 12
        assert set(np.unique(e.system)) <= {GPS, GLONASS}
        assert (e.system == GLONASS).sum() >= 3 and (e.system == GPS).sum() >= 3
        assert np.all(e.var_m2 == 10.0)
        r = np.linalg.norm(e.sv_pos_ecef_m, axis=1)
        a = np.where(e.system == GPS, 26_559_700.0, 25_508_000.0)
        assert np.allclose(r, a, atol=1.0)
        assert np.all((e.pr_m > 1.9e7 - 4e5) & (e.pr_m < 2.6e7 + 4e5))
        assert np.all((e.cn0_dbhz > 15) & (e.cn0_dbhz < 56))
        enu = frame.ecef_to_enu(e.sv_pos_ecef_m)
        az = np.sort(np.arctan2(enu[:, 0], enu[:, 1]))
        az_spread.append(np.max(np.diff(np.r_[az, az[0] + 2 * np.pi])))
    assert np.median(az_spread) < np.radians(120)      # no hemisphere without satellites
    # The satellites move: elevations change over the drive.
    first, last = drive.gnss[0], drive.gnss[-1]
    same = [(s, i) for s, i in zip(first.system, first.sv_id)
            if (s, i) in set(zip(last.system, last.sv_id))]
    assert same
    moved = [abs(last.elevation_deg[(last.system == s) & (last.sv_id == i)][0]
                 - first.elevation_deg[(first.system == s) & (first.sv_id == i)][0])
             for s, i in same]
    assert max(moved) > 0.5


def _residuals(d, sagnac=True):
    """Per epoch and system: pr - geometric range from the truth, demeaned; and the means."""
    spread, means = [], []
    for e in d.gnss:
        i = np.searchsorted(d.truth.stamp_ns, e.stamp_ns)
        assert d.truth.stamp_ns[i] == e.stamp_ns
        rx = d.truth.ecef_m[i]
        sv = sagnac_corrected(e.sv_pos_ecef_m, rx) if sagnac else e.sv_pos_ecef_m
        r = e.pr_m - np.linalg.norm(sv - rx, axis=1)
        row = {}
        for s in (GPS, GLONASS):
            m = e.system == s
            spread.extend(r[m] - r[m].mean())
            row[s] = r[m].mean()
        means.append(row)
    return np.asarray(spread), means


def test_clock_is_common_mode_and_sagnac_is_needed(clean):
    spread, means = _residuals(clean, sagnac=True)
    rms = np.sqrt(np.mean(spread ** 2))
    # 10 m^2 white noise, demeaned over ~6 satellites per system.
    assert 2.5 < rms < 3.3
    spread_raw, _ = _residuals(clean, sagnac=False)
    assert np.sqrt(np.mean(spread_raw ** 2)) > 2.5 * rms
    clock = clean.info['rx_clock_bias_m']
    isb = clean.info['isb_glonass_m']
    gps = np.array([m[GPS] for m in means])
    glo = np.array([m[GLONASS] for m in means])
    assert np.abs(gps - clock).max() < 6.0
    assert np.abs(glo - clock - isb).max() < 8.0
    assert abs(np.mean(glo - gps) - isb) < 0.5
    # The clock is a random walk with drift: it does change along the drive.
    assert np.ptp(clock) > 50.0


def test_nlos_only_on_blocked_satellites_and_positive(drive, clean):
    info = drive.info
    blocked, nlos = info['gnss_blocked'], info['gnss_nlos_m']
    assert 0.1 < blocked.mean() < 0.6
    assert np.all(nlos[~blocked] == 0.0)
    assert np.all((nlos[blocked] >= 5.0) & (nlos[blocked] <= 60.0))
    # Same seed without NLOS: only the NLOS term differs.
    pr = np.array([e.pr_m for e in drive.gnss])
    pr_clean = np.array([e.pr_m for e in clean.gnss])
    assert np.allclose(pr - pr_clean, nlos, atol=1e-6)
    assert np.all(clean.info['gnss_nlos_m'] == 0.0)
    # Correlated in time while blocked: consecutive epochs differ much less than independent
    # U(5, 60) draws would (mean |diff| = 18 m).
    both = blocked[1:] & blocked[:-1]
    sv = np.array([e.system * 100 + e.sv_id for e in drive.gnss])
    same_sv = sv[1:] == sv[:-1]
    d = np.abs(np.diff(nlos, axis=0))[both & same_sv]
    assert len(d) > 50 and d.mean() < 6.0
    # Blocked satellites have a lower C/N0 (compared with the NLOS-free run).
    cn0 = np.array([e.cn0_dbhz for e in drive.gnss])
    cn0_clean = np.array([e.cn0_dbhz for e in clean.gnss])
    drop = (cn0_clean - cn0)[blocked]
    assert np.all((drop >= 6.0) & (drop <= 14.0))
    assert np.all(cn0[~blocked] == cn0_clean[~blocked])


def test_blocked_flag_matches_the_city_geometry(drive):
    sc = make_scenario(drive.info['seed'])
    frame = sc.frame
    for k in range(0, len(drive.gnss), 37):
        e = drive.gnss[k]
        rx = drive.info['gnss_truth_ecef_m'][k]
        sv = sagnac_corrected(e.sv_pos_ecef_m, rx)
        dirs = (sv - rx) @ frame.rot_ecef_to_enu.T
        got = los_blocked(sc.city, frame.ecef_to_enu(rx), dirs)
        assert np.array_equal(got, drive.info['gnss_blocked'][k])


def test_fault_record_matches_injected_errors(faulty, drive):
    info = faulty.info
    recs = info['gnss_faults']
    fm = info['gnss_fault_m']
    assert len(recs) == np.count_nonzero(fm)
    per_epoch = np.count_nonzero(fm, axis=1)
    assert set(np.unique(per_epoch)) == {0, 5}
    frac = np.mean(per_epoch > 0)
    assert 0.15 < frac < 0.5
    pr = np.array([e.pr_m for e in faulty.gnss])
    pr0 = np.array([e.pr_m for e in drive.gnss])
    assert np.allclose(pr - pr0, fm, atol=1e-6)          # the only difference is the fault
    t_ep = np.array([(e.stamp_ns - faulty.gnss[0].stamp_ns) * 1e-9 for e in faulty.gnss])
    for r in recs:
        e = faulty.gnss[r['epoch']]
        assert e.stamp_ns == r['stamp_ns']
        assert e.system[r['index']] == r['system'] and e.sv_id[r['index']] == r['sv_id']
        assert fm[r['epoch'], r['index']] == r['bias_m']
        assert 20.0 <= abs(r['bias_m']) <= 200.0
        assert t_ep[r['epoch']] >= CFG.fault_free_start_s
    # Episodes of a few epochs, bias constant over an episode per satellite.
    for a, b in info['fault_episodes']:
        assert 1 <= b - a <= 10
        assert np.all(per_epoch[a:b] == 5)
    by_key = {}
    for r in recs:
        by_key.setdefault((r['episode'], r['system'], r['sv_id']), set()).add(r['bias_m'])
    assert all(len(v) == 1 for v in by_key.values())
    mags = np.abs([next(iter(v)) for v in by_key.values()])
    assert 80.0 < mags.mean() < 120.0
    signs = np.sign([next(iter(v)) for v in by_key.values()])
    assert 0.25 < np.mean(signs > 0) < 0.75


@pytest.mark.slow
def test_fault_sets_are_nested_and_law_respects_clip():
    d2 = make_emulated_drive(11, faults=2, bias_m=100.0, duration_s=150.0)
    d7 = make_emulated_drive(11, faults=7, bias_m=100.0, duration_s=150.0)
    f2, f7 = d2.info['gnss_fault_m'], d7.info['gnss_fault_m']
    assert d2.info['fault_episodes'] == d7.info['fault_episodes']
    assert np.all(f7[f2 != 0] == f2[f2 != 0])
    assert set(np.unique(np.count_nonzero(f7, axis=1))) == {0, 7}
    big = make_emulated_drive(11, faults=9, bias_m=190.0, duration_s=150.0)
    mags = np.abs(big.info['gnss_fault_m'][big.info['gnss_fault_m'] != 0])
    assert mags.max() <= 200.0 and mags.min() >= 20.0
    assert np.any(mags == 200.0)                          # clipping is active at 190 m
    none = make_emulated_drive(11, faults=0, duration_s=150.0)
    assert none.info['gnss_faults'] == [] and not none.info['gnss_fault_m'].any()
    with pytest.raises(ValueError):
        make_emulated_drive(11, faults=13)


# ---------------------------------------------------------------------------- seeds, options

@pytest.mark.slow
def test_deterministic_per_seed_and_different_across_seeds(drive):
    again = make_emulated_drive(3, faults=0, nlos=True)
    assert np.array_equal(again.truth.ecef_m, drive.truth.ecef_m)
    assert np.array_equal(again.imu.accel_mps2, drive.imu.accel_mps2)
    assert np.array_equal(again.odometry.speed_mps, drive.odometry.speed_mps)
    for a, b in zip(again.gnss, drive.gnss):
        assert np.array_equal(a.pr_m, b.pr_m) and np.array_equal(a.sv_pos_ecef_m, b.sv_pos_ecef_m)
    other = make_emulated_drive(4, faults=0, nlos=True)
    n = min(len(other.truth), len(drive.truth))
    assert np.abs(other.truth.ecef_m[:n] - drive.truth.ecef_m[:n]).max() > 50.0
    assert other.gnss[0].stamp_ns != drive.gnss[0].stamp_ns
    assert not np.allclose(other.gnss[0].sv_pos_ecef_m, drive.gnss[0].sv_pos_ecef_m)
    f3 = make_emulated_drive(3, faults=3, duration_s=200.0).info['fault_episodes']
    f4 = make_emulated_drive(4, faults=3, duration_s=200.0).info['fault_episodes']
    assert f3 != f4
    # Streams are independent generators.
    assert stream_rng(3, 'camera').random() == stream_rng(3, 'camera').random()
    assert stream_rng(3, 'camera').random() != stream_rng(3, 'imu').random()


def test_duration_cut_is_a_prefix(drive):
    short = make_emulated_drive(3, faults=0, nlos=True, duration_s=60.0)
    t = (short.truth.stamp_ns[-1] - short.truth.stamp_ns[0]) * 1e-9
    assert abs(t - 60.0) < 0.011
    assert len(short.gnss) == 61
    n = len(short.truth)
    assert np.array_equal(short.truth.ecef_m, drive.truth.ecef_m[:n])
    assert np.array_equal(short.imu.gyro_rps, drive.imu.gyro_rps[:n])
    assert np.array_equal(short.gnss[-1].pr_m, drive.gnss[60].pr_m)
    assert short.odometry.stamp_ns[-1] <= short.truth.stamp_ns[-1]
    assert short.info['gnss_nlos_m'].shape == (61, 12)


@pytest.mark.slow
def test_higher_gnss_rate():
    d = make_emulated_drive(5, gnss_rate_hz=5.0, nlos=False, duration_s=40.0)
    stamps = np.array([e.stamp_ns for e in d.gnss])
    assert np.all(np.diff(stamps) == 200_000_000) and len(stamps) == 201
    spread, _ = _residuals(d)
    assert 2.4 < np.sqrt(np.mean(spread ** 2)) < 3.4


def test_full_drive_with_faults():
    # Timing of the whole drive: bench.emulation.
    d = make_emulated_drive(9, faults=4)
    assert len(d.gnss) > 200
    assert d.info['route_length_m'] == pytest.approx(CFG.route_length_m, abs=1.0)
    span_s = (d.truth.stamp_ns[-1] - d.truth.stamp_ns[0]) * 1e-9
    assert span_s == pytest.approx(d.info['duration_s'], abs=0.011)
    assert set(np.unique(np.count_nonzero(d.info['gnss_fault_m'], axis=1))) == {0, 4}
