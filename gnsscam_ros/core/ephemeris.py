"""Broadcast ephemerides: satellite position and clock at a transmission time.

GPS, Galileo and BeiDou broadcast Keplerian elements (IS-GPS-200 table 20-IV; Galileo OS
SIS ICD 5.1.1; BeiDou ICD B1I 5.2.4, whose geostationary satellites, PRN 1-5 and 59-63,
are computed in an inertial-like frame and rotated by -5 deg about x and by the Earth's
rotation about z); GLONASS broadcasts a PZ-90 state vector with luni-solar accelerations,
integrated here with a fourth-order Runge-Kutta (GLONASS ICD 5.1, appendix J.1, 60 s
steps). Clocks: the broadcast polynomial, the relativistic term ``F e sqrt(A) sin(E)``
(Keplerian systems; GLONASS includes it in its clock parameters) and the group delay of
the single-frequency signal used (GPS L1 C/A: ``TGD``; Galileo E1: ``BGD(E1,E5b)``;
BeiDou B1I: ``TGD1``).

Times are GPS seconds: seconds since 1980-01-06 00:00:00 GPS time (float, resolution
~0.2 us at this epoch, i.e. millimetres of satellite motion). Galileo system time is taken
equal to GPS time (the GGTO is a few ns); BeiDou time is GPS time - 14 s; GLONASS
reference times are UTC(SU) + 3 h in the navigation message and UTC in RINEX, converted
with the leap seconds of :func:`gps_minus_utc_s`.

Positions are in the ECEF frame of the transmission time (WGS84 / GTRF / CGCS2000 / PZ-90
are taken equal: they differ by centimetres to decimetres), not rotated for the signal's
flight: the consumer does that (``core.frames.sagnac_corrected``).

Everything is vectorised over satellites: one call computes all the satellites of one
system at their own transmission times.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .types import BEIDOU, GALILEO, GLONASS, GPS

SPEED_OF_LIGHT_MPS = 299792458.0
SECONDS_PER_WEEK = 604800.0
#: BeiDou time starts at 2006-01-01 00:00:00 UTC = GPS week 1356 + 14 s.
BDT_WEEK_OFFSET = 1356
BDT_MINUS_GPS_S = -14.0
#: Relativistic clock constant F = -2 sqrt(mu) / c^2 [s / sqrt(m)] (IS-GPS-200 20.3.3.3.3.1).
RELATIVITY_F = -4.442807633e-10

#: Gravitational constant mu [m^3/s^2] and Earth rotation rate [rad/s] of each system's ICD.
GM_M3PS2 = {GPS: 3.986005e14, GALILEO: 3.986004418e14, BEIDOU: 3.986004418e14,
            GLONASS: 3.9860044e14}
OMEGA_E_RPS = {GPS: 7.2921151467e-5, GALILEO: 7.2921151467e-5, BEIDOU: 7.292115e-5,
               GLONASS: 7.292115e-5}
#: PZ-90 second zonal harmonic and equatorial radius (GLONASS ICD table 3.2).
GLONASS_J2 = 1.0826257e-3
GLONASS_RADIUS_M = 6378136.0
GLONASS_STEP_S = 60.0

#: Largest |t - toe| for which an ephemeris is used [s] (the fit intervals: GPS 4 h, Galileo
#: 4 h of validity, BeiDou 1 h updates with longer validity, GLONASS 30 min updates).
MAX_AGE_S = {GPS: 7200.0, GALILEO: 14400.0, BEIDOU: 21600.0, GLONASS: 1800.0}

#: GPS - UTC [s] from the date it applies (GPS seconds of the leap second's start).
_LEAP_SECONDS = ((457833600.0, 14), (820108814.0, 15), (1025136015.0, 16),
                 (1119744016.0, 17), (1167264017.0, 18))


def gps_minus_utc_s(gps_s: float) -> float:
    """GPS - UTC [s] at a GPS time (leap seconds since 2006; 18 s since 2017)."""
    offset = 13.0
    for start, value in _LEAP_SECONDS:
        if gps_s >= start:
            offset = float(value)
    return offset


def is_beidou_geo(prn: np.ndarray) -> np.ndarray:
    """Whether BeiDou PRNs are geostationary (BDS-2 C01-C05, BDS-3 C59-C63)."""
    prn = np.asarray(prn)
    return (prn <= 5) | (prn >= 59)


@dataclass(frozen=True)
class KeplerEphemerides:
    """Broadcast Keplerian records of one system, one row per record.

    Attributes:
        system: System code (GPS, GALILEO or BEIDOU).
        prn: (n,) satellite numbers.
        toe_s: (n,) ephemeris reference time, GPS seconds.
        toe_sow_s: (n,) the same as seconds of the system's own week (enters Omega).
        toc_s: (n,) clock reference time, GPS seconds.
        af0_s, af1, af2_per_s: (n,) clock polynomial [s], [s/s], [s/s^2].
        group_delay_s: (n,) group delay of the single-frequency signal, subtracted from
            the clock [s].
        healthy: (n,) the record's health flags say usable.
        sqrt_a, ecc, i0, idot, omega0, omega_dot, omega, m0, delta_n, cuc, cus, crc, crs,
            cic, cis: (n,) the orbit elements [sqrt(m), -, rad, rad/s, rad, rad/s, rad,
            rad, rad/s, rad, rad, m, m, rad, rad].
    """

    system: int
    prn: np.ndarray
    toe_s: np.ndarray
    toe_sow_s: np.ndarray
    toc_s: np.ndarray
    af0_s: np.ndarray
    af1: np.ndarray
    af2_per_s: np.ndarray
    group_delay_s: np.ndarray
    healthy: np.ndarray
    sqrt_a: np.ndarray
    ecc: np.ndarray
    i0: np.ndarray
    idot: np.ndarray
    omega0: np.ndarray
    omega_dot: np.ndarray
    omega: np.ndarray
    m0: np.ndarray
    delta_n: np.ndarray
    cuc: np.ndarray
    cus: np.ndarray
    crc: np.ndarray
    crs: np.ndarray
    cic: np.ndarray
    cis: np.ndarray

    def __len__(self) -> int:
        return int(self.prn.shape[0])

    @property
    def reference_s(self) -> np.ndarray:
        """(n,) the time each record refers to (its toe), GPS seconds."""
        return self.toe_s

    def clock_s(self, rows: np.ndarray, t_s: np.ndarray) -> np.ndarray:
        """Satellite clock offset without the relativistic term [s] (polynomial minus the
        group delay) of records ``rows`` at GPS times ``t_s``."""
        dt = t_s - self.toc_s[rows]
        return (self.af0_s[rows] + dt * (self.af1[rows] + dt * self.af2_per_s[rows])
                - self.group_delay_s[rows])

    def position(self, rows: np.ndarray, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """ECEF positions of records ``rows`` at GPS times ``t_s``.

        Returns:
            (k, 3) positions [m] and (k,) relativistic clock terms [s].
        """
        gm, omega_e = GM_M3PS2[self.system], OMEGA_E_RPS[self.system]
        tk = t_s - self.toe_s[rows]
        a = self.sqrt_a[rows] ** 2
        ecc = self.ecc[rows]
        mean_anomaly = self.m0[rows] + (np.sqrt(gm / a ** 3) + self.delta_n[rows]) * tk
        ecc_anomaly = mean_anomaly.copy()
        for _ in range(8):      # Newton on E - e sin E = M; e < 0.03 converges in 3-4
            ecc_anomaly -= ((ecc_anomaly - ecc * np.sin(ecc_anomaly) - mean_anomaly)
                            / (1.0 - ecc * np.cos(ecc_anomaly)))
        sin_e, cos_e = np.sin(ecc_anomaly), np.cos(ecc_anomaly)
        true_anomaly = np.arctan2(np.sqrt(1.0 - ecc ** 2) * sin_e, cos_e - ecc)
        phi = true_anomaly + self.omega[rows]
        s2, c2 = np.sin(2.0 * phi), np.cos(2.0 * phi)
        u = phi + self.cus[rows] * s2 + self.cuc[rows] * c2
        r = a * (1.0 - ecc * cos_e) + self.crs[rows] * s2 + self.crc[rows] * c2
        inc = self.i0[rows] + self.idot[rows] * tk + self.cis[rows] * s2 + self.cic[rows] * c2
        x_orb, y_orb = r * np.cos(u), r * np.sin(u)
        geo = (is_beidou_geo(self.prn[rows]) if self.system == BEIDOU
               else np.zeros(rows.shape, dtype=bool))
        # Longitude of the ascending node: Earth-fixed for MEO/IGSO; GEO in the inertial-
        # like frame of BeiDou ICD 5.2.4.12 (rotated into ECEF below).
        node = (self.omega0[rows] + self.omega_dot[rows] * tk
                - omega_e * self.toe_sow_s[rows] - np.where(geo, 0.0, omega_e * tk))
        sin_n, cos_n = np.sin(node), np.cos(node)
        cos_i, sin_i = np.cos(inc), np.sin(inc)
        pos = np.stack([x_orb * cos_n - y_orb * cos_i * sin_n,
                        x_orb * sin_n + y_orb * cos_i * cos_n,
                        y_orb * sin_i], axis=1)
        if geo.any():
            g = pos[geo]
            angle = omega_e * tk[geo]
            sin_z, cos_z = np.sin(angle), np.cos(angle)
            sin_x, cos_x = np.sin(np.radians(-5.0)), np.cos(np.radians(-5.0))
            # R_z(omega_e tk) R_x(-5 deg) applied to the GEO position.
            y_rot = g[:, 1] * cos_x + g[:, 2] * sin_x
            z_rot = -g[:, 1] * sin_x + g[:, 2] * cos_x
            pos[geo] = np.stack([g[:, 0] * cos_z + y_rot * sin_z,
                                 -g[:, 0] * sin_z + y_rot * cos_z, z_rot], axis=1)
        relativistic = RELATIVITY_F * ecc * self.sqrt_a[rows] * sin_e
        return pos, relativistic


@dataclass(frozen=True)
class GlonassEphemerides:
    """Broadcast GLONASS records, one row per record.

    Attributes:
        prn: (n,) slot numbers.
        toe_s: (n,) reference time tb, GPS seconds.
        pos_m, vel_mps, acc_mps2: (n, 3) PZ-90 state and luni-solar acceleration at tb.
        tau_n_s: (n,) clock offset -TauN as RINEX gives it (satellite clock - GLONASS
            time) [s].
        gamma_n: (n,) relative frequency offset GammaN [s/s].
        freq_channel: (n,) frequency channel k (L1 = 1602 + 0.5625 k MHz).
        healthy: (n,) the health flag says usable.
    """

    prn: np.ndarray
    toe_s: np.ndarray
    pos_m: np.ndarray
    vel_mps: np.ndarray
    acc_mps2: np.ndarray
    tau_n_s: np.ndarray
    gamma_n: np.ndarray
    freq_channel: np.ndarray
    healthy: np.ndarray
    system: int = GLONASS

    def __len__(self) -> int:
        return int(self.prn.shape[0])

    @property
    def reference_s(self) -> np.ndarray:
        return self.toe_s

    def clock_s(self, rows: np.ndarray, t_s: np.ndarray) -> np.ndarray:
        """Satellite clock offset [s]: ``-TauN + GammaN (t - tb)`` (ICD 3.3.3)."""
        return self.tau_n_s[rows] + self.gamma_n[rows] * (t_s - self.toe_s[rows])

    def position(self, rows: np.ndarray, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """PZ-90 positions at ``t_s`` by RK4 integration from tb (steps <= 60 s, all
        satellites together; the last step is shortened to land on ``t_s``).

        Returns:
            (k, 3) positions [m] and (k,) zeros (the relativistic term is in the clock
            parameters).
        """
        state = np.concatenate([self.pos_m[rows], self.vel_mps[rows]], axis=1)
        acc = self.acc_mps2[rows]
        remaining = t_s - self.toe_s[rows]
        while np.any(np.abs(remaining) > 1e-9):
            h = np.clip(remaining, -GLONASS_STEP_S, GLONASS_STEP_S)[:, None]
            k1 = _glonass_derivative(state, acc)
            k2 = _glonass_derivative(state + 0.5 * h * k1, acc)
            k3 = _glonass_derivative(state + 0.5 * h * k2, acc)
            k4 = _glonass_derivative(state + h * k3, acc)
            state = state + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
            remaining = remaining - h[:, 0]
        return state[:, :3].copy(), np.zeros(rows.shape[0])


def _glonass_derivative(state: np.ndarray, acc: np.ndarray) -> np.ndarray:
    """d/dt of the PZ-90 state (GLONASS ICD A.3.1.2: central field, J2, rotating frame,
    broadcast luni-solar acceleration)."""
    r_vec, v_vec = state[:, :3], state[:, 3:]
    x, y, z = r_vec[:, 0], r_vec[:, 1], r_vec[:, 2]
    r2 = np.einsum('ij,ij->i', r_vec, r_vec)
    r = np.sqrt(r2)
    gm, omega = GM_M3PS2[GLONASS], OMEGA_E_RPS[GLONASS]
    mu_r3 = gm / (r2 * r)
    j2_term = 1.5 * GLONASS_J2 * gm * GLONASS_RADIUS_M ** 2 / (r2 * r2 * r)
    z2_r2 = 5.0 * z * z / r2
    ax = (-mu_r3 * x - j2_term * x * (1.0 - z2_r2) + omega ** 2 * x
          + 2.0 * omega * v_vec[:, 1] + acc[:, 0])
    ay = (-mu_r3 * y - j2_term * y * (1.0 - z2_r2) + omega ** 2 * y
          - 2.0 * omega * v_vec[:, 0] + acc[:, 1])
    az = -mu_r3 * z - j2_term * z * (3.0 - z2_r2) + acc[:, 2]
    return np.concatenate([v_vec, np.stack([ax, ay, az], axis=1)], axis=1)


#: Why a satellite gets no position: codes of :meth:`EphemerisSelector.select`.
NO_NAV, STALE_NAV, UNHEALTHY = 1, 2, 3
SELECT_REASONS = {NO_NAV: 'no_nav', STALE_NAV: 'stale_nav', UNHEALTHY: 'unhealthy'}


class EphemerisSelector:
    """Picks, per satellite, the healthy record nearest in time (within ``MAX_AGE_S``).

    The records are sorted by satellite once; a selection is a few whole-array operations
    over all records of the system (a few hundred to a few thousand): microseconds.
    """

    def __init__(self, eph: KeplerEphemerides | GlonassEphemerides):
        self.eph = eph
        order = np.lexsort((eph.reference_s, eph.prn))
        self.order = order
        self.sorted_prn = np.asarray(eph.prn)[order]
        self.sorted_ref = np.asarray(eph.reference_s)[order]
        self.sorted_healthy = np.asarray(eph.healthy, dtype=bool)[order]
        self.max_age_s = MAX_AGE_S[eph.system]

    def select(self, prn: np.ndarray, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Records for satellites ``prn`` at GPS time ``t_s``.

        Returns:
            (k,) record rows (-1 where none) and (k,) reason codes (0 found, else
            ``NO_NAV``, ``STALE_NAV`` or ``UNHEALTHY``).
        """
        prn = np.asarray(prn)
        rows = np.full(prn.shape, -1, dtype=np.int64)
        reason = np.full(prn.shape, NO_NAV, dtype=np.int8)
        if not self.sorted_prn.size:
            return rows, reason
        start = np.searchsorted(self.sorted_prn, prn, side='left')
        stop = np.searchsorted(self.sorted_prn, prn, side='right')
        have = stop > start
        age = np.abs(self.sorted_ref - t_s)
        fresh = age <= self.max_age_s
        usable = fresh & self.sorted_healthy
        # Score per record: usable records by age, then unhealthy fresh, then stale.
        score = np.where(usable, age, np.where(fresh, 1e12 + age, 1e15 + age))
        for k in np.flatnonzero(have):      # one slice per observed satellite (<= ~40)
            s, e = start[k], stop[k]
            best = s + int(np.argmin(score[s:e]))
            if usable[best]:
                rows[k], reason[k] = self.order[best], 0
            else:
                reason[k] = UNHEALTHY if fresh[best] else STALE_NAV
        return rows, reason


def satellite_states(eph: KeplerEphemerides | GlonassEphemerides, rows: np.ndarray,
                     t_rx_s: float, pr_m: np.ndarray, iterations: int = 2
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Satellite positions and clocks at the transmission time of each pseudorange.

    The transmission time is ``t_rx - pr / c - dt_sv`` (the satellite clock enters through
    the pseudorange, which holds the receiver's and satellite's clocks); starting from the
    satellite clock at ``t_rx - pr / c`` one or two fixed-point steps converge (dt_sv
    changes by < 1e-12 s per ms).

    Args:
        eph: The system's records.
        rows: (k,) record rows (all valid).
        t_rx_s: Reception time in GPS seconds (receiver clock, as the observation file
            stamps it).
        pr_m: (k,) pseudoranges [m].
        iterations: Fixed-point steps on the satellite clock.

    Returns:
        (k, 3) ECEF positions at transmission [m], (k,) satellite clock offsets including
        the relativistic term and the group delay [s], (k,) transmission times (GPS
        seconds).
    """
    t_nominal = t_rx_s - pr_m / SPEED_OF_LIGHT_MPS
    t_tx = t_nominal
    clock = eph.clock_s(rows, t_tx)
    for _ in range(iterations):
        t_tx = t_nominal - clock
        clock = eph.clock_s(rows, t_tx)
    pos, relativistic = eph.position(rows, t_tx)
    return pos, clock + relativistic, t_tx
