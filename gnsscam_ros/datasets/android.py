"""Android GnssLogger raw measurements (``Raw`` rows) -> observation epochs for
``core.preprocess``.

A GnssLogger text log (``# Raw,<columns>`` header, ``Raw,...`` rows) or a Google Smartphone
Decimeter Challenge ``device_gnss.csv`` (``MessageType,<columns>`` header) is read with the
csv module. Per row (Android ``GnssMeasurement`` / ``GnssClock``, the GSDC formulas):

* reception time (GPS time) ``t_rx = TimeNanos + TimeOffsetNanos - (FullBiasNanos +
  BiasNanos)`` [ns since the GPS epoch];
* the satellite's transmission time ``ReceivedSvTimeNanos`` is a time of week for GPS,
  Galileo and QZSS, a BeiDou time of week (GPS - 14 s), a GLONASS time of day (UTC + 3 h);
  ``pseudorange = c (t_rx - t_tx)`` in that time scale, with the week (day) rollover
  removed;
* a row is used when its State says the time is decoded (GPS/Galileo/BeiDou:
  TOW_DECODED or TOW_KNOWN; GLONASS: TOD_DECODED or TOD_KNOWN); rows of other signals than
  L1 C/A, E1, B1I, G1 (L5, E5a, ...) are not used (counted in the drive's info).

Each row's own ``FullBiasNanos`` is used, so that the reception time (which sets where
the satellites are) stays within the phone's clock estimate; GSDC's
``RawPseudorangeMeters`` keeps the first row's for the whole log instead, so the two differ
by ``c`` times the change of ``FullBiasNanos`` (the receiver clock, which the filter
estimates per epoch anyway). Rows are grouped into epochs by ``TimeNanos``. The navigation
comes from RINEX files (``datasets.rinex.read_navigation``).
"""
from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pymap3d

from ..core.ephemeris import BDT_MINUS_GPS_S, SECONDS_PER_WEEK, gps_minus_utc_s
from ..core.preprocess import ObservationEpoch
from ..core.types import BEIDOU, GALILEO, GLONASS, GPS, QZSS, SBAS, Drive, Trajectory
from .errors import DatasetError
from .rinex import check_navigation_covers, posix_stamp_ns, read_navigation
from .rinex_drive import corrected_epochs, static_odometry

SPEED_OF_LIGHT_MPS = 299792458.0
#: Android ``GnssStatus.CONSTELLATION_*`` -> system code (IRNSS: none).
SYSTEM_OF_CONSTELLATION = {1: GPS, 2: SBAS, 3: GLONASS, 4: QZSS, 5: BEIDOU, 6: GALILEO, 7: 0}
#: ``GnssMeasurement.STATE_*`` bits meaning the transmission time is known.
STATE_TOW_DECODED, STATE_TOW_KNOWN = 8, 16384
STATE_GLO_TOD_DECODED, STATE_GLO_TOD_KNOWN = 128, 32768
#: Carrier of the signal used per system [Hz] (GLONASS: any G1 channel).
L1_HZ, B1I_HZ = 1575.42e6, 1561.098e6
COLUMNS = ('TimeNanos', 'FullBiasNanos', 'BiasNanos', 'TimeOffsetNanos', 'Svid',
           'ConstellationType', 'State', 'ReceivedSvTimeNanos', 'Cn0DbHz', 'CarrierFrequencyHz')


@dataclass(frozen=True)
class AndroidLog:
    """Observation epochs of a GnssLogger log.

    Attributes:
        path: The file.
        epochs: Observation epochs in time order.
        rows: Raw rows read.
        rows_not_used: reason -> rows left out ('other_signal', 'time_not_decoded').
    """

    path: Path
    epochs: list
    rows: int
    rows_not_used: dict


def _raw_rows(path: Path) -> tuple[list[str], list[tuple[int, list[str]]]]:
    """Header columns and ``(line, fields)`` of the Raw rows."""
    header: list[str] | None = None
    rows = []
    try:
        with path.open('r', encoding='utf-8', newline='') as handle:
            for line_no, fields in enumerate(csv.reader(handle), start=1):
                if not fields:
                    continue
                first = fields[0].strip()
                if first in ('# Raw', 'MessageType') and header is None:
                    header = [f.strip() for f in fields[1:]]
                elif first == 'Raw':
                    rows.append((line_no, fields[1:]))
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise DatasetError(f'{path}: cannot read: {err}') from err
    if header is None:
        raise DatasetError(f'{path}: no "# Raw," header line; not a GnssLogger log')
    missing = [c for c in COLUMNS if c not in header]
    if missing:
        raise DatasetError(f'{path}: Raw header lacks {missing}')
    if not rows:
        raise DatasetError(f'{path}: no Raw rows')
    return header, rows


def _number(path: Path, line_no: int, name: str, text: str) -> float:
    try:
        return float(text) if text.strip() else (0.0 if name in ('BiasNanos',
                                                                 'TimeOffsetNanos')
                                                 else float('nan'))
    except ValueError:
        raise DatasetError(f'{path}:{line_no}: {name} {text!r} is not a number') from None


def pseudoranges_m(t_rx_gps_ns: np.ndarray, tx_ns: np.ndarray,
                   system: np.ndarray) -> np.ndarray:
    """Pseudoranges [m] from the reception time (GPS ns since the GPS epoch) and the
    received satellite time of each row, in the system's own time of week / day."""
    week_ns = int(SECONDS_PER_WEEK * 1e9)
    day_ns = 86400 * 10**9
    t_rx = t_rx_gps_ns.astype(np.int64)
    leap_ns = np.array([int(gps_minus_utc_s(t / 1e9) * 1e9) for t in t_rx], dtype=np.int64)
    local = np.where(system == BEIDOU, (t_rx + int(BDT_MINUS_GPS_S * 1e9)) % week_ns,
                     np.where(system == GLONASS, (t_rx - leap_ns + 3 * 3600 * 10**9) % day_ns,
                              t_rx % week_ns))
    period = np.where(system == GLONASS, day_ns, week_ns)
    travel = local - tx_ns.astype(np.int64)
    travel = np.where(travel < -period // 2, travel + period, travel)     # rollover
    return travel * 1e-9 * SPEED_OF_LIGHT_MPS


def read_android_log(path: Path) -> AndroidLog:
    """The observation epochs of a GnssLogger log (module docstring).

    Raises:
        DatasetError: Unreadable file, missing columns, a number that is not one (file and
            line named), or no usable row.
    """
    path = Path(path)
    header, rows = _raw_rows(path)
    col = {name: header.index(name) for name in COLUMNS}
    values = np.array([[_number(path, line_no, name, f[col[name]] if col[name] < len(f)
                                else '') for name in COLUMNS] for line_no, f in rows])
    v = {name: values[:, i] for i, name in enumerate(COLUMNS)}
    # Integers of 19 digits lose precision in a float: the clock terms are read again.
    exact = {name: np.array([int(float(f[col[name]] or 0)) if name != 'FullBiasNanos'
                             else int(f[col[name]]) for _, f in rows], dtype=np.int64)
             for name in ('TimeNanos', 'FullBiasNanos', 'ReceivedSvTimeNanos')}
    t_rx = (exact['TimeNanos'] - exact['FullBiasNanos']
            + np.round(v['TimeOffsetNanos'] - v['BiasNanos']).astype(np.int64))
    system = np.array([SYSTEM_OF_CONSTELLATION.get(int(c), 0) for c in v['ConstellationType']])
    freq = v['CarrierFrequencyHz']
    glonass = system == GLONASS
    l1 = np.where(system == BEIDOU, np.abs(freq - B1I_HZ) < 1e6,
                  np.where(glonass, np.abs(freq - 1602e6) < 10e6, np.abs(freq - L1_HZ) < 1e6))
    state = v['State'].astype(np.int64)
    decoded = np.where(glonass, state & (STATE_GLO_TOD_DECODED | STATE_GLO_TOD_KNOWN),
                       state & (STATE_TOW_DECODED | STATE_TOW_KNOWN)) != 0
    pr = pseudoranges_m(t_rx, exact['ReceivedSvTimeNanos'], system)
    pr = np.where(decoded, pr, np.nan)
    not_used = {'other_signal': int((~l1).sum()), 'time_not_decoded': int((l1 & ~decoded).sum())}
    epochs = []
    stamps = exact['TimeNanos']
    for stamp in np.unique(stamps[l1]):
        k = l1 & (stamps == stamp)
        t0 = int(t_rx[k][0])
        epochs.append(ObservationEpoch(
            stamp_ns=posix_stamp_ns(t0), gps_s=t0 / 1e9, system=system[k],
            prn=v['Svid'][k].astype(np.int64), pr_m=pr[k], cn0_dbhz=v['Cn0DbHz'][k]))
    if not epochs:
        raise DatasetError(f'{path}: no L1/E1/B1I/G1 measurement rows')
    return AndroidLog(path, epochs, len(rows), {k: n for k, n in not_used.items() if n})


def read_ground_truth(path: Path) -> Trajectory:
    """A GSDC ``ground_truth.csv`` (``LatitudeDegrees``, ``LongitudeDegrees``,
    ``AltitudeMeters``, ``UnixTimeMillis``) as a trajectory (stamps: UTC POSIX ns).

    Raises:
        DatasetError: Unreadable, missing columns, or not a number (file and line named).
    """
    path = Path(path)
    try:
        with path.open('r', encoding='utf-8', newline='') as handle:
            rows = list(csv.DictReader(handle))
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise DatasetError(f'{path}: cannot read: {err}') from err
    names = ('LatitudeDegrees', 'LongitudeDegrees', 'AltitudeMeters', 'UnixTimeMillis')
    if not rows or any(n not in rows[0] for n in names):
        raise DatasetError(f'{path}: needs the columns {list(names)}')
    values = np.array([[_number(path, i + 2, n, r[n] or '') for n in names]
                       for i, r in enumerate(rows)])
    ecef = np.stack(pymap3d.geodetic2ecef(values[:, 0], values[:, 1], values[:, 2]), axis=1)
    stamps = (values[:, 3] * 1e6).astype(np.int64)
    if np.any(np.diff(stamps) <= 0):
        raise DatasetError(f'{path}: UnixTimeMillis not increasing')
    return Trajectory(stamp_ns=stamps, ecef_m=ecef)


def load_android(log_path: Path, nav_paths: list[Path], static: bool = False,
                 truth_path: Path | None = None,
                 systems: tuple[int, ...] | None = None) -> Drive:
    """A GnssLogger log with RINEX broadcast navigation as a Drive (as
    :func:`.rinex_drive.load_rinex`).

    Raises:
        DatasetError: Unreadable files, navigation of another time, no usable epoch.
    """
    if not nav_paths:
        raise DatasetError('give at least one navigation file (--nav)')
    log = read_android_log(Path(log_path))
    nav = read_navigation([Path(p) for p in nav_paths])
    check_navigation_covers(nav, log)
    epochs, skipped, unusable = corrected_epochs(log.path, log.epochs, nav, None, systems)
    truth = read_ground_truth(truth_path) if truth_path is not None else None
    return Drive(
        name=Path(log_path).stem, origin_llh=None, gnss=epochs,
        odometry=(static_odometry(epochs[0].stamp_ns, epochs[-1].stamp_ns) if static
                  else None), imu=None, truth=truth,
        info={'observations': str(log.path), 'navigation': list(nav.sources),
              'static': bool(static), 'systems': None if systems is None else list(systems),
              'epochs': len(epochs), 'epochs_unusable': unusable,
              'skipped_satellites': skipped, 'rows_not_used': log.rows_not_used,
              'license': 'Google Smartphone Decimeter Challenge data'})
