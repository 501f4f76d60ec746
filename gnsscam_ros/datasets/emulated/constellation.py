"""GNSS constellation of the emulated drive and its geometry seen from the receiver.

GPS (30 satellites, 6 planes, 55 deg, a = 26,560 km) and GLONASS (24, 3 planes, 64.8 deg,
a = 25,508 km) on circular orbits with a seeded constellation phase. Ranges come from the
light-time equation in an Earth-fixed frame: satellite positions are reported at
transmission, so a user needs the Sagnac correction of :func:`...core.frames.sagnac_corrected`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...core.frames import OMEGA_EARTH_RPS, SPEED_OF_LIGHT_MPS, LocalFrame
from ...core.types import GLONASS, GPS
from .config import EmulationConfig

MU_EARTH_M3PS2 = 3.986004418e14     # WGS84 gravitational parameter [m^3/s^2]
GPS_SEMI_MAJOR_AXIS_M = 26_559_700.0
GLONASS_SEMI_MAJOR_AXIS_M = 25_508_000.0


def unix_to_era_rad(t_unix_s: float) -> float:
    """Earth rotation angle (IERS 2003, UT1 ~ UTC) at a Unix time [rad]."""
    jd = t_unix_s / 86400.0 + 2440587.5
    return float(2 * np.pi * ((0.7790572732640 + 1.00273781191135448 * (jd - 2451545.0)) % 1.0))


@dataclass(frozen=True)
class Constellation:
    """Circular orbits: semi-major axis, inclination, RAAN, argument of latitude at t = 0."""

    system: np.ndarray
    sv_id: np.ndarray
    a_m: np.ndarray
    incl: np.ndarray
    raan: np.ndarray
    u0: np.ndarray
    era0: float   # Earth rotation angle at t = 0 [rad]

    def ecef(self, t_s: np.ndarray) -> np.ndarray:
        """(n, S, 3) satellite ECEF positions (frame of time t) at times (n,) or (n, S) [m]."""
        t = np.asarray(t_s, dtype=float)
        if t.ndim == 1:
            t = t[:, None]
        u = self.u0 + np.sqrt(MU_EARTH_M3PS2 / self.a_m ** 3) * t
        cu, su = np.cos(u), np.sin(u)
        co, so = np.cos(self.raan), np.sin(self.raan)
        ci, si = np.cos(self.incl), np.sin(self.incl)
        x = self.a_m * (co * cu - so * su * ci)
        y = self.a_m * (so * cu + co * su * ci)
        z = self.a_m * su * si
        th = self.era0 + OMEGA_EARTH_RPS * t
        ct, st = np.cos(th), np.sin(th)
        return np.stack([ct * x + st * y, -st * x + ct * y, np.broadcast_to(z, x.shape)], -1)


def make_constellation(rng: np.random.Generator, era0: float) -> Constellation:
    """GPS 6x5 and GLONASS 3x8 with a seeded overall phase and small slot irregularities."""
    deg = np.pi / 180.0
    p, k = np.meshgrid(np.arange(6), np.arange(5), indexing='ij')
    gps_raan = rng.uniform(0, 2 * np.pi) + 60 * deg * p.ravel()
    gps_u = (rng.uniform(0, 2 * np.pi) + 72 * deg * k.ravel() + 14 * deg * p.ravel()
             + rng.normal(0, 4 * deg, p.size))
    p2, k2 = np.meshgrid(np.arange(3), np.arange(8), indexing='ij')
    glo_raan = rng.uniform(0, 2 * np.pi) + 120 * deg * p2.ravel()
    glo_u = rng.uniform(0, 2 * np.pi) + 45 * deg * k2.ravel() + 15 * deg * p2.ravel()
    n_gps, n_glo = p.size, p2.size
    return Constellation(
        system=np.r_[np.full(n_gps, GPS), np.full(n_glo, GLONASS)],
        sv_id=np.r_[np.arange(1, n_gps + 1), np.arange(1, n_glo + 1)],
        a_m=np.r_[np.full(n_gps, GPS_SEMI_MAJOR_AXIS_M),
                  np.full(n_glo, GLONASS_SEMI_MAJOR_AXIS_M)],
        incl=np.r_[np.full(n_gps, 55.0 * deg), np.full(n_glo, 64.8 * deg)],
        raan=np.r_[gps_raan, glo_raan], u0=np.r_[gps_u, glo_u], era0=era0)


def _rot_z(xyz: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Rotate ECEF vectors into the frame turned by ``theta`` about z (as sagnac_corrected)."""
    c, s = np.cos(theta), np.sin(theta)
    return np.stack([c * xyz[..., 0] + s * xyz[..., 1], -s * xyz[..., 0] + c * xyz[..., 1],
                     xyz[..., 2]], -1)


def light_time(const: Constellation, t_rx_s: np.ndarray, rx_ecef: np.ndarray):
    """Solve the light-time equation for every (epoch, satellite).

    Finds the flight time ``tau`` with ``c tau = |R_z(w tau) x_sv(t_rx - tau) - x_rx|``: the
    satellite position at transmission, expressed in the Earth-fixed frame of the reception
    time. The fixed-point iteration contracts by ~v_sv/c ~ 1e-5 per step.

    Returns:
        ``(sv_tx (n, S, 3) ECEF of transmission time, sv_rx (n, S, 3) same point in the
        ECEF frame of reception, range (n, S) geometric range [m])``.
    """
    tau = np.full((len(t_rx_s), len(const.system)), 0.075)
    for _ in range(4):
        sv_tx = const.ecef(t_rx_s[:, None] - tau)
        sv_rx = _rot_z(sv_tx, OMEGA_EARTH_RPS * tau)
        rng_m = np.linalg.norm(sv_rx - rx_ecef[:, None, :], axis=-1)
        tau = rng_m / SPEED_OF_LIGHT_MPS
    sv_tx = const.ecef(t_rx_s[:, None] - tau)
    sv_rx = _rot_z(sv_tx, OMEGA_EARTH_RPS * tau)
    return sv_tx, sv_rx, np.linalg.norm(sv_rx - rx_ecef[:, None, :], axis=-1)


@dataclass(frozen=True)
class SkyView:
    """The constellation along the drive, seen from the receiver at each epoch.

    Attributes:
        const: The constellation (S satellites).
        sv_tx: (n, S, 3) satellite ECEF positions at transmission, frame of transmission [m].
        los: (n, S, 3) receiver-to-satellite vectors in the local ENU frame [m].
        rho: (n, S) geometric ranges (light-time solution) [m].
        el_deg: (n, S) elevations [deg].
    """

    const: Constellation
    sv_tx: np.ndarray
    los: np.ndarray
    rho: np.ndarray
    el_deg: np.ndarray


def visible_constellation(rng: np.random.Generator, t0_ns: int, t_s: np.ndarray,
                          rx_ecef: np.ndarray, frame: LocalFrame,
                          cfg: EmulationConfig) -> SkyView:
    """A constellation with enough satellites above the mask at every epoch.

    The constellation phase is redrawn until >= ``n_sv + 2`` satellites (with
    ``>= n_sv - max_gps`` GLONASS) are above the mask at every epoch, so that tracking
    never runs short.

    Args:
        rng: The drive's ``'constellation'`` stream.
        t0_ns: Unix time of ``t_s = 0`` [ns].
        t_s: (n,) epoch times from the start [s].
        rx_ecef: (n, 3) receiver positions [m].
        frame: Local ENU frame of the drive.
        cfg: Parameters (mask, satellite counts).

    Returns:
        The constellation and its geometry at the epochs.

    Raises:
        RuntimeError: when no phase in 100 draws has enough satellites in view.
    """
    era0 = unix_to_era_rad(t0_ns / 1e9)
    for _ in range(100):
        const = make_constellation(rng, era0)
        sv_tx, sv_rx, rho = light_time(const, t_s, rx_ecef)
        los = (sv_rx - rx_ecef[:, None, :]) @ frame.rot_ecef_to_enu.T     # (n, S, 3) ENU
        el_all = np.degrees(np.arcsin(los[..., 2] / rho))
        vis = el_all > cfg.elevation_mask_deg
        if (vis.sum(1).min() >= cfg.n_sv + 2
                and vis[:, const.system == GLONASS].sum(1).min() >= cfg.n_sv - cfg.max_gps):
            return SkyView(const=const, sv_tx=sv_tx, los=los, rho=rho, el_deg=el_all)
    raise RuntimeError('no constellation phase with enough visible satellites')
