"""Geotags of database images: the position table and the positions CSV (untrusted input:
rows with non-finite or out-of-range positions, or file names outside the image folder,
are skipped by name with the reason)."""
from __future__ import annotations

import csv
import math
import os
import stat
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..core.frames import LocalFrame
from .errors import MapDatabaseError

WGS84_COLUMNS = ('lat', 'lon', 'alt_m')          # degrees, degrees, metres (ellipsoidal)
LOCAL_COLUMNS = ('east_m', 'north_m', 'up_m')    # metres in the local ENU (map) frame

#: Largest coordinate of a database position [m]: local east/north/up and altitude, and
#: the ENU offset of a WGS84 position from the origin (a map spans a city, not the globe;
#: 1e300 would overflow the filter downstream).
MAX_POSITION_M = 1.0e7
#: Largest positions CSV read [bytes] (~50 bytes a row).
MAX_CSV_BYTES = 256 * 1024 ** 2


@dataclass(frozen=True)
class SkippedImage:
    """A CSV row or image left out of a build, and why."""

    filename: str
    reason: str
    line: int | None = None      # CSV line number (header = 1)

    def __str__(self) -> str:
        where = f' (line {self.line})' if self.line is not None else ''
        return f'{self.filename}{where}: {self.reason}'


@dataclass(frozen=True)
class PositionTable:
    """Positions of the database images.

    Attributes:
        columns: Names of the position columns as in the CSV header, in CSV order
            (e.g. ``('lat', 'lon', 'alt_m')`` or ``('east_m', 'north_m')``).
        values: (N, C) float64 values of those columns, as given.
        enu_m: (N, 3) east, north, up [m] in the database's local frame (for WGS84 input:
            the frame at ``origin_llh``; for local input: the coordinates as given, up = 0
            when absent).
        llh: (N, 3) latitude [deg], longitude [deg], ellipsoidal altitude [m] (0 when
            absent), or None for a local-only database.
        origin_llh: Origin of ``enu_m`` for WGS84 input, else None.
    """

    columns: tuple[str, ...]
    values: np.ndarray
    enu_m: np.ndarray
    llh: np.ndarray | None = None
    origin_llh: tuple[float, float, float] | None = None

    def __len__(self) -> int:
        return int(self.enu_m.shape[0])

    def column_dict(self, i: int) -> dict[str, float]:
        """Position columns of image ``i`` as ``{name: value}``."""
        return {c: float(v) for c, v in zip(self.columns, self.values[i])}

    def subset(self, keep: np.ndarray) -> 'PositionTable':
        return PositionTable(self.columns, self.values[keep], self.enu_m[keep],
                             None if self.llh is None else self.llh[keep], self.origin_llh)

    @classmethod
    def from_columns(cls, columns: Sequence[str], values: np.ndarray,
                     origin_llh: tuple[float, float, float] | None = None
                     ) -> 'PositionTable':
        """Interpret position columns (names lower-cased: see module constants).

        Args:
            columns: Column names; must contain ``lat, lon`` or ``east_m, north_m``.
            values: (N, C) float values.
            origin_llh: Local frame origin for WGS84 input (default: the first row).

        Raises:
            ValueError: when neither column set is present or values are out of range.
        """
        columns = tuple(columns)
        values = np.asarray(values, dtype=np.float64).reshape(-1, len(columns))
        key = {c.strip().lower(): i for i, c in enumerate(columns)}

        def col(name, default=0.0):
            return values[:, key[name]] if name in key else np.full(len(values), default)

        llh = None
        if 'lat' in key and 'lon' in key:
            llh = np.stack([col('lat'), col('lon'), col('alt_m')], axis=1)
            if np.any(np.abs(llh[:, 0]) > 90) or np.any(np.abs(llh[:, 1]) > 180):
                raise ValueError('latitude must be in [-90, 90] and longitude in [-180, 180]')
        if 'east_m' in key and 'north_m' in key:
            # Local coordinates win for the ENU array when both sets are given: they are
            # the user's own map frame.
            enu = np.stack([col('east_m'), col('north_m'), col('up_m')], axis=1)
        elif llh is not None:
            if origin_llh is None and len(llh):
                origin_llh = tuple(float(v) for v in llh[0])
            enu = (LocalFrame(*origin_llh).geodetic_to_enu(llh[:, 0], llh[:, 1], llh[:, 2])
                   if len(llh) else np.zeros((0, 3)))
        else:
            raise ValueError(f'position columns must include lat,lon or east_m,north_m; '
                             f'got {list(columns)}')
        if llh is None:
            origin_llh = None
        return cls(columns, values, np.asarray(enu, dtype=np.float64).reshape(-1, 3), llh,
                   None if origin_llh is None else tuple(float(v) for v in origin_llh))


def read_positions_csv(path: str | os.PathLike
                       ) -> tuple[list[tuple[int, str, list[float]]], tuple[str, ...],
                                  list[SkippedImage]]:
    """Read the positions CSV of a build.

    The header must have ``filename`` and ``lat,lon[,alt_m]`` and/or
    ``east_m,north_m[,up_m]`` (case-insensitive); other columns are ignored.

    Returns:
        (rows, position column names as in the header, skipped rows). Each row is
        (line number, filename, values of the position columns).

    Raises:
        MapDatabaseError: naming the file when it is missing, unreadable or lacks columns.
    """
    path = os.fspath(path)
    reader = None
    try:
        info = os.stat(path)
        if not stat.S_ISREG(info.st_mode):
            raise MapDatabaseError(f'{path}: positions CSV is not a regular file')
        if info.st_size > MAX_CSV_BYTES:
            raise MapDatabaseError(f'{path}: positions CSV of {info.st_size / 1e6:.0f} MB is '
                                   f'larger than {MAX_CSV_BYTES / 1e6:.0f} MB')
        with open(path, newline='', encoding='utf-8-sig') as f:
            reader = csv.reader(f)
            header = next(reader, None)
            if header is None:
                raise MapDatabaseError(f'{path}: empty positions CSV (no header)')
            header_line = reader.line_num
            lines = [(reader.line_num, r) for r in reader]
    except FileNotFoundError as err:
        raise MapDatabaseError(f'{path}: no such positions CSV') from err
    except UnicodeDecodeError as err:
        # The text layer decodes ahead of the csv reader: the line is found in the bytes.
        raise MapDatabaseError(f'{_at(path, _undecodable_line(path))}: cannot read positions '
                               f'CSV (not UTF-8 text: {err.reason})') from err
    except csv.Error as err:
        # line_num: the physical lines read, the one at fault included.
        raise MapDatabaseError(f'{_at(path, reader.line_num if reader else None)}: cannot '
                               f'read positions CSV ({err})') from err
    except (OSError, ValueError) as err:
        raise MapDatabaseError(f'{path}: cannot read positions CSV ({err})') from err
    key = {h.strip().lower(): i for i, h in enumerate(header)}
    if 'filename' not in key:
        raise MapDatabaseError(f'{path}:{header_line}: positions CSV needs a "filename" '
                               f'column; header is {header}')
    wanted = [c for c in WGS84_COLUMNS + LOCAL_COLUMNS if c in key]
    if not ({'lat', 'lon'} <= set(wanted) or {'east_m', 'north_m'} <= set(wanted)):
        raise MapDatabaseError(f'{path}:{header_line}: positions CSV needs lat,lon[,alt_m] '
                               f'or east_m,north_m[,up_m] columns; header is {header}')
    idx = sorted(key[c] for c in wanted)          # CSV order
    names = tuple(header[i].strip() for i in idx)
    rows, skipped, seen = [], [], set()
    for line, r in lines:
        if not any(cell.strip() for cell in r):
            continue                               # blank line
        name = r[key['filename']].strip() if len(r) > key['filename'] else ''
        if not name:
            skipped.append(SkippedImage('<no filename>', 'empty filename', line))
            continue
        if name in seen:
            skipped.append(SkippedImage(name, 'duplicate row for this image', line))
            continue
        try:
            vals = [float(r[i]) for i in idx]
        except (IndexError, ValueError):
            skipped.append(SkippedImage(name, 'missing or non-numeric position value', line))
            continue
        if not all(math.isfinite(v) for v in vals):
            skipped.append(SkippedImage(name, 'non-finite position value', line))
            continue
        lowered = {c.lower(): v for c, v in zip(names, vals)}
        if abs(lowered.get('lat', 0.0)) > 90 or abs(lowered.get('lon', 0.0)) > 180:
            skipped.append(SkippedImage(name, 'latitude/longitude out of range', line))
            continue
        metres = [abs(v) for c, v in lowered.items() if c not in ('lat', 'lon')]
        if metres and max(metres) > MAX_POSITION_M:
            skipped.append(SkippedImage(name, f'position value out of range (|value| > '
                                              f'{MAX_POSITION_M:g} m)', line))
            continue
        seen.add(name)
        rows.append((line, name, vals))
    return rows, names, skipped


def _at(path: str, line: int | None) -> str:
    """``PATH:LINE``, or ``PATH`` when the line is unknown (0 or None: nothing read yet)."""
    return f'{path}:{line}' if line else path


def _undecodable_line(path: str) -> int | None:
    """Number of the first line of ``path`` that is not UTF-8, counted as the csv reader
    counts them (``\\n``, ``\\r\\n`` or ``\\r`` ends a line); None if none is found.

    Lines are split on the bytes (latin-1 maps every byte to one character, and no UTF-8
    sequence holds a line-break byte), then each is decoded on its own.
    """
    try:
        with open(path, encoding='latin-1', newline='') as f:
            for number, text in enumerate(f, start=1):
                try:
                    text.encode('latin-1').decode('utf-8-sig' if number == 1 else 'utf-8')
                except UnicodeDecodeError:
                    return number
    except OSError:
        pass
    return None


def _outside(images_dir: str, name: str) -> str | None:
    """Why the CSV file name ``name`` may not be read from ``images_dir``, or None.

    Refused: a NUL byte, and any name whose real path (symbolic links followed) is not
    inside the real path of ``images_dir`` (absolute names, ``..``, links leading out).
    """
    if '\x00' in name:
        return 'file name contains a NUL byte'
    try:
        root = os.path.realpath(images_dir)
        target = os.path.realpath(os.path.join(images_dir, name))
    except (OSError, ValueError) as err:
        return f'file name cannot be resolved ({err})'
    if os.path.commonpath([root, target]) != root or target == root:
        return f'resolves outside the image folder {images_dir} (to {target}); not read'
    return None


# ======================================================================== matches
