"""Measurement and trajectory containers shared by the core, the datasets and the nodes.

Times are integer nanoseconds (``stamp_ns``); positions are metres; arrays are numpy.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Outcomes of a filter epoch (``EpochResult.status``; ``core.filter``).
UPDATED = 'updated'            # GNSS update applied; integrity computed
PROPAGATED = 'propagated'      # epoch unusable: motion only, integrity not available
REJECTED = 'rejected'          # epoch refused (time going backwards): state unchanged
WAITING = 'waiting'            # no initial fix yet
# The epoch left the state non-finite or absurd: it was discarded and the next usable fix
# initialises the filter again.
INVALID = 'invalid'

# GNSS system identifiers, as in the smartLoc files and the `system` PointCloud2 field.
GPS, SBAS, GLONASS, GALILEO, QZSS, BEIDOU = 1, 2, 4, 8, 16, 32


@dataclass(frozen=True)
class GnssEpoch:
    """All pseudoranges of one receiver epoch.

    Attributes:
        stamp_ns: Receiver time of the epoch [ns].
        sv_pos_ecef_m: (k, 3) satellite ECEF positions at transmission, not yet corrected
            for Earth rotation during signal flight [m].
        pr_m: (k,) pseudoranges, satellite clock and atmosphere removed [m].
        var_m2: (k,) pseudorange variances [m^2].
        sv_id: (k,) satellite numbers within their system.
        system: (k,) system identifiers (GPS=1, GLONASS=4, ...).
        elevation_deg: (k,) elevation angles [deg] (NaN when unknown).
        cn0_dbhz: (k,) carrier-to-noise density ratios [dB-Hz] (NaN when unknown).
    """

    stamp_ns: int
    sv_pos_ecef_m: np.ndarray
    pr_m: np.ndarray
    var_m2: np.ndarray
    sv_id: np.ndarray
    system: np.ndarray
    elevation_deg: np.ndarray
    cn0_dbhz: np.ndarray

    @property
    def n_sv(self) -> int:
        return int(self.pr_m.shape[0])

    def subset(self, keep: np.ndarray) -> 'GnssEpoch':
        """Return the epoch restricted to the satellites selected by ``keep``."""
        return GnssEpoch(
            stamp_ns=self.stamp_ns, sv_pos_ecef_m=self.sv_pos_ecef_m[keep],
            pr_m=self.pr_m[keep], var_m2=self.var_m2[keep], sv_id=self.sv_id[keep],
            system=self.system[keep], elevation_deg=self.elevation_deg[keep],
            cn0_dbhz=self.cn0_dbhz[keep])


@dataclass(frozen=True)
class OdometrySeries:
    """Vehicle-frame speed and yaw rate samples (wheel odometry / smartLoc ``odom3``).

    Attributes:
        stamp_ns: (n,) sample times [ns], strictly increasing.
        speed_mps: (n,) forward speed [m/s].
        yaw_rate_rps: (n,) yaw rate about the up axis [rad/s], counter-clockwise positive.
        speed_var: (n,) speed variance [(m/s)^2].
        yaw_rate_var: (n,) yaw-rate variance [(rad/s)^2].
    """

    stamp_ns: np.ndarray
    speed_mps: np.ndarray
    yaw_rate_rps: np.ndarray
    speed_var: np.ndarray
    yaw_rate_var: np.ndarray

    def __len__(self) -> int:
        return int(self.stamp_ns.shape[0])


@dataclass(frozen=True)
class ImuSeries:
    """Body-frame IMU samples (x forward, y left, z up).

    Attributes:
        stamp_ns: (n,) sample times [ns].
        accel_mps2: (n, 3) specific force [m/s^2] (gravity included on z).
        gyro_rps: (n, 3) angular rate [rad/s].
    """

    stamp_ns: np.ndarray
    accel_mps2: np.ndarray
    gyro_rps: np.ndarray

    def __len__(self) -> int:
        return int(self.stamp_ns.shape[0])


@dataclass(frozen=True)
class Trajectory:
    """Ground-truth or estimated positions.

    Attributes:
        stamp_ns: (n,) times [ns].
        ecef_m: (n, 3) ECEF positions [m].
        yaw_rad: (n,) heading in the local ENU frame, counter-clockwise from east [rad], or
            None when unknown.
    """

    stamp_ns: np.ndarray
    ecef_m: np.ndarray
    yaw_rad: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.stamp_ns.shape[0])


@dataclass
class Drive:
    """One dataset run: everything the filter and the evaluation need.

    Attributes:
        name: Human-readable name.
        origin_llh: (lat_deg, lon_deg, alt_m) of the local ENU ``map`` frame, or None to
            anchor it at the first robust GNSS fix (what an online system can do).
        gnss: GNSS epochs in time order.
        odometry: Wheel odometry, or None.
        imu: IMU samples, or None.
        truth: Ground truth (evaluation only, never used online), or None.
        camera: Camera frames (filled by the camera part of the emulated drive), or None.
        info: Free-form provenance (fault injection record, seed, files read).
    """

    name: str
    origin_llh: tuple[float, float, float] | None
    gnss: list[GnssEpoch]
    odometry: OdometrySeries | None
    imu: ImuSeries | None
    truth: Trajectory | None
    camera: object | None = None
    info: dict = field(default_factory=dict)
