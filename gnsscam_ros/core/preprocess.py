"""Raw observations + broadcast navigation -> one corrected ``GnssEpoch``.

The preprocessing layer between a receiver (RINEX file, a u-blox RXM-RAWX driver, an
Android log) and ``gnss/pseudoranges``. Per satellite of one observation epoch:

1. systems not handled (SBAS, QZSS, NavIC) are skipped (``unhandled_system``), and so are
   satellites without a code pseudorange on the signal used (``no_signal``);
2. the healthy broadcast record nearest in time is picked (``no_nav``, ``stale_nav``,
   ``unhealthy`` otherwise; ``core.ephemeris.EphemerisSelector``);
3. position and clock at transmission time, iterating on the signal travel time
   (``core.ephemeris.satellite_states``): clock polynomial, relativistic term, group delay;
4. a rough receiver position (the previous epoch's, or a few Gauss-Newton steps from the
   Earth's centre on the clock-corrected pseudoranges) gives azimuth and elevation; below
   the mask the satellite is skipped (``elevation_mask``);
5. Klobuchar ionosphere and Saastamoinen troposphere are removed and the variance is set
   (``core.corrections``).

The output is exactly what ``gnss/pseudoranges`` carries (``msg_adapters.wire``): the
pseudorange with satellite clock, ionosphere and troposphere removed, the satellite's ECEF
position at transmission time *not* rotated for the Earth's rotation during the flight
(the filter does it, ``core.frames.sagnac_corrected``). Vectorised over satellites; no
ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import corrections
from .ephemeris import (SELECT_REASONS, EphemerisSelector, GlonassEphemerides,
                        KeplerEphemerides, satellite_states)
from .frames import LocalFrame, sagnac_corrected
from .types import BEIDOU, GALILEO, GLONASS, GPS, GnssEpoch

SPEED_OF_LIGHT_MPS = 299792458.0
#: Systems with a broadcast orbit model here.
HANDLED_SYSTEMS = (GPS, GLONASS, GALILEO, BEIDOU)
#: Reasons a satellite is skipped, in the order they are checked.
SKIP_REASONS = ('unhandled_system', 'no_signal', 'no_nav', 'stale_nav', 'unhealthy',
                'no_receiver_position', 'elevation_mask')
#: A rough fix farther than this from the Earth's surface is not a receiver position [m].
_ROUGH_FIX_RADIUS_M = (6.0e6, 7.0e6)


@dataclass(frozen=True)
class ObservationEpoch:
    """One receiver epoch of raw code observations (any source: RINEX, RXM-RAWX, Android).

    Attributes:
        stamp_ns: The stamp the corrected epoch gets (``msg_adapters.wire``: UTC as POSIX
            nanoseconds, i.e. ROS time) [ns].
        gps_s: Reception time by the receiver's clock, GPS seconds (since 1980-01-06).
        system: (k,) system codes (``core.types``: GPS=1, GLONASS=4, ...).
        prn: (k,) satellite numbers within the system (GLONASS: slot).
        pr_m: (k,) raw code pseudoranges [m] (NaN: no code on the signal used).
        cn0_dbhz: (k,) carrier-to-noise density [dB-Hz] (NaN: unknown).
    """

    stamp_ns: int
    gps_s: float
    system: np.ndarray
    prn: np.ndarray
    pr_m: np.ndarray
    cn0_dbhz: np.ndarray


@dataclass(frozen=True)
class Navigation:
    """Broadcast navigation data of all systems.

    Attributes:
        ephemerides: system code -> its records.
        klobuchar_alpha, klobuchar_beta: (4,) GPS Klobuchar coefficients, or None (no
            ionospheric correction then; said in ``PreprocessConfig``'s counts).
        sources: Files the data came from.
    """

    ephemerides: dict
    klobuchar_alpha: np.ndarray | None = None
    klobuchar_beta: np.ndarray | None = None
    sources: tuple = ()

    def span_s(self) -> tuple[float, float] | None:
        """First and last record reference times (GPS seconds), or None when empty."""
        refs = [np.asarray(e.reference_s) for e in self.ephemerides.values() if len(e)]
        if not refs:
            return None
        allref = np.concatenate(refs)
        return float(allref.min()), float(allref.max())


@dataclass(frozen=True)
class PreprocessConfig:
    """Parameters of the preprocessing layer (one default for every receiver).

    Attributes:
        elevation_mask_deg: Satellites below are skipped [deg].
        ionosphere: Remove the Klobuchar delay.
        troposphere: Remove the Saastamoinen delay.
    """

    elevation_mask_deg: float = 10.0
    ionosphere: bool = True
    troposphere: bool = True


@dataclass
class PreprocessResult:
    """One corrected epoch and what was left out.

    Attributes:
        epoch: The corrected epoch (possibly with no satellite).
        skipped: reason -> satellites skipped (``SKIP_REASONS``).
        rough_ecef_m: The receiver position used for the corrections, or None.
    """

    epoch: GnssEpoch
    skipped: dict = field(default_factory=dict)
    rough_ecef_m: np.ndarray | None = None


def _carrier_hz(system: np.ndarray, channel: np.ndarray) -> np.ndarray:
    """Carrier of the single-frequency signal used: L1/E1, B1I, or GLONASS G1(k)."""
    return np.select([system == BEIDOU, system == GLONASS],
                     [corrections.FREQ_B1I_HZ,
                      corrections.FREQ_G1_HZ + corrections.FREQ_G1_STEP_HZ * channel],
                     corrections.FREQ_L1_HZ)


def rough_fix(sv_ecef_m: np.ndarray, pr_m: np.ndarray, system: np.ndarray,
              start_ecef_m: np.ndarray | None = None, iterations: int = 8
              ) -> np.ndarray | None:
    """Unweighted Gauss-Newton position with one clock per system (Earth rotation applied),
    good to metres to tens of metres: the geometry of the corrections, not a solution.

    Returns:
        (3,) ECEF [m], or None with too few satellites or no convergence to the surface.
    """
    systems, index = np.unique(system, return_inverse=True)
    n_unknowns = 3 + systems.size
    if pr_m.size < n_unknowns:
        return None
    x = np.zeros(n_unknowns)
    if start_ecef_m is not None:
        x[:3] = start_ecef_m
    for _ in range(iterations):
        sv = sagnac_corrected(sv_ecef_m, x[:3]) if np.any(x[:3]) else sv_ecef_m
        diff = sv - x[:3]
        rng = np.linalg.norm(diff, axis=1)
        jac = np.zeros((pr_m.size, n_unknowns))
        jac[:, :3] = -diff / rng[:, None]
        jac[np.arange(pr_m.size), 3 + index] = 1.0
        step, *_ = np.linalg.lstsq(jac, pr_m - rng - x[3:][index], rcond=None)
        x += step
        if np.linalg.norm(step[:3]) < 1e-3:
            break
    radius = float(np.linalg.norm(x[:3]))
    if not (np.all(np.isfinite(x)) and _ROUGH_FIX_RADIUS_M[0] < radius < _ROUGH_FIX_RADIUS_M[1]):
        return None
    return x[:3].copy()


class Preprocessor:
    """Turns observation epochs into corrected epochs, one after another (it keeps the
    last rough receiver position as the next epoch's geometry).

    Args:
        navigation: Broadcast navigation data.
        config: Parameters (default :class:`PreprocessConfig`).
    """

    def __init__(self, navigation: Navigation, config: PreprocessConfig | None = None):
        self.navigation = navigation
        self.config = config or PreprocessConfig()
        self.selectors = {s: EphemerisSelector(e) for s, e in navigation.ephemerides.items()
                          if len(e)}
        self.rough_ecef_m: np.ndarray | None = None

    def process(self, obs: ObservationEpoch) -> PreprocessResult:
        """Correct one observation epoch (see the module docstring).

        Returns:
            The corrected epoch and the skipped satellites by reason.
        """
        k = obs.pr_m.shape[0]
        reason = np.zeros(k, dtype=np.int8)          # 0 kept, else 1 + SKIP_REASONS index
        handled = np.isin(obs.system, HANDLED_SYSTEMS)
        reason[~handled] = 1
        reason[handled & ~np.isfinite(obs.pr_m)] = 2
        sv = np.full((k, 3), np.nan)
        clock = np.zeros(k)
        channel = np.zeros(k)
        for system in np.unique(obs.system[reason == 0]):
            members = np.flatnonzero((obs.system == system) & (reason == 0))
            selector = self.selectors.get(int(system))
            if selector is None:
                reason[members] = 3
                continue
            rows, codes = selector.select(obs.prn[members], obs.gps_s)
            for code, name in SELECT_REASONS.items():
                reason[members[codes == code]] = 1 + SKIP_REASONS.index(name)
            found = members[codes == 0]
            if not found.size:
                continue
            eph = selector.eph
            pos, clk, _ = satellite_states(eph, rows[codes == 0], obs.gps_s, obs.pr_m[found])
            sv[found], clock[found] = pos, clk
            if isinstance(eph, GlonassEphemerides):
                channel[found] = eph.freq_channel[rows[codes == 0]]
        ok = reason == 0
        pr = obs.pr_m + SPEED_OF_LIGHT_MPS * clock
        rough = self._rough_position(sv[ok], pr[ok], obs.system[ok])
        elevation = np.full(k, np.nan)
        atmosphere = np.zeros(k)
        if rough is None:
            reason[ok] = 1 + SKIP_REASONS.index('no_receiver_position')
        else:
            frame = LocalFrame.from_ecef(rough)
            azimuth, elev = corrections.azimuth_elevation(rough, sv[ok], frame.rot_ecef_to_enu)
            elevation[ok] = elev
            atmosphere[ok] = self._atmosphere(frame, azimuth, elev, obs.gps_s,
                                              _carrier_hz(obs.system[ok], channel[ok]))
            low = ok.copy()
            low[ok] = elev < np.radians(self.config.elevation_mask_deg)
            reason[low] = 1 + SKIP_REASONS.index('elevation_mask')
        keep = reason == 0
        counts = np.bincount(reason, minlength=len(SKIP_REASONS) + 1)[1:]
        skipped = {name: int(n) for name, n in zip(SKIP_REASONS, counts) if n}
        epoch = GnssEpoch(
            stamp_ns=int(obs.stamp_ns), sv_pos_ecef_m=sv[keep],
            pr_m=(pr - atmosphere)[keep],
            var_m2=corrections.pseudorange_variance_m2(elevation[keep], obs.cn0_dbhz[keep]),
            sv_id=obs.prn[keep].astype(np.int64), system=obs.system[keep].astype(np.int64),
            elevation_deg=np.degrees(elevation[keep]), cn0_dbhz=obs.cn0_dbhz[keep].copy())
        if rough is not None and keep.sum() >= 4 + np.unique(epoch.system).size:
            # The corrected epoch refines the geometry of the next one.
            better = rough_fix(epoch.sv_pos_ecef_m, epoch.pr_m, epoch.system, rough, 3)
            self.rough_ecef_m = better if better is not None else rough
        return PreprocessResult(epoch, skipped, rough)

    def _rough_position(self, sv: np.ndarray, pr: np.ndarray,
                        system: np.ndarray) -> np.ndarray | None:
        """The receiver position for the corrections: the last one, else a fresh rough
        fix (the first epoch, or after the receiver was lost)."""
        if self.rough_ecef_m is not None:
            return self.rough_ecef_m
        first = rough_fix(sv, pr, system)
        if first is None:
            return None
        # The second pass starts near the solution, where Earth rotation is applied.
        return rough_fix(sv, pr, system, first)

    def _atmosphere(self, frame: LocalFrame, azimuth: np.ndarray, elevation: np.ndarray,
                    gps_s: float, carrier_hz: np.ndarray) -> np.ndarray:
        """Ionospheric + tropospheric delay of each satellite [m] (what is enabled)."""
        lat, lon, height = frame.origin_llh
        lat_rad, lon_rad = np.radians(lat), np.radians(lon)
        delay = np.zeros(elevation.shape)
        nav = self.navigation
        if self.config.ionosphere and nav.klobuchar_alpha is not None:
            l1 = corrections.klobuchar_l1_delay_m(nav.klobuchar_alpha, nav.klobuchar_beta,
                                                  lat_rad, lon_rad, azimuth,
                                                  np.maximum(elevation, 0.0), gps_s)
            delay += l1 * (corrections.FREQ_L1_HZ / carrier_hz) ** 2
        if self.config.troposphere:
            delay += corrections.tropo_delay_m(lat_rad, height, np.maximum(elevation, 0.0))
        return delay


__all__ = ['HANDLED_SYSTEMS', 'KeplerEphemerides', 'GlonassEphemerides', 'Navigation',
           'ObservationEpoch', 'PreprocessConfig', 'PreprocessResult', 'Preprocessor',
           'SKIP_REASONS', 'rough_fix']
