"""Data variations of a drive (datasets.variants, the ramp faults of datasets.faults):
each does what it says and nothing else, and leaves the drive it was given as it was."""
import dataclasses

import numpy as np
import pytest

from gnsscam_ros.core.types import GLONASS, GPS
from gnsscam_ros.datasets.errors import DatasetError
from gnsscam_ros.datasets.faults import FaultEpisodes, inject_pseudorange_faults
from gnsscam_ros.datasets.variants import (decimate_gnss, drive_digest, drop_cn0,
                                           gnss_rate_hz, gnss_stamps_ns, leave_troposphere,
                                           scale_variances, select_systems, set_variances,
                                           shift_cn0, start_after)

S = 1_000_000_000


def assert_same_except(a, b, changed=()):
    """Two epochs equal in every field but ``changed``."""
    for f in dataclasses.fields(a):
        if f.name not in changed:
            np.testing.assert_array_equal(getattr(a, f.name), getattr(b, f.name), f.name)


def assert_same_series(a, b):
    for x, y in zip(dataclasses.astuple(a), dataclasses.astuple(b)):
        np.testing.assert_array_equal(x, y)


@pytest.fixture
def drive(smartloc_excerpt):
    return smartloc_excerpt


@pytest.fixture
def untouched(drive):
    """The digest of the drive before a test; checked unchanged after it."""
    before = drive_digest(drive)
    yield
    assert drive_digest(drive) == before


@pytest.mark.parametrize('factor', [0.25, 0.5, 2.0, 4.0])
def test_scale_variances_multiplies_every_stated_variance(drive, untouched, factor):
    out = scale_variances(drive, factor)
    assert len(out.gnss) == len(drive.gnss)
    for a, b in zip(drive.gnss, out.gnss):
        np.testing.assert_allclose(b.var_m2, a.var_m2 * factor, rtol=1e-15)
        assert_same_except(a, b, ('var_m2',))
    assert out.odometry is drive.odometry and out.truth is drive.truth
    assert out.info['variants'][-1] == {'kind': 'scale_variances', 'factor': factor}


@pytest.mark.parametrize('offset', [-8.0, 8.0])
def test_shift_cn0_offsets_every_reported_cn0_and_keeps_unknown_ones_unknown(
        drive, untouched, offset):
    first = drive.gnss[0]
    cn0 = first.cn0_dbhz.copy()
    cn0[0] = np.nan                       # one satellite without C/N0
    drive = dataclasses.replace(drive, gnss=[dataclasses.replace(first, cn0_dbhz=cn0),
                                             *drive.gnss[1:]])
    out = shift_cn0(drive, offset)
    assert np.isnan(out.gnss[0].cn0_dbhz[0])
    np.testing.assert_array_equal(out.gnss[0].cn0_dbhz[1:], cn0[1:] + offset)
    for a, b in zip(drive.gnss[1:], out.gnss[1:]):
        np.testing.assert_array_equal(b.cn0_dbhz, a.cn0_dbhz + offset)
        assert_same_except(a, b, ('cn0_dbhz',))
    assert out.info['variants'][-1] == {'kind': 'shift_cn0', 'offset_dbhz': offset}
    with pytest.raises(ValueError, match='finite'):
        shift_cn0(drive, float('nan'))


def test_drop_cn0_leaves_no_cn0_and_nothing_else_changed(drive, untouched):
    assert np.isfinite(np.concatenate([e.cn0_dbhz for e in drive.gnss])).all()
    out = drop_cn0(drive)
    for a, b in zip(drive.gnss, out.gnss):
        assert b.cn0_dbhz.shape == a.cn0_dbhz.shape and np.isnan(b.cn0_dbhz).all()
        assert_same_except(a, b, ('cn0_dbhz',))
    assert out.info['variants'][-1] == {'kind': 'drop_cn0'}


def test_leave_troposphere_adds_the_mapped_slant_delay_and_nothing_else(drive, untouched):
    out = leave_troposphere(drive, 52.5, 0.0)
    for a, b in zip(drive.gnss, out.gnss):
        assert_same_except(a, b, ('pr_m',))
        delay = b.pr_m - a.pr_m
        # Sea level, standard atmosphere: 2.3 m hydrostatic and 0.1 m wet at the zenith;
        # the Black-Eisner mapping is 1 / sin(el) within 1 % above 20 deg.
        high = a.elevation_deg > 20.0
        np.testing.assert_allclose(delay[high] * np.sin(np.radians(a.elevation_deg[high])),
                                   2.4, atol=0.1)
        assert np.all(np.diff(delay[np.argsort(a.elevation_deg)]) <= 0)
    assert out.info['variants'][-1] == {'kind': 'leave_troposphere', 'lat_deg': 52.5,
                                        'height_m': 0.0}
    # At 2 km the air above is thinner: a fifth less delay.
    at_2km = leave_troposphere(drive, 52.5, 2000.0)
    ratio = ((at_2km.gnss[0].pr_m - drive.gnss[0].pr_m)
             / (out.gnss[0].pr_m - drive.gnss[0].pr_m))
    assert np.all((0.7 < ratio) & (ratio < 0.85))


def test_leave_troposphere_refuses_an_unknown_elevation_or_place(drive):
    first = drive.gnss[0]
    elevation = first.elevation_deg.copy()
    elevation[1] = np.nan
    blind = dataclasses.replace(drive, gnss=[dataclasses.replace(first,
                                                                 elevation_deg=elevation)])
    with pytest.raises(DatasetError, match='elevation'):
        leave_troposphere(blind, 52.5, 0.0)
    with pytest.raises(ValueError, match='finite'):
        leave_troposphere(drive, float('nan'), 0.0)


@pytest.mark.parametrize('var_m2', [25.0, 4.0])
def test_set_variances_gives_every_pseudorange_the_constant(drive, untouched, var_m2):
    out = set_variances(drive, var_m2)
    stated = np.concatenate([e.var_m2 for e in drive.gnss])
    assert np.ptp(stated) > 0                    # the file states different variances
    for a, b in zip(drive.gnss, out.gnss):
        assert np.all(b.var_m2 == var_m2) and b.var_m2.shape == a.var_m2.shape
        assert_same_except(a, b, ('var_m2',))


@pytest.mark.parametrize('bad', [0.0, -1.0, float('nan'), float('inf')])
def test_variances_refuse_a_bad_value(drive, bad):
    with pytest.raises(ValueError):
        scale_variances(drive, bad)
    with pytest.raises(ValueError):
        set_variances(drive, bad)


def test_the_excerpt_is_a_5_hz_file(drive):
    """What the decimation tests assume: epochs 0.2 s apart (0.3 s now and then)."""
    dt = np.diff(gnss_stamps_ns(drive)) / S
    assert np.median(dt) == pytest.approx(0.2, abs=1e-3)
    assert 4.5 < gnss_rate_hz(drive) <= 5.0


@pytest.mark.parametrize('rate_hz', [1.0, 2.0])
def test_decimate_gnss_keeps_epochs_at_the_requested_rate(drive, untouched, rate_hz):
    out = decimate_gnss(drive, rate_hz)
    stamps = gnss_stamps_ns(out)
    native_s = float(np.median(np.diff(gnss_stamps_ns(drive)))) / S
    dt = np.diff(stamps) / S
    assert gnss_rate_hz(out) == pytest.approx(rate_hz, rel=0.05)
    assert dt.min() >= 1.0 / rate_hz - native_s / 2 - 1e-6
    assert dt.max() <= 1.0 / rate_hz + native_s + 1e-6
    # A subset of the file's epochs, each unchanged, the first one kept.
    by_stamp = {e.stamp_ns: e for e in drive.gnss}
    assert stamps[0] == drive.gnss[0].stamp_ns
    for e in out.gnss:
        assert_same_except(by_stamp[e.stamp_ns], e)
    assert_same_series(out.odometry, drive.odometry)     # odometry at its own rate
    record = out.info['variants'][-1]
    assert record['epochs_kept'] == len(out.gnss) < len(drive.gnss)
    assert record['rate_hz_after'] == pytest.approx(rate_hz, rel=0.05)


def test_decimation_at_or_above_the_file_rate_keeps_every_epoch(drive, untouched):
    for rate in (5.0, 10.0):
        out = decimate_gnss(drive, rate)
        assert [e.stamp_ns for e in out.gnss] == [e.stamp_ns for e in drive.gnss]
        assert drive_digest(out) == drive_digest(drive)
    with pytest.raises(ValueError):
        decimate_gnss(drive, 0.0)


@pytest.mark.parametrize('system', [GPS, GLONASS])
def test_select_systems_keeps_one_system_and_drops_epochs_with_too_few(drive, untouched,
                                                                       system):
    out = select_systems(drive, [system], min_satellites=5)
    counts = np.array([np.sum(e.system == system) for e in drive.gnss])
    assert len(out.gnss) == int(np.sum(counts >= 5)) > 0
    by_stamp = {e.stamp_ns: e for e in drive.gnss}
    for e in out.gnss:
        assert np.all(e.system == system) and e.n_sv >= 5
        original = by_stamp[e.stamp_ns]
        assert_same_except(original.subset(original.system == system), e)
    record = out.info['variants'][-1]
    assert record['epochs_kept'] == len(out.gnss)
    assert record['epochs_dropped'] == len(drive.gnss) - len(out.gnss)
    assert_same_series(out.odometry, drive.odometry)


def test_select_systems_with_more_satellites_than_any_epoch_has_refuses(drive):
    with pytest.raises(DatasetError, match='leaves no GNSS epoch'):
        select_systems(drive, [GLONASS], min_satellites=64)
    with pytest.raises(ValueError):
        select_systems(drive, [], min_satellites=5)


@pytest.mark.parametrize('start_s', [10.0, 30.0])
def test_start_after_drops_what_came_before_and_keeps_the_truth(drive, untouched, start_s):
    out = start_after(drive, start_s)
    t_start = drive.gnss[0].stamp_ns + int(start_s * S)
    assert out.gnss[0].stamp_ns >= t_start
    assert out.gnss[0].stamp_ns - t_start < S          # nothing after the start dropped
    assert len(out.gnss) == sum(e.stamp_ns >= t_start for e in drive.gnss)
    assert out.odometry.stamp_ns[0] >= t_start
    assert len(out.odometry) == int(np.sum(drive.odometry.stamp_ns >= t_start))
    assert out.truth is drive.truth                     # scoring only: kept whole


def test_start_zero_changes_no_data_and_a_late_start_refuses(drive):
    assert drive_digest(start_after(drive, 0.0)) == drive_digest(drive)
    with pytest.raises(DatasetError, match='leaves no GNSS epoch'):
        start_after(drive, 3600.0)
    with pytest.raises(ValueError):
        start_after(drive, -1.0)


def test_digest_names_the_content(drive):
    copy = dataclasses.replace(drive, gnss=[dataclasses.replace(e) for e in drive.gnss])
    assert drive_digest(copy) == drive_digest(drive)
    first = drive.gnss[0]
    changed = [dataclasses.replace(first, pr_m=first.pr_m + 1e-3), *drive.gnss[1:]]
    assert drive_digest(dataclasses.replace(drive, gnss=changed)) != drive_digest(drive)


def test_ramp_faults_grow_linearly_over_the_step_faults_episodes(drive):
    spec = FaultEpisodes(episodes=2, satellites=(1, 2), bias_m=(30.0, 100.0),
                         duration_s=(20.0, 40.0))
    step = inject_pseudorange_faults(drive, 7, spec)
    ramp = inject_pseudorange_faults(drive, 7, dataclasses.replace(spec, profile='ramp'))
    assert [dict(r, profile=None) for r in step.info['injected_faults']] == \
        [dict(r, profile=None) for r in ramp.info['injected_faults']]
    for a, s, r in zip(drive.gnss, step.gnss, ramp.gnss):
        step_add, ramp_add = s.pr_m - a.pr_m, r.pr_m - a.pr_m
        assert np.all(np.abs(ramp_add) <= np.abs(step_add) + 1e-6)
        assert np.all(np.sign(ramp_add[ramp_add != 0]) == np.sign(step_add[ramp_add != 0]))
    # One satellite of the first episode: its bias is ~0 at the start, full at the end,
    # and linear in between (no other episode overlaps it in this draw).
    episode = ramp.info['injected_faults'][0]
    key = tuple(episode['satellites'][0])
    start, end = episode['start_ns'], episode['start_ns'] + episode['duration_s'] * S
    t, added = [], []
    for a, r in zip(drive.gnss, ramp.gnss):
        hit = [i for i, k in enumerate(zip(a.system, a.sv_id)) if tuple(k) == key]
        if hit and start <= a.stamp_ns < end:
            t.append((a.stamp_ns - start) / (end - start))
            added.append(r.pr_m[hit[0]] - a.pr_m[hit[0]])
    assert len(t) > 20
    np.testing.assert_allclose(added, np.array(t) * episode['bias_m'][0], atol=1e-6)
    with pytest.raises(ValueError, match='profile'):
        FaultEpisodes(profile='sine')
