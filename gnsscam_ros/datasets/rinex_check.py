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
    """

    version: float
    file_type: str
    time_system: str
    first_epoch: str


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
    for i, line in enumerate(lines[:5000]):
        label = line[60:80].strip()
        if label == 'END OF HEADER':
            return RinexHeader(version, file_type, time_system, first), i + 1, n_obs
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


def _check_nav(path: Path, header: RinexHeader, lines: list[str], start: int) -> None:
    i = start
    v2_lines = 4 if header.file_type == 'G' else 8
    while i < len(lines):
        line = lines[i]
        if not line.strip():
            i += 1
            continue
        if header.version >= 3:
            n = NAV_RECORD_LINES.get(line[:1])
            if n is None or not line[1:3].strip().isdigit():
                raise DatasetError(f'{path}:{i + 1}: expected a navigation record starting '
                                   'with a satellite (G01, E11, ...)')
            first_value = 23
        else:
            n, first_value = v2_lines, 22
        if i + n > len(lines):
            raise DatasetError(f'{path}:{i + 1}: navigation record of {n} lines cut short '
                               '(truncated)')
        for j in range(n):
            text = lines[i + j][first_value if j == 0 else (4 if header.version >= 3 else 3):]
            for k in range(0, len(text.rstrip()), 19):
                field = text[k:k + 19].strip().replace('D', 'E').replace('d', 'e')
                if field:
                    try:
                        float(field)
                    except ValueError:
                        raise DatasetError(f'{path}:{i + j + 1}: {field!r} is not a '
                                           'number') from None
        i += n


def check_structure(path: Path, kind: str) -> tuple[RinexHeader, str]:
    """Read a RINEX file and check its structure (module docstring).

    Args:
        path: The file.
        kind: 'obs' or 'nav' (what the caller needs).

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
        if header.file_type not in ('N', 'G'):
            raise DatasetError(f'{path}:1: RINEX type {header.file_type!r}, a navigation '
                               "file ('N') was expected")
        _check_nav(path, header, lines, start)
    if start >= len(lines) or not any(line.strip() for line in lines[start:start + 50]):
        raise DatasetError(f'{path}: no records after the header')
    return header, text
