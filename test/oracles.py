"""Independent reference implementations the tests hold the package's code against."""
import numpy as np

from gnsscam_ros.core.particles import MotionIncrement
from gnsscam_ros.core.types import OdometrySeries


def integrate_odometry(odom: OdometrySeries, t0_ns: int, t1_ns: int) -> MotionIncrement:
    """Integrate speed and yaw rate over ``[t0_ns, t1_ns]`` (trapezoidal rule).

    Samples are linearly interpolated at the interval ends; outside the recorded span the
    nearest sample is held. Variances add up as for white noise on each sample period.

    Args:
        odom: Odometry series (stamps strictly increasing).
        t0_ns: Interval start [ns].
        t1_ns: Interval end [ns], not before ``t0_ns``.

    Returns:
        The motion increment (distance along the heading and heading change).
    """
    if t1_ns < t0_ns:
        raise ValueError(f'interval ends before it starts: {t0_ns} > {t1_ns}')
    dt_s = (t1_ns - t0_ns) * 1e-9
    if len(odom) == 0 or dt_s == 0.0:
        return MotionIncrement.stationary(dt_s)
    inside = (odom.stamp_ns > t0_ns) & (odom.stamp_ns < t1_ns)
    t = np.concatenate(([t0_ns], odom.stamp_ns[inside], [t1_ns])).astype(float) * 1e-9
    stamps_s = odom.stamp_ns.astype(float) * 1e-9
    speed = np.interp(t, stamps_s, odom.speed_mps)
    yaw_rate = np.interp(t, stamps_s, odom.yaw_rate_rps)
    steps = np.diff(t)
    distance = float(np.sum(0.5 * (speed[1:] + speed[:-1]) * steps))
    dyaw = float(np.sum(0.5 * (yaw_rate[1:] + yaw_rate[:-1]) * steps))
    speed_var = float(np.interp(t0_ns * 1e-9, stamps_s, odom.speed_var))
    yaw_var = float(np.interp(t0_ns * 1e-9, stamps_s, odom.yaw_rate_var))
    # Each sample's error persists for its own period: var = sigma^2 * sum(step^2)
    # (white noise per sample), an honest figure for the odometry's own quoted variances.
    sum_sq = float(np.sum(steps ** 2))
    return MotionIncrement(dt_s=dt_s, distance_m=distance, dyaw_rad=dyaw,
                           distance_var_m2=speed_var * sum_sq, dyaw_var_rad2=yaw_var * sum_sq)
