"""Atmospheric corrections and the pseudorange variance model of the preprocessing layer.

* **Ionosphere**: the Klobuchar model (IS-GPS-200 20.3.3.5.2.5) with the GPS broadcast
  coefficients of the navigation header (``GPSA``/``GPSB``, RINEX 2 ``ION ALPHA/BETA``),
  for every system: it gives the L1 group delay, scaled to the signal's carrier by
  ``(f_L1 / f)^2`` (Galileo E1 = L1; BeiDou B1I 1561.098 MHz; GLONASS G1 per channel).
  Galileo's NeQuick-G and BeiDou's own Klobuchar coefficients are not used: one model for
  all keeps the residual ionosphere common to the systems (the per-system receiver clocks
  absorb a common part); Klobuchar removes about half of the delay.
* **Troposphere**: Saastamoinen zenith delays (hydrostatic and wet) of a standard
  atmosphere at the receiver's height (1013.25 hPa, 15 C and 50 % humidity at sea level,
  the RTKLIB defaults), mapped to the elevation with the Black and Eisner function
  ``m(el) = 1.001 / sqrt(0.002001 + sin^2 el)`` (the RTCA DO-229 mapping).
* **Variance** of a corrected pseudorange [m^2]::

      var = SIGMA_URE^2 + (SIGMA_ZENITH / sin el)^2 * 10^(max(0, CN0_REF - cn0) / 10)

  a broadcast orbit/clock floor plus receiver noise, multipath and residual atmosphere
  growing at low elevation and weak signal (C/N0 unknown: no C/N0 factor). The filter
  learns its error model online; this is a relative weight between satellites.
"""
from __future__ import annotations

import numpy as np

SPEED_OF_LIGHT_MPS = 299792458.0
FREQ_L1_HZ = 1575.42e6
FREQ_B1I_HZ = 1561.098e6
FREQ_G1_HZ, FREQ_G1_STEP_HZ = 1602.0e6, 0.5625e6

#: Variance model (module docstring): broadcast orbit + clock error (~1 m RMS, the SP3/CLK
#: comparison), zenith noise + residual atmosphere, reference C/N0 of a clean signal.
SIGMA_URE_M = 1.0
SIGMA_ZENITH_M = 1.5
CN0_REF_DBHZ = 45.0


def klobuchar_l1_delay_m(alpha: np.ndarray, beta: np.ndarray, lat_rad: float, lon_rad: float,
                         azimuth_rad: np.ndarray, elevation_rad: np.ndarray,
                         gps_s: float) -> np.ndarray:
    """Ionospheric group delay on GPS L1 from the Klobuchar model [m].

    Args:
        alpha, beta: (4,) broadcast coefficients [s, s/sc, s/sc^2, s/sc^3] and
            [s, s/sc, ...].
        lat_rad, lon_rad: Receiver geodetic latitude and longitude [rad].
        azimuth_rad, elevation_rad: (k,) satellite azimuth and elevation [rad].
        gps_s: GPS time [s] (only its time of day matters).

    Returns:
        (k,) L1 delays [m].
    """
    el_sc = elevation_rad / np.pi                       # semicircles
    psi = 0.0137 / (el_sc + 0.11) - 0.022               # Earth-centred angle [sc]
    phi_i = np.clip(lat_rad / np.pi + psi * np.cos(azimuth_rad), -0.416, 0.416)
    lam_i = lon_rad / np.pi + psi * np.sin(azimuth_rad) / np.cos(phi_i * np.pi)
    phi_m = phi_i + 0.064 * np.cos((lam_i - 1.617) * np.pi)
    local_s = np.mod(4.32e4 * lam_i + gps_s, 86400.0)
    slant = 1.0 + 16.0 * (0.53 - el_sc) ** 3
    amplitude = np.maximum(np.polyval(np.asarray(alpha)[::-1], phi_m), 0.0)
    period = np.maximum(np.polyval(np.asarray(beta)[::-1], phi_m), 72000.0)
    x = 2.0 * np.pi * (local_s - 50400.0) / period
    day = np.abs(x) < 1.57
    delay_s = slant * (5e-9 + np.where(day, amplitude * (1.0 - x ** 2 / 2.0 + x ** 4 / 24.0),
                                       0.0))
    return SPEED_OF_LIGHT_MPS * delay_s


def saastamoinen_zenith_m(lat_rad: float, height_m: float) -> tuple[float, float]:
    """Hydrostatic and wet zenith delays of a standard atmosphere [m] (Saastamoinen 1972,
    the formulation of RTKLIB's ``tropmodel``)."""
    h = float(np.clip(height_m, 0.0, 1.0e4))
    pressure = 1013.25 * (1.0 - 2.2557e-5 * h) ** 5.2568
    temperature = 15.0 - 6.5e-3 * h + 273.16
    e_wv = 6.108 * 0.5 * np.exp((17.15 * temperature - 4684.0) / (temperature - 38.45))
    hydro = 0.0022768 * pressure / (1.0 - 0.00266 * np.cos(2.0 * lat_rad) - 0.00028 * h / 1e3)
    wet = 0.002277 * (1255.0 / temperature + 0.05) * e_wv
    return float(hydro), float(wet)


def tropo_delay_m(lat_rad: float, height_m: float, elevation_rad: np.ndarray) -> np.ndarray:
    """Slant tropospheric delay [m]: Saastamoinen zenith delays times the Black-Eisner
    mapping function."""
    hydro, wet = saastamoinen_zenith_m(lat_rad, height_m)
    mapping = 1.001 / np.sqrt(0.002001 + np.sin(elevation_rad) ** 2)
    return (hydro + wet) * mapping


def pseudorange_variance_m2(elevation_rad: np.ndarray, cn0_dbhz: np.ndarray) -> np.ndarray:
    """The variance model of the module docstring [m^2] (NaN C/N0: no C/N0 factor)."""
    sin_el = np.maximum(np.sin(elevation_rad), np.sin(np.radians(5.0)))
    weak = np.where(np.isfinite(cn0_dbhz), np.maximum(0.0, CN0_REF_DBHZ - cn0_dbhz), 0.0)
    return SIGMA_URE_M ** 2 + (SIGMA_ZENITH_M / sin_el) ** 2 * 10.0 ** (weak / 10.0)


def azimuth_elevation(rx_ecef_m: np.ndarray, sv_ecef_m: np.ndarray,
                      rot_ecef_to_enu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(k,) azimuth (from north, clockwise) and elevation [rad] of satellites seen from a
    receiver; ``rot_ecef_to_enu`` rows are the east, north, up unit vectors."""
    enu = (sv_ecef_m - rx_ecef_m) @ rot_ecef_to_enu.T
    horizontal = np.hypot(enu[:, 0], enu[:, 1])
    return np.arctan2(enu[:, 0], enu[:, 1]), np.arctan2(enu[:, 2], horizontal)
