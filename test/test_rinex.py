"""RINEX observations + broadcast navigation -> corrected epochs (core.ephemeris,
core.corrections, core.preprocess, datasets.rinex*), on the fixtures of test/data/rinex/.

Known answers: broadcast orbits and clocks against the CODE precise products; snapshot
fixes against the stations' published coordinates; a GLONASS state integration against
scipy's adaptive integrator of the same equations; a BeiDou GEO stays over one spot.
Bad input: truncated and corrupt files, navigation of another day, no usable satellite:
one line naming the file (and line), exit code 3, nothing written.
"""
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from gnsscam_ros.bags import convert_cli
from gnsscam_ros.core import ephemeris
from gnsscam_ros.core.frames import LocalFrame
from gnsscam_ros.core.gnss_checks import residual_ratio
from gnsscam_ros.core.preprocess import Preprocessor
from gnsscam_ros.core.snapshot import solve_snapshot
from gnsscam_ros.core.types import BEIDOU, GALILEO, GLONASS, GPS
from gnsscam_ros.datasets.errors import DatasetError
from gnsscam_ros.datasets.rinex import read_navigation, read_observations
from gnsscam_ros.datasets.rinex_drive import load_rinex
from gnsscam_ros.evaluation import cli as eval_cli
from gnsscam_ros.evaluation.orbits import compare

DATA = Path(__file__).resolve().parent / 'data' / 'rinex'
SLAC_OBS = DATA / 'slac1180.21o'
SLAC_NAV = [DATA / 'brdc1180.21n']
# Monument of the header comments (37.416517 N, -122.204262 E, 63.696 m) in ECEF.
SLAC_ECEF = np.array([-2703115.921, -4291767.208, 3854247.906])
NYA1_OBS = DATA / 'NYA100NOR_S_20241240000_01D_30S_MO.crx.gz'
NYA1_NAV = [DATA / f'NYA100NOR_S_20241240000_01D_{s}.rnx.gz' for s in ('GN', 'EN', 'CN')]
NYA1_ECEF = np.array([1202433.613, 252632.407, 6237772.780])       # IGS20
PDEL_OBS, PDEL_NAV = DATA / 'pdel0010.21o', [DATA / 'cbw10010.21n.gz']


def wls_errors(drive, station, systems=None):
    """(n, 3) ENU errors of the snapshot fixes of a drive's epochs [m]."""
    frame = LocalFrame.from_ecef(station)
    out = []
    for epoch in drive.gnss:
        if systems is not None:
            epoch = epoch.subset(np.isin(epoch.system, systems))
        if epoch.n_sv >= 4 + np.unique(epoch.system).size:
            out.append(frame.ecef_to_enu(solve_snapshot(epoch).ecef_m))
    return np.array(out)


def test_broadcast_gps_orbits_and_clocks_match_precise_products():
    result = compare(SLAC_NAV, DATA / 'COD0MGXFIN_20211180000_01D_05M_ORB.SP3',
                     DATA / 'COD0MGXFIN_20211180000_01D_30S_CLK.CLK')
    assert result['orbit_samples'] >= 4 * 20 and result['clock_samples'] >= 4 * 20
    assert result['orbit_3d_rms_m'] <= 2.0
    assert result['clock_rms_m'] <= 3.0


@pytest.mark.parametrize('station, obs, nav, systems', [
    ('slac', SLAC_OBS, SLAC_NAV, (GPS,)),
    ('nya1', NYA1_OBS, NYA1_NAV, (GPS,)),
    ('nya1', NYA1_OBS, NYA1_NAV, None)])
def test_snapshot_fix_from_rinex_matches_published_coordinates(station, obs, nav, systems):
    truth = SLAC_ECEF if station == 'slac' else NYA1_ECEF
    drive = load_rinex(obs, nav, station_ecef_m=truth)
    err = wls_errors(drive, truth, systems)
    assert len(err) == len(drive.gnss) >= 4
    assert np.sqrt(np.mean(err[:, 0] ** 2 + err[:, 1] ** 2)) <= 3.0
    assert np.sqrt(np.mean(err[:, 2] ** 2)) <= 6.0
    if systems is None:
        used = np.concatenate([e.system for e in drive.gnss])
        assert {GPS, GALILEO, BEIDOU} <= set(used.tolist())


def test_skipped_satellites_are_counted_by_reason():
    obs = read_observations(SLAC_OBS)
    pre = Preprocessor(read_navigation(SLAC_NAV))
    for raw in obs.epochs:
        result = pre.process(raw)
        # GLONASS and Galileo are observed, the navigation is GPS only.
        n_other = int(np.isin(raw.system, (GLONASS, GALILEO)).sum())
        assert result.skipped.get('no_nav', 0) >= n_other > 0
        assert result.epoch.n_sv + sum(result.skipped.values()) == raw.system.size
        assert set(result.epoch.system.tolist()) == {GPS}
        assert np.all(result.epoch.elevation_deg >= 10.0)
        # Satellite positions at transmission, not rotated: GPS orbit radii 26,560 km +- e.
        radius = np.linalg.norm(result.epoch.sv_pos_ecef_m, axis=1)
        assert np.all((radius > 2.55e7) & (radius < 2.75e7))


def test_glonass_integration_matches_adaptive_integrator():
    state = np.array([[1.2e7, -1.8e7, 1.0e7, 1.5e3, 1.5e3, 2.2e3]])
    eph = ephemeris.GlonassEphemerides(
        prn=np.array([1]), toe_s=np.array([0.0]), pos_m=state[:, :3], vel_mps=state[:, 3:],
        acc_mps2=np.array([[1e-6, -2e-6, 3e-6]]), tau_n_s=np.zeros(1), gamma_n=np.zeros(1),
        freq_channel=np.zeros(1), healthy=np.array([True]))
    t = 900.0       # 15 min: the largest |t - tb| of a 30 min update interval
    mine, _ = eph.position(np.array([0]), np.array([t]))

    def rhs(_, y):
        return ephemeris._glonass_derivative(y[None, :], eph.acc_mps2)[0]
    ref = solve_ivp(rhs, (0.0, t), state[0], rtol=1e-12, atol=1e-6).y[:3, -1]
    assert np.linalg.norm(mine[0] - ref) < 0.05
    back, _ = eph.position(np.array([0]), np.array([-t]))
    assert np.linalg.norm(back[0] - state[0, :3]) > 1e6       # it moved


def geo_record(prn: int) -> ephemeris.KeplerEphemerides:
    """A BeiDou record on a geostationary orbit: mean motion = Earth rotation, elements in
    the GEO reference frame (inclined by -5 deg about x, ICD 5.2.4.12)."""
    gm, omega_e = ephemeris.GM_M3PS2[BEIDOU], ephemeris.OMEGA_E_RPS[BEIDOU]
    one, zero = np.ones(1), np.zeros(1)
    return ephemeris.KeplerEphemerides(
        system=BEIDOU, prn=np.array([prn]), toe_s=zero, toe_sow_s=zero, toc_s=zero,
        af0_s=zero, af1=zero, af2_per_s=zero, group_delay_s=zero, healthy=np.array([True]),
        sqrt_a=one * (gm / omega_e ** 2) ** (1.0 / 6.0), ecc=zero, i0=one * np.radians(-5.0),
        idot=zero, omega0=zero, omega_dot=zero, omega=zero, m0=zero, delta_n=zero,
        cuc=zero, cus=zero, crc=zero, crs=zero, cic=zero, cis=zero)


def test_beidou_geo_rotation_gives_a_fixed_equatorial_point():
    geo = geo_record(3)
    t = np.array([0.0, 3600.0, 6 * 3600.0])
    p, _ = geo.position(np.zeros(3, dtype=int), t)
    assert np.allclose(np.linalg.norm(p, axis=1), 42.164e6, rtol=1e-3)
    assert np.all(np.abs(p[:, 2]) < 1.0)                       # equatorial
    assert np.linalg.norm(p - p[0], axis=1).max() < 1.0        # fixed over the Earth
    # The same elements read as a MEO/IGSO satellite give a 5 deg inclined orbit.
    meo, _ = geo_record(30).position(np.zeros(3, dtype=int), t)
    assert np.abs(meo[:, 2]).max() > 1e6


def test_no_usable_satellites_one_line_and_exit_code(tmp_path, capsys):
    with pytest.raises(DatasetError, match=str(PDEL_OBS)):
        load_rinex(PDEL_OBS, PDEL_NAV)
    out = tmp_path / 'x.json'
    code = eval_cli.main(['rinex', '--obs', str(PDEL_OBS), '--nav', str(PDEL_NAV[0]),
                          '--station-ecef', '4551595.8776', '-2186892.8650', '3883411.0240',
                          '--json', str(out), '--quiet'])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == eval_cli.EXIT_INPUT == 3
    assert len(err) == 1 and 'usable satellites' in err[0] and 'stale_nav' in err[0]
    assert not out.exists()


def test_navigation_of_another_day(tmp_path, capsys):
    bag = tmp_path / 'bag'
    code = convert_cli.main(['rinex', '--obs', str(SLAC_OBS), '--nav', str(NYA1_NAV[0]),
                             '--out', str(bag), '--quiet'])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == convert_cli.EXIT_INPUT
    assert len(err) == 1 and 'another day' in err[0] and NYA1_NAV[0].name in err[0]
    assert not bag.exists() and list(tmp_path.iterdir()) == []


def test_truncated_observation_file_names_the_line(tmp_path):
    lines = SLAC_OBS.read_text().splitlines(keepends=True)
    cut = tmp_path / 'cut.21o'
    cut.write_text(''.join(lines[:-3]))
    with pytest.raises(DatasetError, match=r'cut\.21o:\d+: .*truncated'):
        read_observations(cut)
    text = NYA1_OBS.read_bytes()
    broken = tmp_path / 'broken.crx.gz'
    broken.write_bytes(text[:len(text) // 2])
    with pytest.raises(DatasetError, match='broken.crx.gz: corrupt or truncated gzip'):
        read_observations(broken)


def test_corrupt_navigation_number_names_the_line(tmp_path):
    lines = SLAC_NAV[0].read_text().splitlines(keepends=True)
    header_end = next(i for i, line in enumerate(lines) if 'END OF HEADER' in line)
    target = header_end + 3
    lines[target] = lines[target][:5] + 'x.xxxxxxxxxxxD+00' + lines[target][22:]
    bad = tmp_path / 'bad.21n'
    bad.write_text(''.join(lines))
    with pytest.raises(DatasetError, match=rf'bad\.21n:{target + 1}: .* not a number'):
        read_navigation([bad])
    short = tmp_path / 'short.21n'
    short.write_text(''.join(lines[:header_end + 5]))
    with pytest.raises(DatasetError, match=r'short\.21n:\d+: .*truncated'):
        read_navigation([short])


def test_residual_ratio_flags_understated_variances():
    rng = np.random.default_rng(3)
    residual = rng.normal(0.0, 3.0, 40)
    assert 0.6 < residual_ratio(residual, np.full(40, 9.0)) < 1.6
    assert residual_ratio(residual, np.full(40, 0.01)) > 5.0


@pytest.mark.slow
def test_convert_rinex_static_bag(tmp_path, capsys):
    bag = tmp_path / 'bag'
    code = convert_cli.main(['rinex', '--obs', str(NYA1_OBS)]
                            + sum((['--nav', str(p)] for p in NYA1_NAV), [])
                            + ['--static', '--station-ecef', *map(str, NYA1_ECEF),
                               '--out', str(bag)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert 'satellites skipped' in captured.err
    for topic in ('/gnss/pseudoranges', '/odom/twist', '/ground_truth/pose', '/dataset/info'):
        assert topic in captured.out
