"""Operations on a whole drive (any dataset): cutting it short."""
from __future__ import annotations

import dataclasses

import numpy as np

from ..core.types import Drive, ImuSeries, OdometrySeries, Trajectory


def cut_drive(drive: Drive, duration_s: float | None) -> Drive:
    """The first ``duration_s`` seconds of a drive (None or <= 0: the whole drive).

    The cut starts at the first GNSS epoch; odometry, IMU and truth are kept over the same
    span (truth one second longer, so that the last epoch is bracketed).
    """
    if not duration_s or duration_s <= 0 or not drive.gnss:
        return drive
    t0 = drive.gnss[0].stamp_ns
    t1 = t0 + int(round(duration_s * 1e9))

    def keep(stamps, end=t1):
        return (np.asarray(stamps) >= t0 - 10**9) & (np.asarray(stamps) <= end)

    odo, imu, truth = drive.odometry, drive.imu, drive.truth
    if odo is not None:
        k = keep(odo.stamp_ns)
        odo = OdometrySeries(odo.stamp_ns[k], odo.speed_mps[k], odo.yaw_rate_rps[k],
                             odo.speed_var[k], odo.yaw_rate_var[k])
    if imu is not None:
        k = keep(imu.stamp_ns)
        imu = ImuSeries(imu.stamp_ns[k], imu.accel_mps2[k], imu.gyro_rps[k])
    if truth is not None:
        k = keep(truth.stamp_ns, t1 + 10**9)
        truth = Trajectory(truth.stamp_ns[k], truth.ecef_m[k],
                           None if truth.yaw_rad is None else truth.yaw_rad[k])
    return dataclasses.replace(
        drive, gnss=[e for e in drive.gnss if e.stamp_ns <= t1], odometry=odo, imu=imu,
        truth=truth, info={**drive.info, 'cut_s': float(duration_s)})
