"""Loader for the smartLoc dataset in the libRSF text format.

Each line is one measurement, whitespace separated, identified by its first token
(``readme.txt`` of the dataset):

* ``pseudorange3 t pr var x y z sv_id system elevation cn0`` (11 fields)
* ``odom3 t vx vy vz wx wy wz cov_vx cov_vy cov_vz cov_wx cov_wy cov_wz`` (14 fields)
* ``point3 t x y z c11 ... c33`` (14 fields, ground truth in ECEF)

Every value is checked where it is read, against the physical limits of
:data:`FIELD_LIMITS` (finite everything; a time a ROS stamp can hold; pseudoranges,
variances, satellite and receiver positions, speeds and rates a road vehicle and a GNSS
constellation can have), and at most :data:`MAX_SATELLITES_PER_EPOCH` pseudoranges share a
time stamp. A line outside them is refused with the file and line
(:class:`~.errors.DatasetError`), so that nothing absurd (NaN, 1e308) reaches the filter
or the JSON written at the end. Lines longer than :data:`MAX_LINE_CHARS` are refused too
(a binary or garbage file is not read into memory whole).

smartLoc data: Copyright 2016-2022 P. Reisdorf, T. Pfeifer, J. Bressler, S. Bauer,
P. Weissig, S. Lange (TU Chemnitz), CC BY-SA 4.0.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..core.types import Drive, GnssEpoch, OdometrySeries, Trajectory
from .errors import DatasetError

_FIELDS = {'pseudorange3': 11, 'odom3': 14, 'point3': 14}

#: Longest line read [characters]; libRSF lines are ~100-200.
MAX_LINE_CHARS = 4096
#: Most pseudoranges in one epoch (GPS + GLONASS + Galileo + BeiDou in view, a few
#: signals each, stay below it; smartLoc has at most 17). Beyond it one epoch's cost and
#: memory in the filter grow without bound.
MAX_SATELLITES_PER_EPOCH = 256
#: Largest time stamp [s]: builtin_interfaces/Time.sec is an int32.
MAX_TIME_S = 2.0 ** 31 - 1
#: Satellite distance from the Earth's centre [m]: above the surface, below 100,000 km
#: (GNSS orbits: 25,500-42,200 km).
SATELLITE_RADIUS_M = (6.3e6, 1.0e8)
#: Receiver (ground truth) distance from the Earth's centre [m]: near the surface (polar
#: radius 6,357 km, equatorial 6,378 km; -400 m to 600 km height and more to spare).
RECEIVER_RADIUS_M = (6.0e6, 7.0e6)

#: Per record type, per field after the tag: ``(name, lowest, highest, integer)``. A value
#: outside is refused with file and line.
FIELD_LIMITS: dict[str, tuple[tuple[str, float, float, bool], ...]] = {
    'pseudorange3': (
        ('time [s]', 0.0, MAX_TIME_S, False),
        ('pseudorange [m]', 1.0, 1.0e8, False),        # 100,000 km: far beyond GEO
        ('variance [m^2]', 1e-6, 1.0e10, False),        # sigma up to 100 km; > 0
        ('satellite x [m]', -1.0e8, 1.0e8, False),
        ('satellite y [m]', -1.0e8, 1.0e8, False),
        ('satellite z [m]', -1.0e8, 1.0e8, False),
        ('satellite id', 0.0, 65535.0, True),           # uint16 on the wire
        ('system', 0.0, 255.0, True),                   # uint8 on the wire
        ('elevation [deg]', -90.0, 90.0, False),
        ('C/N0 [dB-Hz]', 0.0, 100.0, False),
    ),
    'odom3': (
        ('time [s]', 0.0, MAX_TIME_S, False),
        *((f'{axis} [m/s]', -100.0, 100.0, False) for axis in ('vx', 'vy', 'vz')),
        *((f'{axis} [rad/s]', -10.0, 10.0, False) for axis in ('wx', 'wy', 'wz')),
        *((f'variance of {axis}', 0.0, 1.0e6, False)
          for axis in ('vx', 'vy', 'vz', 'wx', 'wy', 'wz')),
    ),
    'point3': (
        ('time [s]', 0.0, MAX_TIME_S, False),
        *((f'{axis} [m]', -1.0e7, 1.0e7, False) for axis in ('x', 'y', 'z')),
        *((f'covariance c{i}{j} [m^2]', -1.0e12, 1.0e12, False)
          for i in (1, 2, 3) for j in (1, 2, 3)),
    ),
}


def _seconds_to_ns(t_s: float) -> int:
    return int(round(t_s * 1e9))


def read_records(path: Path) -> dict[str, list[tuple[int, list[float]]]]:
    """Parse a libRSF text file into ``{tag: [(line_no, values), ...]}``.

    Args:
        path: File to read.

    Returns:
        The numeric fields (after the tag) of every line, grouped by tag.

    Raises:
        DatasetError: The file is missing or unreadable, or a line has an unknown tag, the
            wrong number of fields, a field that is not a number or a value outside
            :data:`FIELD_LIMITS` (file and line named).
    """
    path = Path(path)
    records: dict[str, list[tuple[int, list[float]]]] = {tag: [] for tag in _FIELDS}
    try:
        handle = path.open('r', encoding='utf-8')
    except OSError as err:
        raise DatasetError(f'{path}: cannot open: {err.strerror or err}') from err
    with handle:
        try:
            line_no = 0
            # readline with a limit: a garbage file without newlines is not read whole.
            for line in iter(lambda: handle.readline(MAX_LINE_CHARS + 1), ''):
                line_no += 1
                if len(line) > MAX_LINE_CHARS:
                    raise DatasetError(f'{path}:{line_no}: line longer than {MAX_LINE_CHARS} '
                                       'characters; not a libRSF text file?')
                if '\x00' in line:
                    raise DatasetError(f'{path}:{line_no}: NUL byte; not a text file')
                tokens = line.split()
                if not tokens or tokens[0].startswith('#'):
                    continue
                tag = tokens[0]
                if tag not in _FIELDS:
                    raise DatasetError(f'{path}:{line_no}: unknown record type '
                                       f'{_shown(tag)}')
                if len(tokens) != _FIELDS[tag]:
                    raise DatasetError(
                        f'{path}:{line_no}: {tag} needs {_FIELDS[tag]} fields, '
                        f'got {len(tokens)}')
                values = []
                for (name, _, _, _), tok in zip(FIELD_LIMITS[tag], tokens[1:]):
                    try:
                        values.append(float(tok))
                    except ValueError:
                        raise DatasetError(f'{path}:{line_no}: {tag}: {name} '
                                           f'{_shown(tok)} is not a number') from None
                _check_values(path, line_no, tag, values)
                records[tag].append((line_no, values))
        except UnicodeDecodeError as err:
            raise DatasetError(f'{path}:{line_no + 1}: not a text file (UTF-8: '
                               f'{err.reason})') from err
        except OSError as err:
            raise DatasetError(f'{path}: cannot read: {err.strerror or err}') from err
    return records


def _shown(token: str, limit: int = 40) -> str:
    """A token for an error message: quoted, cut short."""
    return repr(token if len(token) <= limit else token[:limit] + '...')


def _check_values(path: Path, line_no: int, tag: str, values: list[float]) -> None:
    """Refuse a line whose values leave :data:`FIELD_LIMITS` (or the radius limits)."""
    for (name, lo, hi, integer), value in zip(FIELD_LIMITS[tag], values):
        if not math.isfinite(value):
            raise DatasetError(f'{path}:{line_no}: {tag}: {name} is {value}, not finite')
        if not lo <= value <= hi:
            raise DatasetError(f'{path}:{line_no}: {tag}: {name} {value:g} is outside '
                               f'[{lo:g}, {hi:g}]')
        if integer and value != int(value):
            raise DatasetError(f'{path}:{line_no}: {tag}: {name} {value:g} is not an '
                               'integer')
    if tag in ('pseudorange3', 'point3'):
        lo, hi = SATELLITE_RADIUS_M if tag == 'pseudorange3' else RECEIVER_RADIUS_M
        xyz = values[3:6] if tag == 'pseudorange3' else values[1:4]
        radius = math.sqrt(sum(v * v for v in xyz))
        what = 'satellite' if tag == 'pseudorange3' else 'position'
        if not lo <= radius <= hi:
            raise DatasetError(f'{path}:{line_no}: {tag}: {what} {radius:.6g} m from the '
                               f"Earth's centre is outside [{lo:g}, {hi:g}] m (ECEF)")


def _gnss_epochs(rows: list[tuple[int, list[float]]], path: Path) -> list[GnssEpoch]:
    """Group pseudorange rows by time stamp into epochs, in file order."""
    if not rows:
        return []
    data = np.array([values for _, values in rows], dtype=float)
    stamps = np.array([_seconds_to_ns(t) for t in data[:, 0]], dtype=np.int64)
    # Epoch boundaries: where the stamp changes (the files are written epoch by epoch).
    starts = np.flatnonzero(np.r_[True, stamps[1:] != stamps[:-1]])
    ends = np.r_[starts[1:], len(stamps)]
    epochs = []
    for s, e in zip(starts, ends):
        if e - s > MAX_SATELLITES_PER_EPOCH:
            raise DatasetError(f'{path}:{rows[int(s)][0]}: {e - s} pseudoranges in one epoch, '
                               f'more than {MAX_SATELLITES_PER_EPOCH}')
        block = data[s:e]
        epochs.append(GnssEpoch(
            stamp_ns=int(stamps[s]), pr_m=block[:, 1].copy(), var_m2=block[:, 2].copy(),
            sv_pos_ecef_m=block[:, 3:6].copy(), sv_id=block[:, 6].astype(np.int64),
            system=block[:, 7].astype(np.int64), elevation_deg=block[:, 8].copy(),
            cn0_dbhz=block[:, 9].copy()))
    order = np.array([ep.stamp_ns for ep in epochs])
    if np.any(np.diff(order) <= 0):
        bad = int(np.flatnonzero(np.diff(order) <= 0)[0]) + 1
        line_no = rows[int(starts[bad])][0]
        raise DatasetError(f'{path}:{line_no}: pseudorange epochs are not in time order')
    return epochs


def _odometry(rows: list[tuple[int, list[float]]], path: Path) -> OdometrySeries | None:
    if not rows:
        return None
    data = np.array([values for _, values in rows], dtype=float)
    stamps = np.array([_seconds_to_ns(t) for t in data[:, 0]], dtype=np.int64)
    if np.any(np.diff(stamps) <= 0):
        bad = int(np.flatnonzero(np.diff(stamps) <= 0)[0]) + 1
        raise DatasetError(f'{path}:{rows[bad][0]}: odom3 time stamps are not increasing')
    # Vehicle frame: x forward; yaw rate is the turn rate about z.
    return OdometrySeries(stamp_ns=stamps, speed_mps=data[:, 1].copy(),
                          yaw_rate_rps=data[:, 6].copy(), speed_var=data[:, 7].copy(),
                          yaw_rate_var=data[:, 12].copy())


def _truth(rows: list[tuple[int, list[float]]], path: Path) -> Trajectory | None:
    if not rows:
        return None
    data = np.array([values for _, values in rows], dtype=float)
    stamps = np.array([_seconds_to_ns(t) for t in data[:, 0]], dtype=np.int64)
    # The evaluation interpolates the truth in time: its stamps must increase.
    if np.any(np.diff(stamps) <= 0):
        bad = int(np.flatnonzero(np.diff(stamps) <= 0)[0]) + 1
        raise DatasetError(f'{path}:{rows[bad][0]}: point3 time stamps are not increasing')
    return Trajectory(stamp_ns=stamps, ecef_m=data[:, 1:4].copy())


def discover_files(folder: Path) -> tuple[Path, Path | None]:
    """Find the input and ground-truth files in a smartLoc folder.

    The input file is the ``*Input*.txt`` (or the only ``.txt`` holding pseudoranges); the
    ground truth is the matching ``*GT*.txt`` when present.

    Raises:
        DatasetError: No or several candidate input files.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f'{folder}: not a directory')
    inputs = sorted(p for p in folder.glob('*.txt') if 'input' in p.name.lower())
    if len(inputs) != 1:
        raise DatasetError(
            f'{folder}: expected exactly one *Input*.txt file, found '
            f'{[p.name for p in inputs] or "none"}; pass --input and --truth explicitly')
    stem = inputs[0].name.lower().replace('input', 'gt')
    truths = [p for p in folder.glob('*.txt') if p.name.lower() == stem]
    return inputs[0], (truths[0] if truths else None)


def load_smartloc(input_path: Path, truth_path: Path | None = None,
                  name: str | None = None) -> Drive:
    """Load a smartLoc run (pseudoranges, odometry and optional ground truth).

    Args:
        input_path: The ``*_Input.txt`` file (pseudorange3 and odom3 lines).
        truth_path: The ``*_GT.txt`` file (point3 lines), or None.
        name: Name for the run; defaults to the input file's stem.

    Returns:
        A Drive with ``origin_llh=None`` (the filter anchors its map frame at the first
        robust fix) and the ground truth attached for evaluation only.

    Raises:
        DatasetError: Unreadable or malformed file (file and line named), or no pseudoranges.
    """
    input_path = Path(input_path)
    records = read_records(input_path)
    epochs = _gnss_epochs(records['pseudorange3'], input_path)
    if not epochs:
        raise DatasetError(f'{input_path}: no pseudorange3 lines')
    odometry = _odometry(records['odom3'], input_path)
    truth = None
    if truth_path is not None:
        truth_records = read_records(Path(truth_path))
        truth = _truth(truth_records['point3'], Path(truth_path))
        if truth is None:
            raise DatasetError(f'{truth_path}: no point3 lines')
    return Drive(name=name or input_path.stem.replace('_Input', ''), origin_llh=None,
                 gnss=epochs, odometry=odometry, imu=None, truth=truth,
                 info={'input': str(input_path),
                       'truth': str(truth_path) if truth_path else None,
                       'license': 'smartLoc dataset, TU Chemnitz, CC BY-SA 4.0'})


def load_smartloc_args(folder: Path | None, input_path: Path | None = None,
                       truth_path: Path | None = None) -> Drive:
    """Load a run named the way the command-line tools take it.

    Either explicit ``input_path`` (and optional ``truth_path``), or a ``folder`` whose
    input and ground-truth files are discovered (:func:`discover_files`); an explicit
    ``truth_path`` wins over the discovered one.

    Raises:
        DatasetError: Nothing to load, or the files are missing or malformed.
    """
    if input_path is not None:
        return load_smartloc(input_path, truth_path)
    if folder is None:
        raise DatasetError('give a smartLoc folder or --input/--truth')
    found_input, found_truth = discover_files(folder)
    return load_smartloc(found_input, truth_path or found_truth)
