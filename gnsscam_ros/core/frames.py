"""Earth frames: ECEF <-> geodetic <-> local ENU (the ``map`` frame), via pymap3d.

The filter works in a local east-north-up frame anchored at ``origin_llh``; satellites stay
ECEF until they are converted once per epoch.
"""
from __future__ import annotations

import numpy as np
import pymap3d

OMEGA_EARTH_RPS = 7.2921151467e-5   # WGS84 Earth rotation rate [rad/s]
SPEED_OF_LIGHT_MPS = 299792458.0


class LocalFrame:
    """A local ENU frame with its origin at a geodetic point (WGS84)."""

    def __init__(self, lat_deg: float, lon_deg: float, alt_m: float):
        if not (np.isfinite(lat_deg) and np.isfinite(lon_deg) and np.isfinite(alt_m)):
            raise ValueError(f'frame origin must be finite, got {(lat_deg, lon_deg, alt_m)}')
        if not -90.0 <= lat_deg <= 90.0:
            raise ValueError(f'origin latitude {lat_deg} deg outside [-90, 90]')
        self.origin_llh = (float(lat_deg), float(lon_deg), float(alt_m))
        self.origin_ecef_m = np.array(pymap3d.geodetic2ecef(*self.origin_llh))
        lat, lon = np.radians(lat_deg), np.radians(lon_deg)
        sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
        # Rows are the east, north, up unit vectors expressed in ECEF.
        self.rot_ecef_to_enu = np.array([[-so, co, 0.0],
                                         [-sl * co, -sl * so, cl],
                                         [cl * co, cl * so, sl]])

    @classmethod
    def from_ecef(cls, ecef_m: np.ndarray) -> 'LocalFrame':
        """Frame whose origin is the geodetic point under ``ecef_m`` [m]."""
        lat, lon, alt = pymap3d.ecef2geodetic(*np.asarray(ecef_m, dtype=float))
        return cls(float(lat), float(lon), float(alt))

    @classmethod
    def at_origin_or(cls, origin_llh, first_ecef_m: np.ndarray) -> 'LocalFrame':
        """A drive's map frame: at its ``origin_llh`` (lat, lon, alt) when it has one,
        else under ``first_ecef_m`` (its first ground-truth position) [m]."""
        return cls(*origin_llh) if origin_llh is not None else cls.from_ecef(first_ecef_m)

    def ecef_to_enu(self, ecef_m: np.ndarray) -> np.ndarray:
        """(..., 3) ECEF [m] -> (..., 3) local ENU [m] (a rigid transform)."""
        return (np.asarray(ecef_m, dtype=float) - self.origin_ecef_m) @ self.rot_ecef_to_enu.T

    def enu_to_ecef(self, enu_m: np.ndarray) -> np.ndarray:
        """(..., 3) local ENU [m] -> (..., 3) ECEF [m]."""
        return np.asarray(enu_m, dtype=float) @ self.rot_ecef_to_enu + self.origin_ecef_m

    def enu_to_geodetic(self, enu_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(..., 3) local ENU [m] -> latitude [deg], longitude [deg], altitude [m]."""
        enu = np.asarray(enu_m, dtype=float)
        return pymap3d.enu2geodetic(enu[..., 0], enu[..., 1], enu[..., 2], *self.origin_llh)

    def geodetic_to_enu(self, lat_deg, lon_deg, alt_m) -> np.ndarray:
        """Geodetic (WGS84) -> (..., 3) local ENU [m]."""
        e, n, u = pymap3d.geodetic2enu(lat_deg, lon_deg, alt_m, *self.origin_llh)
        return np.stack([np.asarray(e), np.asarray(n), np.asarray(u)], axis=-1)


def sagnac_corrected(sv_pos_ecef_m: np.ndarray, rx_ecef_m: np.ndarray) -> np.ndarray:
    """Rotate satellite positions into the ECEF frame of the reception time.

    Satellite positions are given in the ECEF frame at transmission; during the ~70 ms of
    signal flight the Earth turns by omega*tau, which moves the receiver up to ~30 m in range.

    Args:
        sv_pos_ecef_m: (k, 3) satellite positions at transmission [m].
        rx_ecef_m: (3,) approximate receiver position [m] (metres of error are harmless).

    Returns:
        (k, 3) satellite positions in the ECEF frame at reception [m].
    """
    sv = np.asarray(sv_pos_ecef_m, dtype=float)
    tau_s = row_norms(sv - rx_ecef_m) / SPEED_OF_LIGHT_MPS
    theta = OMEGA_EARTH_RPS * tau_s
    c, s = np.cos(theta), np.sin(theta)
    out = sv.copy()
    out[:, 0] = c * sv[:, 0] + s * sv[:, 1]
    out[:, 1] = -s * sv[:, 0] + c * sv[:, 1]
    return out


def row_norms(vectors: np.ndarray) -> np.ndarray:
    """Euclidean norm of each row of a (k, d) float array: ``np.linalg.norm(vectors,
    axis=1)``'s arithmetic (the same results to the bit) without its dispatch, which cost
    more than the arithmetic on the dozen rows of an epoch's satellites."""
    return np.sqrt(np.add.reduce(vectors * vectors, axis=1))
