"""IMU and wheel odometry of the emulated drive, from the truth kinematics.

* **IMU** (``imu_rate_hz``, body x forward, y left, z up): specific force
  ``(dv/dt, kappa v^2, g)`` and gyro ``(0, 0, kappa v)`` plus constant biases and white
  noise. The Earth rate is not included (below the gyro bias of an automotive MEMS IMU).
  The ground is flat, so there is no pitch or roll.
* **Odometry** (``odom_rate_hz``): truth speed and yaw rate plus white noise; a wheel-speed
  sensor reads exactly 0 at standstill and never a negative speed.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import EmulationConfig
from .trajectory import Pose

GRAVITY_MPS2 = 9.81                 # local gravity magnitude used for the IMU [m/s^2]


@dataclass(frozen=True)
class ImuSynthesis:
    """Simulated IMU samples, one per truth sample.

    Attributes:
        accel_mps2: (n, 3) specific force, body frame [m/s^2].
        gyro_rps: (n, 3) angular rate, body frame [rad/s].
        accel_bias_mps2: (3,) the constant accelerometer bias included [m/s^2].
        gyro_bias_rps: (3,) the constant gyro bias included [rad/s].
    """

    accel_mps2: np.ndarray
    gyro_rps: np.ndarray
    accel_bias_mps2: np.ndarray
    gyro_bias_rps: np.ndarray


@dataclass(frozen=True)
class OdometrySynthesis:
    """Simulated wheel odometry on a subset of the truth samples.

    Attributes:
        index: (m,) indices of the truth samples read.
        speed_mps: (m,) measured forward speed [m/s].
        yaw_rate_rps: (m,) measured yaw rate [rad/s].
    """

    index: np.ndarray
    speed_mps: np.ndarray
    yaw_rate_rps: np.ndarray


def synthesize_imu(rng: np.random.Generator, pose: Pose, cfg: EmulationConfig) -> ImuSynthesis:
    """IMU samples at the truth samples ``pose`` (see the module docstring).

    Args:
        rng: The drive's ``'imu'`` stream.
        pose: Truth kinematics at the IMU rate.
        cfg: Parameters (noise and bias levels).
    """
    n = len(pose.speed_mps)
    acc_bias = rng.normal(0.0, cfg.accel_bias_mps2, 3)
    gyro_bias = rng.normal(0.0, cfg.gyro_bias_rps, 3)
    accel = np.column_stack([pose.accel_mps2, pose.speed_mps * pose.yaw_rate_rps,
                             np.full(n, GRAVITY_MPS2)])
    gyro = np.column_stack([np.zeros(n), np.zeros(n), pose.yaw_rate_rps])
    accel = accel + acc_bias + rng.normal(0.0, cfg.accel_noise_mps2, (n, 3))
    gyro = gyro + gyro_bias + rng.normal(0.0, cfg.gyro_noise_rps, (n, 3))
    return ImuSynthesis(accel_mps2=accel, gyro_rps=gyro, accel_bias_mps2=acc_bias,
                        gyro_bias_rps=gyro_bias)


def synthesize_odometry(rng: np.random.Generator, pose: Pose,
                        cfg: EmulationConfig) -> OdometrySynthesis:
    """Odometry every ``imu_rate_hz / odom_rate_hz`` truth samples (module docstring).

    Args:
        rng: The drive's ``'odometry'`` stream.
        pose: Truth kinematics at the IMU rate.
        cfg: Parameters (rates, noise levels).
    """
    step = int(round(cfg.imu_rate_hz / cfg.odom_rate_hz))
    io = np.arange(0, len(pose.speed_mps), step)
    v_o = pose.speed_mps[io]
    speed = np.where(v_o < 1e-3, 0.0,
                     np.maximum(v_o + rng.normal(0.0, cfg.odom_speed_std_mps, len(io)), 0.0))
    yaw_rate = pose.yaw_rate_rps[io] + rng.normal(0.0, cfg.odom_yaw_rate_std_rps, len(io))
    return OdometrySynthesis(index=io, speed_mps=speed, yaw_rate_rps=yaw_rate)
