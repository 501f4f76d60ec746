"""The epoch engine: readiness of an epoch, verdicts, and inputs in any arrival order."""
import math

import numpy as np
import pytest

from gnsscam_ros.core.engine import (CAMERA, DEAD_RECKONING, DROPPED_OLDEST, ERROR, NO_MATCH,
                                     OK, QUEUED, STALE, EpochEngine, InputTiming, best_match)
from gnsscam_ros.core.filter import UPDATED, FilterConfig
from gnsscam_ros.core.fusion import CameraMeasurement
from gnsscam_ros.core.motion import ADDED, OUT_OF_ORDER, RESET, dead_reckon
from gnsscam_ros.datasets.emulated.drive import make_emulated_drive
from gnsscam_ros.evaluation.runner import engine_reports

S = 1_000_000_000


@pytest.fixture(scope='module')
def drive():
    return make_emulated_drive(3, duration_s=25.0)


@pytest.fixture(scope='module')
def states(drive):
    return dead_reckon(drive.imu, drive.odometry)


def initialised_engine(drive, timing=None):
    engine = EpochEngine(FilterConfig(n_particles=200, n_posteriors=20),
                         rng=np.random.default_rng(1), timing=timing)
    engine.add_gnss(drive.gnss[0])
    (first,) = engine.ready_reports()           # the first fix needs no motion
    assert first.result.status == UPDATED
    return engine


@pytest.mark.slow
def test_dead_reckoning_wait_is_bounded_and_ends_when_it_stops(drive, states):
    engine = initialised_engine(drive)
    epoch = drive.gnss[1]
    for s in states:
        if s.stamp_ns < epoch.stamp_ns - S // 2:
            assert engine.add_dead_reckoning(s, now_s=100.0) == ADDED
    assert engine.add_gnss(epoch, now_s=100.0) == QUEUED
    # Running dead reckoning behind the epoch: wait, at most odometry_wait_s.
    assert engine.waiting_for(epoch.stamp_ns, 100.0, 100.1) == (DEAD_RECKONING,)
    assert engine.waiting_for(epoch.stamp_ns, 100.0, 100.25) == ()
    # Silent for longer than odometry_timeout_s: nothing to wait for.
    assert engine.waiting_for(epoch.stamp_ns, 101.5, 101.5) == ()
    (report,) = engine.ready_reports(now_s=100.3)
    assert report.late == (DEAD_RECKONING,) and engine.counts['dead_reckoning_late'] == 1
    # Half a second of the interval had no dead reckoning: unknown motion, never OK.
    assert report.result.motion_unknown_s > 0.4
    assert report.verdict.level != OK


def test_gnss_only_operation_does_not_wait_for_dead_reckoning(drive):
    engine = initialised_engine(drive)
    engine.add_gnss(drive.gnss[1], now_s=10.0)
    # Never any dead reckoning: its first states may still be on their way ...
    assert engine.waiting_for(drive.gnss[1].stamp_ns, 10.0, 10.1) == (DEAD_RECKONING,)
    # ... but GNSS flowing odometry_timeout_s without any is GNSS-only operation.
    engine.add_gnss(drive.gnss[2], now_s=12.0)
    engine._first_gnss_s = 10.0
    assert engine.waiting_for(drive.gnss[2].stamp_ns, 12.0, 12.0) == ()


def test_camera_wait_uses_the_frame_period_and_a_stopped_camera_is_not_waited_for(
        drive, states):
    t = drive.gnss[1].stamp_ns
    covering = [s for s in states if s.stamp_ns <= t + S // 10]     # motion is not waited for
    engine = initialised_engine(drive)
    # Images every 0.5 s; the newest 0.3 s before the epoch: none due, ready.
    for k in range(4):
        engine.add_camera(t - int((1.8 - 0.5 * k) * S), None)
    assert engine._camera_stamps[-1] == t - int(0.3 * S)
    assert engine.waiting_for(t, None, None) == ()
    # The newest 0.6 s before: one image is due, the epoch waits for it (bounded) ...
    engine = initialised_engine(drive)
    for s in covering:
        engine.add_dead_reckoning(s, now_s=5.0)
    for k in range(3):
        assert engine.add_camera(t - int((1.6 - 0.5 * k) * S), None) == NO_MATCH
    assert engine.waiting_for(t, 5.0, 5.1) == (CAMERA,)
    assert engine.waiting_for(t, 5.0, 5.3) == ()        # camera_wait_s = 0.2 s
    # ... unless the other inputs are camera_timeout_s past it: the camera stopped.
    engine.add_gnss(drive.gnss[3])
    assert engine.waiting_for(t, 5.0, 5.1) == ()


def test_gnss_queue_drops_the_oldest_and_refuses_out_of_order(drive):
    engine = initialised_engine(drive, InputTiming(gnss_queue_size=2))
    assert engine.add_gnss(drive.gnss[2], 1.0) == QUEUED
    assert engine.add_gnss(drive.gnss[1], 1.0) == OUT_OF_ORDER
    assert engine.add_gnss(drive.gnss[3], 1.0) == QUEUED
    assert engine.add_gnss(drive.gnss[4], 1.0) == DROPPED_OLDEST
    queued = [e.stamp_ns for e, _ in engine.queue]
    assert queued == [drive.gnss[3].stamp_ns, drive.gnss[4].stamp_ns]
    assert engine.counts['dropped_epochs'] == 1


@pytest.mark.slow
def test_reports_do_not_depend_on_when_later_inputs_arrive(drive, states):
    """Inputs interleaved in stamp order, or every input before any epoch runs: the same
    estimates bit for bit (an epoch only uses inputs stamped at or before it)."""
    config = FilterConfig(n_particles=300, n_posteriors=20)
    epochs = drive.gnss[:15]
    camera = [CameraMeasurement(int(e.stamp_ns - S // 3), np.array([5.0, -3.0, 0.0]), 1.0, k)
              for k, e in enumerate(epochs[2:], start=2)]
    a = EpochEngine(config, rng=np.random.default_rng(4),
                    timing=InputTiming(gnss_queue_size=None))
    interleaved = [(r.result.position_enu_m, r.verdict.protection_level_m)
                   for r in engine_reports(a, epochs, states, camera)]
    b = EpochEngine(config, rng=np.random.default_rng(4),
                    timing=InputTiming(gnss_queue_size=None))
    for s in states:
        b.add_dead_reckoning(s)
    for m in camera:
        b.add_camera(m.stamp_ns, m)
    for e in epochs:
        b.add_gnss(e)
    all_first = [(r.result.position_enu_m, r.verdict.protection_level_m)
                 for r in b.ready_reports(flush=True)]
    assert len(interleaved) == len(all_first) == len(epochs)
    for (pa, la), (pb, lb) in zip(interleaved, all_first):
        np.testing.assert_array_equal(pa, pb)
        assert la == lb or (math.isnan(la) and math.isnan(lb))
    assert any(r.camera_alpha is not None for r in [a.filter.last_result])


def test_verdicts_and_a_restart_of_the_dead_reckoning(drive, states):
    engine = initialised_engine(drive)
    stale = engine.stale_verdict(123, 'no GNSS')
    assert stale.level == STALE and stale.epoch_status is None
    assert stale.epoch_stamp_ns == drive.gnss[0].stamp_ns and math.isnan(stale.risk_bound)
    for s in states[:40]:
        engine.add_dead_reckoning(s)
    restarted = states[5].__class__(**{**states[40].__dict__, 'x_m': 0.0, 'y_m': 0.0,
                                       'distance_var_m2': 0.0, 'yaw_var_rad2': 0.0})
    assert engine.add_dead_reckoning(restarted) == RESET
    assert engine.motion.resets == 1
    engine.add_gnss(drive.gnss[1])
    (report,) = engine.ready_reports(flush=True)
    verdict = report.verdict
    assert verdict.level in (OK, ERROR) and verdict.epoch_status == UPDATED
    assert verdict.details['dead_reckoning_resets'] == 1
    assert set(verdict.risk_bounds_by_limit) == set(
        float(v) for v in engine.config.alert_limits_m[1:])


def test_best_match_is_the_first_of_the_top_k():
    assert best_match(5, np.zeros((0, 3)), np.zeros(0), 0) is None
    m = best_match(5, np.array([[1.0, 2.0, 3.0], [9.0, 9.0, 9.0]]), np.array([0.9, 0.5]), 7)
    assert m.stamp_ns == 5 and m.frame_id == 7 and m.score == 0.9
    np.testing.assert_array_equal(m.position_enu_m, [1.0, 2.0, 3.0])
