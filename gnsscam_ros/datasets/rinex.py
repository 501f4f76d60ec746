"""RINEX observation and broadcast navigation files -> a Drive of corrected epochs.

Observation files are read by georinex (RINEX 2.11 and 3.0x, gzip) with hatanaka for
Hatanaka-compressed ``.crx``/``.crx.gz`` files; navigation files by the record reader of
:mod:`.rinex_check` (georinex 1.16.2 loses Galileo and BeiDou records); the orbit and
correction maths is the project's core (``core.ephemeris``, ``core.corrections``,
``core.preprocess``).
Why these libraries: ``docs/rinex.md`` (gnss_lib_py measured against them; pyrtklib by
install size and API only).

Before georinex parses a file, :func:`check_structure` walks its records and refuses a
truncated or corrupt one with the file and line (georinex reads what it can of a damaged
file without saying so).

Signals used (single frequency, the first present in this order): GPS ``C1C C1W C1P C1X``
(RINEX 2 ``C1 P1``); GLONASS ``C1C C1P`` (``C1 P1``); Galileo ``C1C C1X C1B`` (``C1``);
BeiDou B1I ``C2I C2X C2Q`` (RINEX 3.01 ``C1I C1Q``). C/N0 is the matching ``S`` code when
the file gives dB-Hz (RINEX 3 always; RINEX 2 when the values are above 10, else they are
the 0-9 signal-strength flags some converters write, and C/N0 is unknown).

Navigation records kept: GPS, Galileo I/NAV (the E1 group delay ``BGD(E1,E5b)``; F/NAV
records carry the E5a one), BeiDou D1/D2 (``TGD1`` for B1I), GLONASS. Health: the record's
health field is zero (GPS SV health, Galileo health and validity bits, BeiDou SatH1,
GLONASS health).
"""
from __future__ import annotations

import dataclasses
import io
import warnings
from pathlib import Path

import numpy as np

from ..core.ephemeris import (BDT_MINUS_GPS_S, BDT_WEEK_OFFSET, MAX_AGE_S, SECONDS_PER_WEEK,
                              GlonassEphemerides, KeplerEphemerides, gps_minus_utc_s)
from ..core.preprocess import Navigation, ObservationEpoch
from ..core.types import BEIDOU, GALILEO, GLONASS, GPS, QZSS, SBAS
from .errors import DatasetError
from .rinex_check import check_structure, read_nav_records

#: RINEX system letter -> system code (0: a system the wire has no code for).
SYSTEM_OF_LETTER = {'G': GPS, 'R': GLONASS, 'E': GALILEO, 'C': BEIDOU, 'J': QZSS, 'S': SBAS,
                    'I': 0}
#: Code observations tried per system, first present wins (module docstring).
CODE_PRIORITY = {GPS: ('C1C', 'C1W', 'C1P', 'C1X', 'C1', 'P1'),
                 GLONASS: ('C1C', 'C1P', 'C1', 'P1'),
                 GALILEO: ('C1C', 'C1X', 'C1B', 'C1'),
                 BEIDOU: ('C2I', 'C2X', 'C2Q')}
CODE_PRIORITY_BEIDOU_301 = ('C1I', 'C1Q')
GPS_EPOCH = np.datetime64('1980-01-06T00:00:00', 'ns')
#: POSIX ns of the GPS epoch (1980-01-06 00:00:00 UTC).
GPS_EPOCH_POSIX_NS = 315964800 * 10**9


def gps_seconds(times: np.ndarray) -> np.ndarray:
    """datetime64 labels in a system's time scale -> seconds since the GPS epoch."""
    return (np.asarray(times, dtype='datetime64[ns]') - GPS_EPOCH).astype(np.int64) / 1e9


def posix_stamp_ns(gps_ns: int) -> int:
    """GPS time [ns since the GPS epoch] -> UTC as POSIX ns (ROS time): minus leap seconds."""
    return int(gps_ns) + GPS_EPOCH_POSIX_NS - int(gps_minus_utc_s(gps_ns / 1e9) * 1e9)


def _georinex_load(path: Path, text: str, **kwargs):
    """georinex.load of a file's checked text, its failures and warnings turned into one
    DatasetError line naming the file."""
    import georinex     # xarray + pandas: ~1 s to import, only when a RINEX file is read
    try:
        with warnings.catch_warnings():
            warnings.simplefilter('ignore')
            return georinex.load(io.StringIO(text), **kwargs)
    except Exception as err:        # georinex raises ValueError, KeyError, IndexError...
        raise DatasetError(f'{path}: not a readable RINEX file ({type(err).__name__}: '
                           f'{err})') from err


# ----------------------------------------------------------------------- navigation
#: Keplerian record layout (RINEX 3 table A8/A10/A14, RINEX 2 table A4): index of each
#: number in a record (epoch line first: af0 af1 af2, then broadcast orbits 1-7).
KEPLER_FIELDS = {'af0': 0, 'af1': 1, 'af2': 2, 'crs': 4, 'delta_n': 5, 'm0': 6, 'cuc': 7,
                 'ecc': 8, 'cus': 9, 'sqrt_a': 10, 'toe': 11, 'cic': 12, 'omega0': 13,
                 'cis': 14, 'i0': 15, 'crc': 16, 'omega': 17, 'omega_dot': 18, 'idot': 19,
                 'data_source': 20, 'week': 21, 'health': 24, 'group_a': 25, 'group_b': 26}
#: GLONASS record layout (RINEX 3 table A11): -TauN, +GammaN, then X, Y, Z blocks.
GLONASS_FIELDS = {'tau_n': 0, 'gamma_n': 1, 'x': 3, 'vx': 4, 'ax': 5, 'health': 6, 'y': 7,
                  'vy': 8, 'ay': 9, 'channel': 10, 'z': 11, 'vz': 12, 'az': 13}


def _kepler(system: int, epochs: np.ndarray, prn: np.ndarray,
            v: np.ndarray) -> KeplerEphemerides:
    """Keplerian records of one system; ``v`` is (n, 29) in the KEPLER_FIELDS layout."""
    f = {name: v[:, i] for name, i in KEPLER_FIELDS.items()}
    if system == BEIDOU:
        week = f['week'] + BDT_WEEK_OFFSET
        shift = -BDT_MINUS_GPS_S                     # BDT labels -> GPS seconds: + 14 s
        group = f['group_a']                         # TGD1 (B1I)
    elif system == GALILEO:
        week, shift, group = f['week'], 0.0, f['group_b']   # BGD(E1, E5b), I/NAV
    else:
        week, shift, group = f['week'], 0.0, f['group_a']   # TGD
    toe = week * SECONDS_PER_WEEK + f['toe'] + shift
    return KeplerEphemerides(
        system=system, prn=prn, toe_s=toe, toe_sow_s=f['toe'],
        toc_s=gps_seconds(epochs) + shift,
        af0_s=f['af0'], af1=f['af1'], af2_per_s=np.nan_to_num(f['af2']),
        group_delay_s=np.nan_to_num(group),
        healthy=(f['health'] == 0) & np.isfinite(toe) & np.isfinite(f['sqrt_a']),
        sqrt_a=f['sqrt_a'], ecc=f['ecc'], i0=f['i0'], idot=f['idot'], omega0=f['omega0'],
        omega_dot=f['omega_dot'], omega=f['omega'], m0=f['m0'], delta_n=f['delta_n'],
        cuc=f['cuc'], cus=f['cus'], crc=f['crc'], crs=f['crs'], cic=f['cic'], cis=f['cis'])


def _glonass(epochs: np.ndarray, prn: np.ndarray, v: np.ndarray) -> GlonassEphemerides:
    """GLONASS records; the epochs are UTC."""
    f = {name: v[:, i] for name, i in GLONASS_FIELDS.items()}
    utc = gps_seconds(epochs)
    toe = utc + np.array([gps_minus_utc_s(t) for t in utc])
    # RINEX stores km, km/s, km/s^2.
    return GlonassEphemerides(
        prn=prn, toe_s=toe, pos_m=np.stack([f['x'], f['y'], f['z']], axis=1) * 1e3,
        vel_mps=np.stack([f['vx'], f['vy'], f['vz']], axis=1) * 1e3,
        acc_mps2=np.stack([f['ax'], f['ay'], f['az']], axis=1) * 1e3,
        tau_n_s=f['tau_n'], gamma_n=f['gamma_n'], freq_channel=np.nan_to_num(f['channel']),
        healthy=f['health'] == 0)


def _concat(parts: list):
    """Records of one system from several files, as one set."""
    if len(parts) == 1:
        return parts[0]
    merged = {}
    for fld in dataclasses.fields(parts[0]):
        first = getattr(parts[0], fld.name)
        merged[fld.name] = (np.concatenate([getattr(p, fld.name) for p in parts])
                            if isinstance(first, np.ndarray) else first)
    return type(parts[0])(**merged)


def read_navigation(paths: list[Path]) -> Navigation:
    """Broadcast navigation from one or more RINEX 2/3 navigation files.

    Parsed by :func:`.rinex_check.read_nav_records` (fixed-format records, checked with
    line numbers): georinex 1.16 returns empty arrays for the RINEX 3.03/3.05 Galileo
    and BeiDou files of ``data/rinex/nya1`` without an error (``docs/rinex.md``).

    Raises:
        DatasetError: A file is missing, truncated, corrupt or holds no record of a
            handled system (file, and line where it applies, named).
    """
    by_system: dict[int, list] = {}
    alpha = beta = None
    for path in map(Path, paths):
        _, records, iono = read_nav_records(path)
        if alpha is None and iono:
            alpha, beta = np.asarray(iono['alpha']), np.asarray(iono['beta'])
        found = False
        for letter in sorted({r[0] for r in records}):
            system = SYSTEM_OF_LETTER.get(letter, 0)
            if system not in (GPS, GLONASS, GALILEO, BEIDOU):
                continue
            mine = [r for r in records if r[0] == letter]
            width = max(len(r[3]) for r in mine)
            values = np.array([r[3] + [np.nan] * (width - len(r[3])) for r in mine])
            epochs = np.array([r[2] for r in mine], dtype='datetime64[ns]')
            prn = np.array([r[1] for r in mine], dtype=np.int64)
            if system == GLONASS:
                part = _glonass(epochs, prn, values)
            else:
                if system == GALILEO:
                    # I/NAV records (data source bits 0 or 2): the E1 group delay.
                    source = np.nan_to_num(values[:, KEPLER_FIELDS['data_source']])
                    inav = (source.astype(np.int64) & 0b101) != 0
                    epochs, prn, values = epochs[inav], prn[inav], values[inav]
                part = _kepler(system, epochs, prn, values)
            by_system.setdefault(system, []).append(part)
            found = found or len(part) > 0
        if not found:
            raise DatasetError(f'{path}: no GPS, GLONASS, Galileo or BeiDou navigation '
                               'records')
    return Navigation(ephemerides={s: _concat(p) for s, p in by_system.items()},
                      klobuchar_alpha=alpha, klobuchar_beta=beta,
                      sources=tuple(str(p) for p in paths))


# ----------------------------------------------------------------------- observations
@dataclasses.dataclass(frozen=True)
class ObservationFile:
    """The code observations of a RINEX observation file.

    Attributes:
        path: The file.
        epochs: Observation epochs in time order (satellites with no observation at all
            in an epoch are left out of it).
        approx_ecef_m: The header's APPROX POSITION XYZ [m] (None when absent or zero).
        interval_s: Nominal epoch interval [s] (from the stamps).
        antenna_delta_enu_m: (3,) antenna reference point from the marker, local ENU [m].
    """

    path: Path
    epochs: list
    approx_ecef_m: np.ndarray | None
    interval_s: float
    antenna_delta_enu_m: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))


def _pick_code(ds, names: np.ndarray, version: float) -> tuple[np.ndarray, np.ndarray]:
    """(time, sv) pseudorange and C/N0 of the signal of each satellite's system."""
    shape = (ds.sizes['time'], ds.sizes['sv'])
    pr = np.full(shape, np.nan)
    cn0 = np.full(shape, np.nan)
    systems = np.array([SYSTEM_OF_LETTER.get(n[0], 0) for n in names])
    for system, codes in CODE_PRIORITY.items():
        if system == BEIDOU and version < 3.02:
            codes = CODE_PRIORITY_BEIDOU_301
        cols = systems == system
        for code in codes:
            if code not in ds.data_vars or not cols.any():
                continue
            values = np.asarray(ds[code].values, dtype=float)[:, cols]
            strength = ('S' + code[1:]) if ('S' + code[1:]) in ds.data_vars else None
            snr = (np.asarray(ds[strength].values, dtype=float)[:, cols] if strength
                   else np.full(values.shape, np.nan))
            if version < 3.0 and np.nanmax(snr, initial=0.0) <= 10.0:
                snr = np.full(values.shape, np.nan)      # 0-9 flags, not dB-Hz
            sub_pr, sub_cn0 = pr[:, cols], cn0[:, cols]
            take = ~np.isfinite(sub_pr) & np.isfinite(values) & (values > 0.0)
            sub_pr[take], sub_cn0[take] = values[take], snr[take]
            pr[:, cols], cn0[:, cols] = sub_pr, sub_cn0
    return pr, cn0


def read_observations(path: Path, duration_s: float | None = None) -> ObservationFile:
    """The code observations of a RINEX 2/3 observation file (``.crx(.gz)`` too).

    Args:
        path: The file.
        duration_s: Read only the first seconds [s] (None: all).

    Raises:
        DatasetError: Missing, truncated or corrupt file (line named where it applies),
            a time system other than GPS, or no epoch.
    """
    path = Path(path)
    header, text = check_structure(path, 'obs')
    if header.time_system not in ('GPS', ''):
        raise DatasetError(f'{path}: observation time system {header.time_system}; only '
                           'GPS time is read')
    kwargs = {}
    if duration_s:
        start = np.datetime64(header.first_epoch, 'ns')
        end = start + np.timedelta64(int(duration_s * 1e9), 'ns')
        kwargs['tlim'] = (str(start), str(end))
    ds = _georinex_load(path, text, **kwargs)
    if 'time' not in ds.sizes or ds.sizes['time'] == 0:
        raise DatasetError(f'{path}: no observation epochs')
    names = np.asarray(ds.sv.values).astype(str)
    version = float(ds.attrs.get('version', header.version))
    pr, cn0 = _pick_code(ds, names, version)
    # A satellite with any observation in the epoch (code or not) is listed, so that one
    # without the code used is counted as skipped ('no_signal').
    seen = np.zeros(pr.shape, dtype=bool)
    for var in ds.data_vars:
        if var[:1] in 'CLDSP':
            seen |= np.isfinite(np.asarray(ds[var].values, dtype=float))
    gps_ns = (np.asarray(ds.time.values, dtype='datetime64[ns]') - GPS_EPOCH).astype(np.int64)
    systems = np.array([SYSTEM_OF_LETTER.get(n[0], 0) for n in names], dtype=np.int64)
    prns = np.array([int(n[1:]) if n[1:].strip().isdigit() else 0 for n in names])
    epochs = []
    for i in range(pr.shape[0]):
        cols = seen[i]
        epochs.append(ObservationEpoch(
            stamp_ns=posix_stamp_ns(int(gps_ns[i])), gps_s=gps_ns[i] / 1e9,
            system=systems[cols], prn=prns[cols], pr_m=pr[i, cols], cn0_dbhz=cn0[i, cols]))
    approx = ds.attrs.get('position')
    approx = (np.asarray(approx, dtype=float) if approx is not None
              and np.linalg.norm(approx) > 1e6 else None)
    interval = float(np.median(np.diff(gps_ns)) / 1e9) if len(gps_ns) > 1 else 0.0
    return ObservationFile(path, epochs, approx, interval,
                           np.asarray(header.antenna_delta_enu_m, dtype=float))


def check_navigation_covers(nav: Navigation, obs: ObservationFile) -> None:
    """Refuse navigation data that cannot serve the observations (e.g. another day).

    Raises:
        DatasetError: No navigation record within the usable age of any observation epoch
            (files and both time spans named).
    """
    span = nav.span_s()
    t0, t1 = obs.epochs[0].gps_s, obs.epochs[-1].gps_s
    slack = max(MAX_AGE_S.values())
    if span is None or span[1] < t0 - slack or span[0] > t1 + slack:
        def day(t):
            return str(GPS_EPOCH + np.timedelta64(int(t * 1e9), 'ns'))[:19]
        covered = f'{day(span[0])} .. {day(span[1])}' if span else 'nothing'
        raise DatasetError(f"{', '.join(nav.sources)}: navigation covers {covered}, the "
                           f'observations of {obs.path} are {day(t0)} .. {day(t1)} '
                           '(navigation of another day?)')


__all__ = ['ObservationFile', 'check_navigation_covers', 'gps_seconds',
           'posix_stamp_ns', 'read_navigation', 'read_observations']
