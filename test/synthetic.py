"""Noise-free synthetic GNSS geometry for known-answer tests.

Independent of the code under test: the geodesy (WGS-84 geodetic to ECEF, the local
east-north-up axes) and the signal's flight (the Earth turning under it) are computed here
from their definitions, with the published constants stated here, and only ``FRAME``, the
project's :class:`LocalFrame` at the same origin, is handed to the code under test. A bug
in the project's frames or Earth-rotation correction therefore shows as a wrong answer
instead of being reproduced by the data.
"""
import numpy as np
from scipy.spatial.transform import Rotation

from gnsscam_ros.core.frames import LocalFrame
from gnsscam_ros.core.types import GPS, GnssEpoch

#: WGS-84 (NIMA TR8350.2): semi-major axis [m], flattening, Earth rotation rate [rad/s].
WGS84_A_M = 6_378_137.0
WGS84_F = 1.0 / 298.257223563
WGS84_OMEGA_RPS = 7.2921151467e-5
#: The speed of light in vacuum (SI, exact) [m/s].
C_MPS = 299_792_458.0
#: A GPS orbit's radius [m] (semi-major axis 26,560 km).
ORBIT_RADIUS_M = 26_560e3

ORIGIN_LLH = (52.5096, 13.3760, 80.0)            # Potsdamer Platz
FRAME = LocalFrame(*ORIGIN_LLH)


def geodetic_to_ecef(lat_deg: float, lon_deg: float, alt_m: float) -> np.ndarray:
    """WGS-84 geodetic -> ECEF [m]: the prime vertical radius N = a / sqrt(1 - e^2 sin^2 phi),
    x = (N + h) cos phi cos lambda, y = (N + h) cos phi sin lambda, z = (N (1 - e^2) + h)
    sin phi."""
    e2 = WGS84_F * (2.0 - WGS84_F)
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    n = WGS84_A_M / np.sqrt(1.0 - e2 * np.sin(lat) ** 2)
    return np.array([(n + alt_m) * np.cos(lat) * np.cos(lon),
                     (n + alt_m) * np.cos(lat) * np.sin(lon),
                     (n * (1.0 - e2) + alt_m) * np.sin(lat)])


def enu_axes(lat_deg: float, lon_deg: float) -> np.ndarray:
    """(3, 3) rows east, north, up in ECEF: up is the ellipsoid normal (what geodetic
    latitude is the elevation of), east the direction of growing longitude, north
    completes the right-handed set."""
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    up = np.array([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
    east = np.cross([0.0, 0.0, 1.0], up)
    east /= np.linalg.norm(east)
    return np.stack([east, np.cross(up, east), up])


ORIGIN_ECEF_M = geodetic_to_ecef(*ORIGIN_LLH)
AXES = enu_axes(*ORIGIN_LLH[:2])


def enu_to_ecef(enu_m) -> np.ndarray:
    """(..., 3) ENU about ``ORIGIN_LLH`` -> ECEF [m]."""
    return ORIGIN_ECEF_M + np.asarray(enu_m, dtype=float) @ AXES


def sky(n: int = 8, seed: int = 0) -> np.ndarray:
    """(n, 3) satellite ECEF positions spread over the sky above FRAME, 26,560 km radius."""
    rng = np.random.default_rng(seed)
    az = np.linspace(0, 2 * np.pi, n, endpoint=False) + rng.uniform(0, 0.3, n)
    el = np.radians(rng.uniform(15, 85, n))
    dirs_enu = np.stack([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)], 1)
    rx = ORIGIN_ECEF_M
    dirs_ecef = dirs_enu @ AXES
    # Solve |rx + t d| = R for t > 0.
    b = dirs_ecef @ rx
    t = -b + np.sqrt(b * b - (rx @ rx - ORBIT_RADIUS_M ** 2))
    return rx + t[:, None] * dirs_ecef


def light_time_range(sv_ecef_m: np.ndarray, rx_ecef_m: np.ndarray) -> np.ndarray:
    """(k,) distance the signal travelled [m]: c * tau, where tau is the flight time.

    ``sv_ecef_m`` holds the satellites at transmission, in the Earth-fixed frame of that
    instant; during the flight the Earth turns by omega * tau about z, so in the frame of
    reception, where the receiver is at ``rx_ecef_m``, the point of transmission lies
    rotated by -omega * tau. The flight time solves tau = |R_z(-omega tau) sv - rx| / c,
    found by fixed-point iteration (a contraction: d/dtau is ~ omega |sv| / c ~ 6e-3).
    """
    sv = np.asarray(sv_ecef_m, dtype=float)
    tau = np.linalg.norm(sv - rx_ecef_m, axis=1) / C_MPS
    for _ in range(20):
        turned = Rotation.from_rotvec(np.outer(-WGS84_OMEGA_RPS * tau, [0.0, 0.0, 1.0]))
        new_tau = np.linalg.norm(turned.apply(sv) - rx_ecef_m, axis=1) / C_MPS
        if np.max(np.abs(new_tau - tau)) < 1e-17:
            break
        tau = new_tau
    else:
        raise AssertionError('light time did not converge')
    return C_MPS * new_tau


def epoch_at(rx_enu_m, clock_m=1234.5, sv_ecef=None, stamp_ns=0, system=None,
             sagnac=True) -> GnssEpoch:
    """An exact epoch: pseudorange = light-time range (with Earth rotation in flight, or
    the straight distance when ``sagnac`` is False) + clock."""
    sv = sky() if sv_ecef is None else sv_ecef
    rx = enu_to_ecef(rx_enu_m)
    rho = light_time_range(sv, rx) if sagnac else np.linalg.norm(sv - rx, axis=1)
    k = sv.shape[0]
    system = np.full(k, GPS) if system is None else np.asarray(system)
    clock = np.broadcast_to(np.asarray(clock_m, dtype=float), (k,)) if np.ndim(
        clock_m) == 0 else np.asarray(clock_m)[np.unique(system, return_inverse=True)[1]]
    return GnssEpoch(stamp_ns=stamp_ns, sv_pos_ecef_m=sv, pr_m=rho + clock,
                     var_m2=np.full(k, 10.0), sv_id=np.arange(1, k + 1), system=system,
                     elevation_deg=np.full(k, 45.0), cn0_dbhz=np.full(k, 45.0))
