"""Reading a RINEX file's text and checking its record structure, with line numbers.

georinex reads whatever it can of a damaged file without saying so (a truncated file
gives fewer epochs; a record cut in the middle gives NaNs). Here the text is walked record
by record first: the header (version line, ``END OF HEADER``), then every observation
epoch (its satellite count against the lines that follow) or navigation record (its line
count and its numbers), so that a truncated or corrupt file is refused with the file and
the line. Compression: gzip (``.gz``) and Hatanaka (``.crx``, ``.##d``; via hatanaka).
"""
from __future__ import annotations

import gzip
import math
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import DatasetError

#: Largest file read [bytes after decompression] (a day of 1 Hz multi-GNSS is ~500 MB).
MAX_TEXT_BYTES = 2 * 10**9
#: Lines of one navigation record, by RINEX 3 system letter (RINEX 2: GPS 8, GLONASS 4).
NAV_RECORD_LINES = {'G': 8, 'E': 8, 'C': 8, 'J': 8, 'I': 8, 'R': 4, 'S': 4}


@dataclass(frozen=True)
class RinexHeader:
    """What the structure check learned from a header.

    Attributes:
        version: RINEX version (2.11, 3.05, ...).
        file_type: 'O' observation or a navigation type ('N', 'G', ...).
        time_system: Time system of TIME OF FIRST OBS ('' when not given).
        first_epoch: ISO time of the first observation epoch ('' for navigation files).
        antenna_delta_enu_m: (east, north, up) of the antenna reference point from the
            marker (ANTENNA: DELTA H/E/N) [m].
    """

    version: float
    file_type: str
    time_system: str
    first_epoch: str
    antenna_delta_enu_m: tuple = (0.0, 0.0, 0.0)


def open_text(path: Path) -> str:
    """The text of a RINEX file, gunzipped and Hatanaka-decompressed as needed.

    Raises:
        DatasetError: Missing, unreadable, not gzip/Hatanaka where it claims, or not text.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise DatasetError(f'{path}: cannot open: {err.strerror or err}') from err
    if raw[:2] == b'\x1f\x8b':
        try:
            raw = gzip.decompress(raw)
        except (OSError, EOFError, zlib.error) as err:
            raise DatasetError(f'{path}: corrupt or truncated gzip file ({err})') from err
    if len(raw) > MAX_TEXT_BYTES:
        raise DatasetError(f'{path}: {len(raw)} bytes, more than {MAX_TEXT_BYTES} read')
    if raw[:80].find(b'CRINEX') >= 0:
        import hatanaka     # only for Hatanaka files
        try:
            raw = hatanaka.decompress(raw)
        except Exception as err:   # hatanaka raises ValueError / HatanakaException
            raise DatasetError(f'{path}: corrupt Hatanaka (CRINEX) file: {err}') from err
    if isinstance(raw, str):
        return raw
    try:
        return raw.decode('ascii')
    except UnicodeDecodeError as err:
        line = raw[:err.start].count(b'\n') + 1
        raise DatasetError(f'{path}:{line}: byte {raw[err.start]:#x} is not ASCII text; '
                           'not a RINEX file?') from err


def _header(path: Path, lines: list[str]) -> tuple[RinexHeader, int, dict]:
    """Parse the header; returns it, the index of the first line after it, and the RINEX
    2 observation type count (key 'n_obs') or the RINEX 3 ones per system."""
    if not lines or lines[0][60:80].strip() != 'RINEX VERSION / TYPE':
        raise DatasetError(f'{path}:1: no RINEX VERSION / TYPE line; not a RINEX file')
    try:
        version = float(lines[0][:9])
    except ValueError:
        raise DatasetError(f'{path}:1: RINEX version {lines[0][:9].strip()!r} is not a '
                           'number') from None
    file_type = lines[0][20:21]
    time_system = first = ''
    n_obs: dict = {}
    pending_sys = ''
    delta = (0.0, 0.0, 0.0)
    for i, line in enumerate(lines[:5000]):
        label = line[60:80].strip()
        if label == 'END OF HEADER':
            return RinexHeader(version, file_type, time_system, first, delta), i + 1, n_obs
        if label == 'ANTENNA: DELTA H/E/N':
            try:
                h, e, n = (float(v) for v in line[:42].split())
            except ValueError:
                raise DatasetError(f'{path}:{i + 1}: bad ANTENNA: DELTA H/E/N') from None
            delta = (e, n, h)
        if label == '# / TYPES OF OBSERV' and line[:6].strip():
            n_obs['n_obs'] = _int(path, i, line[:6])
        elif label == 'SYS / # / OBS TYPES':
            if line[0] != ' ':
                pending_sys = line[0]
                n_obs[pending_sys] = _int(path, i, line[3:6])
        elif label == 'TIME OF FIRST OBS':
            try:
                y, mo, d, h, mi = (int(v) for v in line[:30].split())
                sec = float(line[30:43])
            except ValueError:
                raise DatasetError(f'{path}:{i + 1}: bad TIME OF FIRST OBS') from None
            first = f'{y:04d}-{mo:02d}-{d:02d}T{h:02d}:{mi:02d}:{sec:010.7f}'
            time_system = line[48:51].strip()
    raise DatasetError(f'{path}: no END OF HEADER line; truncated or not a RINEX file')


def _int(path: Path, i: int, text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise DatasetError(f'{path}:{i + 1}: {text.strip()!r} is not a count') from None


def _check_obs3(path: Path, lines: list[str], start: int) -> None:
    i = start
    while i < len(lines):
        line = lines[i]
        if not line.strip():
            i += 1
            continue
        if line[:1] != '>':
            raise DatasetError(f'{path}:{i + 1}: expected an epoch line starting with ">"')
        try:
            flag, count = int(line[29:32]), int(line[32:35])
            if flag <= 1:
                [int(v) for v in line[1:19].split()]
                float(line[19:29])
        except ValueError:
            raise DatasetError(f'{path}:{i + 1}: corrupt epoch line') from None
        body = lines[i + 1:i + 1 + count]
        if len(body) < count:
            raise DatasetError(f'{path}:{i + 1}: epoch announces {count} records, the file '
                               f'ends after {len(body)} (truncated)')
        for j, rec in enumerate(body):
            if flag <= 1 and (rec[:1] == '>' or not rec[1:3].strip().isdigit()):
                raise DatasetError(f'{path}:{i + 2 + j}: expected a satellite record of '
                                   f'the epoch at line {i + 1}')
        i += 1 + count


def _check_obs2(path: Path, lines: list[str], start: int, n_obs: int) -> None:
    per_sat = max(1, math.ceil(n_obs / 5))
    i = start
    while i < len(lines):
        line = lines[i]
        if not line.strip():
            i += 1
            continue
        try:
            flag, count = int(line[26:29]), int(line[29:32])
            if flag <= 1:
                [int(v) for v in line[:15].split()]
                float(line[15:26])
        except ValueError:
            raise DatasetError(f'{path}:{i + 1}: corrupt epoch line') from None
        sat_lines = max(1, math.ceil(count / 12)) if flag <= 1 else 0
        body = count * per_sat if flag <= 1 else count
        need = i + sat_lines + body
        if need > len(lines):
            raise DatasetError(f'{path}:{i + 1}: epoch announces {count} records, the file '
                               'ends before them (truncated)')
        i = need


def _value(path: Path, line_no: int, field: str) -> float:
    field = field.strip().replace('D', 'E').replace('d', 'e')
    if not field:
        return float('nan')
    try:
        return float(field)
    except ValueError:
        raise DatasetError(f'{path}:{line_no}: {field!r} is not a number') from None


def _record_epoch(path: Path, line_no: int, text: str, version: float) -> np.datetime64:
    """The epoch of a navigation record's first line (in the system's own time scale)."""
    try:
        parts = text.split()
        y, mo, d, h, mi = (int(v) for v in parts[:5])
        sec = float(parts[5])
    except (ValueError, IndexError):
        raise DatasetError(f'{path}:{line_no}: corrupt navigation record epoch') from None
    if version < 3:
        y += 2000 if y < 80 else 1900
    try:
        return (np.datetime64(f'{y:04d}-{mo:02d}-{d:02d}T{h:02d}:{mi:02d}', 'ns')
                + np.timedelta64(int(round(sec * 1e9)), 'ns'))
    except ValueError:
        raise DatasetError(f'{path}:{line_no}: impossible navigation record date') from None


def _parse_nav(path: Path, header: RinexHeader, lines: list[str], start: int) -> list:
    """Every navigation record: ``(letter, prn, epoch, values)`` with the record's numbers
    in file order (broadcast orbit 0..n; blank fields NaN)."""
    records = []
    i = start
    v2_letter = 'R' if header.file_type == 'G' else 'G'
    while i < len(lines):
        line = lines[i]
        if not line.strip():
            i += 1
            continue
        if header.version >= 3:
            letter = line[:1]
            n = NAV_RECORD_LINES.get(letter)
            if n is None or not line[1:3].strip().isdigit():
                raise DatasetError(f'{path}:{i + 1}: expected a navigation record starting '
                                   'with a satellite (G01, E11, ...)')
            prn, epoch_text, first, rest = int(line[1:3]), line[3:23], 23, 4
        else:
            letter, n = v2_letter, 4 if v2_letter == 'R' else 8
            if not line[:2].strip().isdigit():
                raise DatasetError(f'{path}:{i + 1}: expected a navigation record starting '
                                   'with a satellite number')
            prn, epoch_text, first, rest = int(line[:2]), line[2:22], 22, 3
        if i + n > len(lines):
            raise DatasetError(f'{path}:{i + 1}: navigation record of {n} lines cut short '
                               '(truncated)')
        epoch = _record_epoch(path, i + 1, epoch_text, header.version)
        values = []
        for j in range(n):
            text = lines[i + j]
            offset = first if j == 0 else rest
            count = 3 if j == 0 else 4
            values += [_value(path, i + j + 1, text[offset + 19 * k:offset + 19 * (k + 1)])
                       for k in range(count)]
        records.append((letter, prn, epoch, values))
        i += n
    return records


def read_nav_records(path: Path) -> tuple[RinexHeader, list, dict]:
    """The records of a RINEX 2/3 navigation file (checked as they are read) and the
    header's GPS Klobuchar coefficients (``{'alpha': [4], 'beta': [4]}``, empty when the
    header has none).

    Raises:
        DatasetError: One line naming the file and the line at fault.
    """
    path = Path(path)
    lines = open_text(path).splitlines()
    header, start, _ = _header(path, lines)
    if header.file_type not in ('N', 'G'):
        raise DatasetError(f'{path}:1: RINEX type {header.file_type!r}, a navigation '
                           "file ('N') was expected")
    iono: dict = {}
    for i, line in enumerate(lines[:start]):
        label = line[60:80].strip()
        key = {'ION ALPHA': 'alpha', 'ION BETA': 'beta'}.get(label)
        if key is None and label == 'IONOSPHERIC CORR' and line[:4] in ('GPSA', 'GPSB'):
            key = 'alpha' if line[:4] == 'GPSA' else 'beta'
        if key is not None:
            body = line[2:50] if label.startswith('ION ') else line[5:53]
            iono[key] = [_value(path, i + 1, body[12 * k:12 * (k + 1)]) for k in range(4)]
    records = _parse_nav(path, header, lines, start)
    if not records:
        raise DatasetError(f'{path}: no navigation records after the header')
    return header, records, iono if len(iono) == 2 else {}


def check_structure(path: Path, kind: str) -> tuple[RinexHeader, str]:
    """Read a RINEX file and check its structure (module docstring).

    Args:
        path: The file.
        kind: 'obs' (navigation files are read by :func:`read_nav_records`).

    Returns:
        The header facts and the (decompressed) text.

    Raises:
        DatasetError: One line naming the file, and the line where it applies.
    """
    path = Path(path)
    text = open_text(path)
    lines = text.splitlines()
    header, start, n_obs = _header(path, lines)
    if kind == 'obs':
        if header.file_type != 'O':
            raise DatasetError(f'{path}:1: RINEX type {header.file_type!r}, an observation '
                               "file ('O') was expected")
        if header.version >= 3:
            _check_obs3(path, lines, start)
        else:
            _check_obs2(path, lines, start, n_obs.get('n_obs', 0))
    else:
        raise ValueError(f'unknown kind {kind!r}; navigation files: read_nav_records')
    if start >= len(lines) or not any(line.strip() for line in lines[start:start + 50]):
        raise DatasetError(f'{path}: no records after the header')
    return header, text
