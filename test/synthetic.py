"""Noise-free synthetic GNSS geometry for known-answer tests."""
import numpy as np

from gnsscam_ros.core.frames import OMEGA_EARTH_RPS, SPEED_OF_LIGHT_MPS, LocalFrame
from gnsscam_ros.core.types import GPS, GnssEpoch

FRAME = LocalFrame(52.5096, 13.3760, 80.0)       # Potsdamer Platz


def sky(n: int = 8, seed: int = 0) -> np.ndarray:
    """(n, 3) satellite ECEF positions spread over the sky above FRAME, 26,560 km radius."""
    rng = np.random.default_rng(seed)
    az = np.linspace(0, 2 * np.pi, n, endpoint=False) + rng.uniform(0, 0.3, n)
    el = np.radians(rng.uniform(15, 85, n))
    dirs_enu = np.stack([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)], 1)
    rx = FRAME.origin_ecef_m
    dirs_ecef = dirs_enu @ FRAME.rot_ecef_to_enu
    # Solve |rx + t d| = R for t > 0.
    b = dirs_ecef @ rx
    t = -b + np.sqrt(b * b - (rx @ rx - 26_560e3 ** 2))
    return rx + t[:, None] * dirs_ecef


def epoch_at(rx_enu_m, clock_m=1234.5, sv_ecef=None, stamp_ns=0, system=None,
             sagnac=True) -> GnssEpoch:
    """An exact epoch: pseudorange = range (with Earth rotation in flight) + clock."""
    sv = sky() if sv_ecef is None else sv_ecef
    rx = FRAME.enu_to_ecef(np.asarray(rx_enu_m, dtype=float))
    rho = np.linalg.norm(sv - rx, axis=1)
    if sagnac:
        # The satellite at transmission, seen in the frame of reception, is rotated by
        # -omega * tau about z; its range is the exact light-time range.
        theta = OMEGA_EARTH_RPS * rho / SPEED_OF_LIGHT_MPS
        c, s = np.cos(theta), np.sin(theta)
        rot = np.stack([c * sv[:, 0] + s * sv[:, 1], -s * sv[:, 0] + c * sv[:, 1], sv[:, 2]], 1)
        rho = np.linalg.norm(rot - rx, axis=1)
    k = sv.shape[0]
    system = np.full(k, GPS) if system is None else np.asarray(system)
    clock = np.broadcast_to(np.asarray(clock_m, dtype=float), (k,)) if np.ndim(
        clock_m) == 0 else np.asarray(clock_m)[np.unique(system, return_inverse=True)[1]]
    return GnssEpoch(stamp_ns=stamp_ns, sv_pos_ecef_m=sv, pr_m=rho + clock,
                     var_m2=np.full(k, 10.0), sv_id=np.arange(1, k + 1), system=system,
                     elevation_deg=np.full(k, 45.0), cn0_dbhz=np.full(k, 45.0))
