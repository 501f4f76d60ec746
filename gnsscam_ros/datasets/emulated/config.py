"""Parameters and random streams of the emulated urban drive.

Everything in the emulated drive is deterministic per seed. Each ingredient (city, route,
IMU, GNSS, faults, camera, ...) draws from its own independent random stream
(:func:`stream_rng`), so that changing one option (e.g. the number of faulty satellites)
leaves the others untouched. :class:`EmulationConfig` holds every physical parameter.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Independent random streams, one per ingredient. Append new names at the END only: the
# position in this tuple selects the SeedSequence child, so existing streams stay unchanged.
STREAMS = ('city', 'route', 'time', 'imu', 'odometry', 'constellation', 'clock', 'noise',
           'nlos', 'faults', 'camera')


def stream_rng(seed: int, name: str) -> np.random.Generator:
    """The independent random generator of one ingredient of the drive of ``seed``.

    Args:
        seed: Drive seed.
        name: One of :data:`STREAMS` (``'camera'`` is reserved for the camera stream).

    Returns:
        A fresh generator; calling twice gives identical sequences.
    """
    child = np.random.SeedSequence(int(seed)).spawn(len(STREAMS))[STREAMS.index(name)]
    return np.random.default_rng(child)


@dataclass(frozen=True)
class EmulationConfig:
    """Every physical parameter of the emulated drive, with its default.

    Attributes:
        origin_llh: (lat_deg, lon_deg, alt_m) of the ENU origin (Frankfurt city centre).
        route_length_m: Length of the driven path [m].
        antenna_height_m: Height of the truth point (GNSS antenna = IMU) above ground [m].
        lane_offset_m: Lane centre to the right of the street centre line [m].
        turn_radius_m: Radius of the turn arcs at intersections [m].
        cruise_speed_mps: (min, max) speed limit drawn per street segment [m/s].
        turn_speed_mps: Speed limit in turns [m/s].
        accel_mps2: Maximum acceleration [m/s^2].
        decel_mps2: Maximum braking deceleration [m/s^2].
        stop_prob: Probability of stopping at an intersection (traffic light).
        stop_duration_s: (min, max) uniform dwell time of a stop [s].
        standstill_s: Standstill at the start and at the end of the drive [s].
        smoothing_s: Std of the Gaussian kernel smoothing the distance-time profile [s].
        imu_rate_hz: IMU and truth rate [Hz].
        odom_rate_hz: Odometry rate [Hz] (must divide ``imu_rate_hz``).
        accel_noise_mps2: Accelerometer white noise std per sample [m/s^2].
        gyro_noise_rps: Gyro white noise std per sample [rad/s].
        accel_bias_mps2: Std of the constant accelerometer bias per axis [m/s^2].
        gyro_bias_rps: Std of the constant gyro bias per axis [rad/s].
        odom_speed_std_mps: Wheel speed noise std [m/s].
        odom_yaw_rate_std_rps: Odometry yaw-rate noise std [rad/s].
        n_sv: Satellites per GNSS epoch.
        max_gps: At most this many of them are GPS (the rest GLONASS).
        elevation_mask_deg: Elevation mask [deg].
        pr_var_m2: Pseudorange white-noise variance [m^2].
        clock_bias0_m: Initial receiver clock bias ~ U(-x, x) [m].
        clock_drift0_mps: Initial clock drift ~ U(-x, x) [m/s].
        clock_bias_rw_m: Clock-bias random walk density [m/sqrt(s)].
        clock_drift_rw_mps: Clock-drift random walk density [m/s/sqrt(s)].
        isb_std_m: Std of the constant GLONASS-minus-GPS inter-system bias [m].
        nlos_range_m: (min, max) of the NLOS excess delay [m].
        nlos_corr_time_s: Correlation time of the NLOS delay of one satellite [s].
        nlos_cn0_drop_db: (min, max) uniform C/N0 loss of a blocked satellite [dB].
        fault_free_start_s: No fault before this time (filter initialisation) [s].
        fault_episode_s: (min, max) uniform duration of a fault episode [s].
        fault_sigma_frac: Std of the fault magnitude as a fraction of ``bias_m``.
        fault_clip_m: (min, max) clip of the fault magnitude [m] (paper: 20-200 m).
    """

    origin_llh: tuple[float, float, float] = (50.1109, 8.6821, 110.0)
    route_length_m: float = 2300.0
    antenna_height_m: float = 1.8
    lane_offset_m: float = 3.0
    turn_radius_m: float = 10.0
    cruise_speed_mps: tuple[float, float] = (8.0, 14.0)
    turn_speed_mps: float = 5.0
    accel_mps2: float = 1.5
    decel_mps2: float = 2.0
    stop_prob: float = 0.3
    stop_duration_s: tuple[float, float] = (3.0, 20.0)
    standstill_s: float = 3.0
    smoothing_s: float = 0.5
    imu_rate_hz: float = 100.0
    odom_rate_hz: float = 10.0
    accel_noise_mps2: float = 0.05
    gyro_noise_rps: float = 2e-3
    accel_bias_mps2: float = 0.05
    gyro_bias_rps: float = 1e-3
    odom_speed_std_mps: float = 0.05
    odom_yaw_rate_std_rps: float = 0.01
    n_sv: int = 12
    max_gps: int = 8
    elevation_mask_deg: float = 10.0
    pr_var_m2: float = 10.0
    clock_bias0_m: float = 3.0e5
    clock_drift0_mps: float = 50.0
    clock_bias_rw_m: float = 0.3
    clock_drift_rw_mps: float = 0.05
    isb_std_m: float = 15.0
    nlos_range_m: tuple[float, float] = (5.0, 60.0)
    nlos_corr_time_s: float = 30.0
    nlos_cn0_drop_db: tuple[float, float] = (6.0, 14.0)
    fault_free_start_s: float = 10.0
    fault_episode_s: tuple[float, float] = (3.0, 10.0)
    fault_sigma_frac: float = 0.25
    fault_clip_m: tuple[float, float] = (20.0, 200.0)
