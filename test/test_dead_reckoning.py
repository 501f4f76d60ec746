"""Dead reckoning known answers (core, no rclpy): the one implementation imu_node and every
offline run share, held against an independent integration (``oracles``)."""
import math
from dataclasses import replace

import numpy as np
import pytest

from gnsscam_ros.core.motion import (ADDED, IMU, ODOMETRY, OUT_OF_ORDER, DeadReckoner,
                                     DeadReckoningConfig, DeadReckoningState,
                                     MotionAccumulator, dead_reckon,
                                     motion_between)
from gnsscam_ros.core.types import ImuSeries, OdometrySeries
from oracles import integrate_odometry

S = 1_000_000_000


def _odometry(t_s, speed, yaw_rate, var=(0.0025, 1e-4)):
    t_s = np.asarray(t_s, float)
    return OdometrySeries(stamp_ns=(t_s * S).astype(np.int64),
                          speed_mps=np.broadcast_to(speed, t_s.shape).astype(float),
                          yaw_rate_rps=np.broadcast_to(yaw_rate, t_s.shape).astype(float),
                          speed_var=np.full(t_s.shape, var[0]),
                          yaw_rate_var=np.full(t_s.shape, var[1]))


def test_dead_reckoning_constant_turn_is_a_circle():
    v, r = 10.0, 0.1                                  # radius 100 m
    t = np.arange(0, 10.0001, 0.1)
    states = dead_reckon(None, _odometry(t, v, r))
    end = states[-1]
    theta = r * 10.0
    # Steps of the arc length along the mid heading: the vertices lie on a circle whose
    # chord per step is the arc length, radius R' = R (dtheta / 2) / sin(dtheta / 2).
    half = r * 0.1 / 2
    radius = v / r * half / np.sin(half)
    assert end.x_m == pytest.approx(radius * np.sin(theta), rel=1e-12)
    assert end.y_m == pytest.approx(radius * (1 - np.cos(theta)), rel=1e-12)
    assert end.yaw_rad == pytest.approx(theta)
    # Variance: sigma^2 T dt per step = sigma^2 T^2 per sample, as integrate_odometry.
    assert end.distance_var_m2 == pytest.approx(0.0025 * 0.1 * 10.0)


def test_dead_reckoning_motion_equals_integrate_odometry():
    rng = np.random.default_rng(0)
    t = np.arange(0, 20.0001, 0.1)
    odo = _odometry(t, 8 + rng.normal(0, 1, t.size), rng.normal(0, 0.05, t.size))
    imu = ImuSeries(stamp_ns=(np.arange(0, 20.0001, 0.01) * S).astype(np.int64),
                    accel_mps2=rng.normal(0, 1, (2001, 3)), gyro_rps=rng.normal(0, 1, (2001, 3)))
    acc = MotionAccumulator()
    every = DeadReckoningConfig(output_period_s=0.0)
    for s in dead_reckon(imu, odo, every):            # odometry preferred for yaw
        acc.add(s)
    for t0, t1 in ((0.0, 1.0), (3.05, 7.3), (10.0, 20.0)):
        a = acc.increment(int(t0 * S), int(t1 * S))
        b = integrate_odometry(odo, int(t0 * S), int(t1 * S))
        assert a.distance_m == pytest.approx(b.distance_m, rel=1e-9)
        assert a.dyaw_rad == pytest.approx(b.dyaw_rad, rel=1e-9, abs=1e-12)
        assert a.dt_s == pytest.approx(b.dt_s)
    a = acc.increment(0, 10 * S)
    b = integrate_odometry(odo, 0, 10 * S)
    assert a.distance_var_m2 == pytest.approx(b.distance_var_m2, rel=1e-9)
    assert a.dyaw_var_rad2 == pytest.approx(b.dyaw_var_rad2, rel=1e-9)


def test_dead_reckoning_output_period_thins_the_states_on_a_stamp_grid():
    rng = np.random.default_rng(2)
    t = np.arange(201) / 10                       # stamps exact in ns: 10 Hz and 100 Hz
    odo = _odometry(t, 8 + rng.normal(0, 1, t.size), rng.normal(0, 0.05, t.size))
    odo = replace(odo, stamp_ns=np.arange(201, dtype=np.int64) * (S // 10))
    imu = ImuSeries(stamp_ns=np.arange(2001, dtype=np.int64) * (S // 100),
                    accel_mps2=rng.normal(0, 1, (2001, 3)), gyro_rps=rng.normal(0, 1, (2001, 3)))
    every = dead_reckon(imu, odo, DeadReckoningConfig(output_period_s=0.0))
    thinned = dead_reckon(imu, odo, DeadReckoningConfig(output_period_s=0.5))
    assert len(every) == 2001
    # The first state at or after each multiple of 0.5 s: the integration is the same,
    # only fewer states are emitted.
    assert [s.stamp_ns for s in thinned] == [int(k * 0.5 * S) for k in range(41)]
    by_stamp = {s.stamp_ns: s for s in every}
    assert all(s == by_stamp[s.stamp_ns] for s in thinned)
    coarse, fine = MotionAccumulator(), MotionAccumulator()
    for s in thinned:
        coarse.add(s)
    for s in every:
        fine.add(s)
    # Intervals on the grid: the same heading change and variances; the distance is the
    # chord of each 0.5 s segment instead of the sum of its 0.01 s chords (shorter by
    # ~dyaw^2 / 24 of it). Off the grid: the linear split of one segment on top.
    for t0, t1 in ((0.0, 1.0), (2.5, 17.0)):
        a = coarse.increment(int(t0 * S), int(t1 * S))
        b = fine.increment(int(t0 * S), int(t1 * S))
        assert a.distance_m == pytest.approx(b.distance_m, rel=1e-4)
        assert a.dyaw_rad == pytest.approx(b.dyaw_rad, rel=1e-9)
        assert a.distance_var_m2 == pytest.approx(b.distance_var_m2, rel=1e-9)
        assert a.dyaw_var_rad2 == pytest.approx(b.dyaw_var_rad2, rel=1e-9)
    a, b = coarse.increment(int(3.05 * S), int(7.3 * S)), fine.increment(int(3.05 * S),
                                                                         int(7.3 * S))
    assert a.distance_m == pytest.approx(b.distance_m, rel=1e-2)
    assert a.dyaw_rad == pytest.approx(b.dyaw_rad, abs=0.02)
    with pytest.raises(ValueError, match='output_period_s'):
        DeadReckoningConfig(output_period_s=-1.0)


def test_dead_reckoning_does_not_depend_on_stream_interleaving():
    rng = np.random.default_rng(1)
    t_odo = np.arange(0, 3.0001, 0.1)
    t_imu = np.arange(0, 3.0001, 0.01)
    odo = [(int(t * S), 5 + rng.normal(), rng.normal(0, 0.1)) for t in t_odo]
    imu = [(int(t * S), rng.normal(), rng.normal(0, 0.1)) for t in t_imu]
    cfg = DeadReckoningConfig(yaw_rate_source=IMU, output_period_s=0.0)   # every state
    a, b = DeadReckoner(cfg), DeadReckoner(cfg)
    out_a, out_b = [], []
    a.add_odometry(*odo[0])
    for s in imu:                                    # then all IMU, then the odometry
        a.add_imu(*s)
        out_a += a.advance({IMU, ODOMETRY})
    assert len(out_a) == 1                           # held at the odometry's newest stamp
    for s in odo[1:]:
        a.add_odometry(*s)
        out_a += a.advance({IMU, ODOMETRY})
    b.add_odometry(*odo[0])
    events = sorted([(s[0], 0, s) for s in odo[1:]] + [(s[0], 1, s) for s in imu])
    for _, kind, s in events:                        # in stamp order
        (b.add_odometry if kind == 0 else b.add_imu)(*s)
        out_b += b.advance({IMU, ODOMETRY})
    assert len(out_b) == len(t_imu)
    assert out_a == out_b


def test_dead_reckoning_imu_only_integrates_acceleration_and_refuses_bad_samples():
    dr = DeadReckoner()
    for k in range(101):                             # 1 m/s^2 for 1 s from rest
        dr.add_imu(k * S // 100, 1.0, 0.0)
        dr.advance()
    assert dr.state.speed_mps == pytest.approx(1.0)
    assert dr.state.x_m == pytest.approx(0.5, rel=1e-9)
    assert dr.state.distance_var_m2 > 0.0
    with pytest.raises(ValueError, match='not after'):
        dr.add_imu(50 * S // 100, 0.0, 0.0)
    with pytest.raises(ValueError, match='non-finite'):
        dr.add_odometry(2 * S, math.nan, 0.0)
    with pytest.raises(ValueError):
        DeadReckoningConfig(yaw_rate_source='compass')


def test_motion_between_inverts_a_step_and_accumulator_overlaps():
    s0 = DeadReckoningState(0, 1.0, 2.0, 3.1, 0, 0, 0, 0, 1.0, 0.1)
    s1 = DeadReckoningState(S, 1.0 + 2 * np.cos(3.2), 2.0 + 2 * np.sin(3.2), 3.3, 0, 0, 0, 0,
                            1.5, 0.3)
    m = motion_between(s0, s1)
    assert m.distance_m == pytest.approx(2.0) and m.dyaw_rad == pytest.approx(0.2)
    assert m.distance_var_m2 == pytest.approx(0.5) and m.dyaw_var_rad2 == pytest.approx(0.2)
    acc = MotionAccumulator()
    assert [acc.add(s0), acc.add(s1), acc.add(s0)] == [ADDED, ADDED, OUT_OF_ORDER]
    half = acc.increment(S // 4, 3 * S // 4)
    assert half.distance_m == pytest.approx(1.0) and half.dt_s == pytest.approx(0.5)
    assert half.unknown_s == 0.0
    # Beyond the newest state the motion is unknown, not a standstill.
    beyond = acc.increment(2 * S, 3 * S)
    assert beyond.distance_m == 0.0 and beyond.unknown_s == pytest.approx(1.0)
    assert acc.increment(S // 2, 2 * S).unknown_s == pytest.approx(1.0)
    with pytest.raises(ValueError):
        acc.increment(S, 0)
