"""Motion loss and dead-reckoning resets are integrity events (offline, nodes' motion path).

The motion reaches the filter as in fusion_node: imu_node's dead reckoning (``dead_reckon``)
through the epoch engine. Dead reckoning that stops for 20 s,
or restarts at its origin (a restarted imu_node), must never leave the flag OK while the
error exceeds the protection level, and the epochs without motion must be ERROR.
"""
import numpy as np
import pytest

from gnsscam_ros.core.filter import FilterConfig
from gnsscam_ros.core.motion import dead_reckon
from gnsscam_ros.core.types import ImuSeries, OdometrySeries
from gnsscam_ros.datasets.emulated.drive import make_emulated_drive
from gnsscam_ros.evaluation.runner import run_epochs

SECOND = 1_000_000_000
LOST = (50 * SECOND, 70 * SECOND)      # drive time of the fault, from the first epoch


@pytest.fixture(scope='module')
def drive():
    return make_emulated_drive(3, duration_s=110.0)


def series_from(drive, t0_ns):
    """The IMU and odometry samples at and after ``t0_ns``."""
    imu, odo = drive.imu, drive.odometry
    keep_i, keep_o = imu.stamp_ns >= t0_ns, odo.stamp_ns >= t0_ns
    return (ImuSeries(imu.stamp_ns[keep_i], imu.accel_mps2[keep_i], imu.gyro_rps[keep_i]),
            OdometrySeries(odo.stamp_ns[keep_o], odo.speed_mps[keep_o],
                           odo.yaw_rate_rps[keep_o], odo.speed_var[keep_o],
                           odo.yaw_rate_var[keep_o]))


def run_with_states(drive, states):
    """The offline run with these dead-reckoning states; also the engine's accumulator."""
    record, engine = run_epochs(drive, FilterConfig(alert_limit_m=25.0), 1, states=states)
    return record, engine.motion


def check_never_ok_beyond_the_level(record):
    diff = record.estimate_enu_m - record.truth_enu_m
    error = np.hypot(diff[:, 0], diff[:, 1])
    assert np.isfinite(record.protection_level_m).all()
    misleading = record.integrity_ok & (error > record.protection_level_m)
    assert not misleading.any(), np.flatnonzero(misleading)
    return error


@pytest.mark.slow
def test_dead_reckoning_lost_for_20_s(drive):
    start = drive.gnss[0].stamp_ns
    states = [s for s in dead_reckon(drive.imu, drive.odometry)
              if not start + LOST[0] < s.stamp_ns < start + LOST[1]]
    record, _ = run_with_states(drive, states)
    check_never_ok_beyond_the_level(record)
    table = record.epochs
    during = (table.stamp_ns > start + LOST[0]) & (table.stamp_ns <= start + LOST[1])
    assert during.sum() >= 15
    assert (table.integrity[during] == 'ERROR').all()
    assert all('motion unknown' in r for r in table.reason[during])
    # The level grows over the gap (a vehicle at up to max_speed_mps).
    pl = table.protection_level_m
    before = pl[(table.stamp_ns <= start + LOST[0])][-1]
    assert pl[during][-1] > 3.0 * before


@pytest.mark.slow
def test_restarted_dead_reckoning_is_detected_not_integrated(drive):
    start = drive.gnss[0].stamp_ns
    restart = start + LOST[0]
    first = [s for s in dead_reckon(drive.imu, drive.odometry) if s.stamp_ns < restart]
    second = dead_reckon(*series_from(drive, restart))        # begins again at (0, 0)
    assert second[0].x_m == 0.0 and abs(first[-1].x_m) > 100.0
    record, acc = run_with_states(drive, first + second)
    assert acc.resets == 1
    error = check_never_ok_beyond_the_level(record)
    table = record.epochs
    # The epoch whose interval holds the restart (the last state of the first run is
    # 0.1 s before it).
    first_after = np.flatnonzero(table.stamp_ns >= restart)[0]
    assert table.integrity[first_after] == 'ERROR'
    assert 'motion unknown' in table.reason[first_after]
    # The jump back to the origin was not taken as motion: the error stays small.
    assert error.max() < 30.0
