"""Corrupt inputs for the command-line tools, and the checks every refusal must pass.

The one implementation of each corruption (libRSF fields and whole-file faults, image
files, dead writers, unwritable folders): the kit's seeded campaigns (:mod:`.corrupt_data`,
:mod:`.corrupt_vision`: one corruption at a random place of a valid corpus file) and the
tests' tables (test_tools_robustness.py, test_tools_robustness_ros.py: each corruption on
a fixed line, with the message part the refusal must hold) both build from it.
"""
from __future__ import annotations

import os
import struct
import subprocess
import sys
import tempfile
import zlib
from pathlib import Path

import cv2
import numpy as np

# ------------------------------------------------------------------ refusal checks


def refusal_lines(err: str, prog: str) -> list[str]:
    """The tool's own lines on stderr (rcutils and codec noise left out)."""
    return [line for line in err.splitlines() if line.startswith(f'{prog}:')]


def assert_refused(code: int, err: str, expected: int, prog: str, *names,
                   strict: bool = True) -> str:
    """Exit code as documented, no traceback, one error line naming every ``names``.

    Args:
        strict: stderr holds nothing but that line (pure-Python tools); otherwise only the
            tool's own lines are counted (ROS tools: rcutils writes its own log lines).

    Returns:
        The error line.
    """
    assert code == expected, f'exit {code}, expected {expected}; stderr:\n{err}'
    assert 'Traceback' not in err, err
    lines = err.strip().splitlines() if strict else refusal_lines(err, prog)
    assert len(lines) == 1, f'expected one error line, got:\n{err}'
    line = lines[0]
    assert line.startswith(f'{prog}:'), line
    for name in names:
        assert str(name) in line, f'{name} not named in: {line}'
    return line


def snapshot(folder: Path) -> dict:
    """Every entry under ``folder`` with its size and mtime (to prove nothing changed)."""
    out = {}
    for p in sorted(Path(folder).rglob('*')):
        st = p.lstat()
        out[str(p.relative_to(folder))] = (st.st_size, st.st_mtime_ns)
    return out


def hidden_leftovers(folder: Path) -> list[str]:
    """Temporary or partial files a failed run might leave (hidden names)."""
    return [p.name for p in Path(folder).iterdir() if p.name.startswith('.')]


def unwritable_folder(scratch: Path) -> Path:
    """A folder nobody may create files in: a read-only one under ``scratch``, or (as root,
    whom permission bits do not stop) sysfs, which refuses even root.

    Raises:
        RuntimeError: neither refuses writes on this machine.
    """
    ro = Path(scratch) / 'read_only'
    ro.mkdir(exist_ok=True)
    ro.chmod(0o555)
    try:
        probe = tempfile.mkdtemp(dir=ro)
    except OSError:
        return ro
    os.rmdir(probe)
    ro.chmod(0o755)
    ro.rmdir()
    try:
        probe = tempfile.mkdtemp(dir='/sys')
    except OSError:
        return Path('/sys')
    os.rmdir(probe)
    raise RuntimeError('no folder here refuses writes (neither a read-only one nor /sys)')


def dead_pid() -> int:
    """The pid of a process that has ended (a partial output's writer that was killed)."""
    proc = subprocess.Popen([sys.executable, '-c', ''])
    proc.wait()
    return proc.pid


# ----------------------------------------------------------------- libRSF text lines
PR = ['pseudorange3', '0', '19949087.65', '25', '14567933.92', '2809850.97', '21875628.07',
      '12', '1', '85.1', '49']
ODOM = ['odom3', '0', '5.85', '0', '0', '0', '0', '-0.0059', '0.0025', '0.0009', '0.0009',
        '4e-06', '4e-06', '4e-06']
POINT = ['point3', '0', '3785108.11', '899901.49', '5037234.46'] + ['0'] * 9
GOOD_INPUT = ' '.join(ODOM) + '\n' + ' '.join(PR) + '\n'
GOOD_TRUTH = ' '.join(POINT) + '\n'
#: Values no libRSF field may hold (non-finite, absurd, not numbers).
BAD_NUMBERS = ('nan', 'NaN', 'inf', '-inf', '1e308', '-1e308', '1e400', 'x', '0x10', '1,5')


def line_with(fields: list[str], index: int, value: str, time: str = '1') -> str:
    """``fields`` as a line with field ``index`` replaced (time 1 s: after the good line)."""
    out = list(fields)
    out[1] = time
    out[index] = value
    return ' '.join(out) + '\n'


#: One field of one record set to a value the loader must refuse: ``{name: (record tag,
#: field index, value, part of the refusal)}``.
FIELD_FAULTS = {
    'pseudorange_negative': ('pseudorange3', 2, '-2e7', 'pseudorange'),
    'variance_zero': ('pseudorange3', 3, '0', 'variance'),
    'variance_negative': ('pseudorange3', 3, '-25', 'variance'),
    'sv_id_fraction': ('pseudorange3', 7, '12.5', 'not an integer'),
    'sv_id_65536': ('pseudorange3', 7, '65536', 'outside'),
    'sv_id_1e12': ('pseudorange3', 7, '1e12', 'outside'),
    'system_fraction': ('pseudorange3', 8, '3.5', 'not an integer'),
    'elevation_91': ('pseudorange3', 9, '91', 'elevation'),
    'elevation_1e5': ('pseudorange3', 9, '1e5', 'elevation'),
    'cn0_negative': ('pseudorange3', 10, '-1', 'C/N0'),
    'time_beyond_int32': ('pseudorange3', 1, '3e9', 'time'),
    'time_1e20': ('pseudorange3', 1, '1e20', 'time'),
    'speed_101': ('odom3', 2, '101', 'vx'),
    'yaw_rate_11': ('odom3', 7, '11', 'wz'),
}
#: Faults of a whole libRSF file: ``{kind: part of the refusal}`` ('' any refusal; None: a
#: correct loader accepts the file).
FILE_FAULTS = {
    'binary_garbage': '', 'nul_bytes': 'NUL', 'invalid_utf8': 'not a text file',
    'empty': 'no pseudorange3 lines', 'only_comments': 'no pseudorange3 lines',
    'crlf': None, 'comments_blanks': None, 'tabs_trailing': None,
}


def file_fault(kind: str, data: bytes, rng: np.random.Generator) -> bytes:
    """``data`` (a valid libRSF file) with the whole-file fault ``kind`` of
    :data:`FILE_FAULTS` at a place ``rng`` picks."""
    if kind == 'binary_garbage':
        return rng.bytes(int(rng.integers(100, 20000)))
    if kind == 'nul_bytes':
        i = int(rng.integers(len(data)))
        return data[:i] + b'\x00' * int(rng.integers(1, 64)) + data[i:]
    if kind == 'invalid_utf8':
        i = int(rng.integers(len(data)))
        return data[:i] + b'\xff\xfe\xc3' + data[i:]
    if kind == 'empty':
        return b''
    if kind == 'only_comments':
        return b'# nothing here\n# at all\n'
    if kind == 'crlf':
        return data.replace(b'\n', b'\r\n')
    if kind == 'comments_blanks':
        return b'# smartLoc excerpt\n\n' + data.replace(b'\n', b'\n\n', 5)
    if kind == 'tabs_trailing':
        return data.replace(b' ', b'\t', 50).replace(b'\n', b'   \n')
    raise ValueError(f'unknown file fault {kind!r}; known: {sorted(FILE_FAULTS)}')


def librsf_cases() -> list[tuple[str, str, str, str]]:
    """``(id, input text, truth text or '', expected message part)``: malformed files.

    The bad line is always line 3 of the input (line 2 of the truth) unless the case says
    otherwise; the expected part is matched in the error line.
    """
    pr = ' '.join(PR)
    records = {'pseudorange3': PR, 'odom3': ODOM}
    cases = []
    for tag, fields in records.items():
        for n in (1, 2, len(fields) // 2, len(fields) - 1, len(fields) + 1):
            line = ' '.join((fields * 2)[:n]) + '\n'
            cases.append((f'{tag}-{n}-fields', GOOD_INPUT + line, '', ':3:'))
    for name, (tag, index, value, expected) in FIELD_FAULTS.items():
        time = value if index == 1 else '1'
        cases.append((name, GOOD_INPUT + line_with(records[tag], index, value, time), '',
                      expected))
    rng = np.random.default_rng(12)
    for kind, expected in FILE_FAULTS.items():
        for seed in range(8 if kind == 'binary_garbage' else 1):
            if expected is not None:
                text = file_fault(kind, GOOD_INPUT.encode(), rng).decode('latin-1')
                cases.append((f'{kind}-{seed}', text, '', expected))
    cases += [
        ('unknown-tag', GOOD_INPUT + 'gyro3 0 1 2 3\n', '', "unknown record type 'gyro3'"),
        ('long-line', GOOD_INPUT + 'pseudorange3 ' + '1' * 10000 + '\n', '', 'longer than'),
        ('latin1', GOOD_INPUT + 'odom3 0 \xe9\n', '', 'not a text file'),
        ('epochs-back', GOOD_INPUT.replace('pseudorange3 0', 'pseudorange3 5') + pr + '\n', '',
         'not in time order'),
        ('odom-repeated', GOOD_INPUT + ' '.join(ODOM) + '\n', '', 'not increasing'),
        ('satellite-at-centre', GOOD_INPUT + ' '.join(PR[:4] + ['0', '0', '0'] + PR[7:])
         .replace('pseudorange3 0', 'pseudorange3 1') + '\n', '', "Earth's centre"),
        ('satellite-beyond-1e8', GOOD_INPUT + line_with(PR, 4, '9.9e7').replace(
            '2809850.97', '9.9e7'), '', "Earth's centre"),
        ('time-negative', ' '.join(ODOM) + '\n' + ' '.join(PR).replace(
            'pseudorange3 0', 'pseudorange3 -1') + '\n', '', 'time'),
        ('too-many-satellites', GOOD_INPUT + line_with(PR, 1, '1') * 257, '',
         '257 pseudoranges in one epoch'),
        ('no-pseudoranges', ' '.join(ODOM) + '\n', '', 'no pseudorange3 lines'),
        ('truth-empty', GOOD_INPUT, '\n', 'no point3 lines'),
        ('truth-at-centre', GOOD_INPUT, GOOD_TRUTH + ' '.join(
            ['point3', '1', '0', '0', '0'] + ['0'] * 9) + '\n', "Earth's centre"),
        ('truth-in-orbit', GOOD_INPUT, GOOD_TRUTH + ' '.join(
            ['point3', '1', '9e6', '0', '0'] + ['0'] * 9) + '\n', "Earth's centre"),
        ('truth-repeated-stamp', GOOD_INPUT, GOOD_TRUTH * 2, 'not increasing'),
        ('truth-short-line', GOOD_INPUT, GOOD_TRUTH + 'point3 1 2 3\n', 'needs 14 fields'),
        ('truth-pseudorange-tag-garbage', GOOD_INPUT, GOOD_TRUTH + 'point3 x\n',
         'needs 14 fields'),
    ]
    return cases


# ---------------------------------------------------------------------- image files
def png_header(width: int, height: int, colour_type: int = 0) -> bytes:
    """A PNG that declares ``width x height`` (8-bit; ``colour_type`` 0 grey, 2 RGB) and
    holds one tiny IDAT (the pixels need not follow)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack('>I', len(data)) + kind + data
                + struct.pack('>I', zlib.crc32(kind + data) & 0xFFFFFFFF))
    ihdr = struct.pack('>IIBBBBB', width, height, 8, colour_type, 0, 0, 0)
    return (b'\x89PNG\r\n\x1a\n' + chunk(b'IHDR', ihdr)
            + chunk(b'IDAT', zlib.compress(b'\x00' * 64)) + chunk(b'IEND', b''))


def jpeg_header(width: int, height: int) -> bytes:
    """JPEG markers up to a baseline frame header declaring ``width x height``."""
    app0 = b'\xff\xe0' + struct.pack('>H', 16) + b'JFIF\x00\x01\x01\x00\x00\x01\x00\x01\x00\x00'
    sof0 = b'\xff\xc0' + struct.pack('>HBHHB', 11, 8, height, width, 1) + b'\x01\x11\x00'
    return b'\xff\xd8' + app0 + sof0 + b'\xff\xd9'


def bmp_header(width: int, height: int) -> bytes:
    info = struct.pack('<IiiHHIIiiII', 40, width, height, 1, 24, 0, 0, 2835, 2835, 0, 0)
    return b'BM' + struct.pack('<IHHI', 54 + 16, 0, 0, 54) + info + b'\x00' * 16


def gif_header(width: int, height: int) -> bytes:
    return b'GIF89a' + struct.pack('<HHBBB', width, height, 0, 0, 0) + b';'


def webp_header(width: int, height: int) -> bytes:
    vp8x = b'VP8X' + struct.pack('<I', 10) + b'\x00\x00\x00\x00' + (
        (width - 1).to_bytes(3, 'little') + (height - 1).to_bytes(3, 'little'))
    return b'RIFF' + struct.pack('<I', 4 + len(vp8x)) + b'WEBP' + vp8x


#: Faults of one image file: ``{kind: why gnsscam_mapdb refuses it}`` (None: a correct
#: tool uses it, or answers it without a match; ``symlink_outside``: refused by a build as
#: outside the image folder, not readable as an image by a query).
IMAGE_FAULTS = {
    'truncated': 'not a decodable image', 'zero_bytes': 'not a decodable image',
    'garbage': 'not a decodable image', 'text': 'not a decodable image',
    'one_pixel': 'too small', 'two_by_two': 'too small', 'directory': 'not a regular file',
    'missing': 'no such image file', 'huge_dimensions': 'larger than',
    'symlink_outside': None, 'png_named_jpg': None, 'grey_featureless': None,
}


def write_image(kind: str, rng: np.random.Generator, good: bytes, path: Path) -> None:
    """A corrupt image of ``kind`` (:data:`IMAGE_FAULTS`) at ``path``, made from the
    encoded valid image ``good``."""
    if kind == 'truncated':
        path.write_bytes(good[:int(len(good) * rng.uniform(0.01, 0.9))])
    elif kind == 'zero_bytes':
        path.write_bytes(b'')
    elif kind == 'garbage':
        path.write_bytes(rng.bytes(int(rng.integers(10, 50_000))))
    elif kind in ('one_pixel', 'two_by_two'):
        n = 1 if kind == 'one_pixel' else 2
        path.write_bytes(_encoded(rng.integers(0, 256, (n, n, 3), dtype=np.uint8)))
    elif kind == 'text':
        path.write_text('this is not an image\n')
    elif kind == 'directory':
        path.mkdir()
    elif kind == 'missing':
        pass                                # a row naming a file that is not there
    elif kind == 'huge_dimensions':
        side = int(rng.choice([65_535, 100_000, 2**31 - 1]))
        path.write_bytes(png_header(side, side, colour_type=2))
    elif kind == 'symlink_outside':
        os.symlink('/etc/hostname', path)
    elif kind == 'png_named_jpg':
        path.write_bytes(_encoded(cv2.imdecode(np.frombuffer(good, np.uint8),
                                               cv2.IMREAD_COLOR)))
    elif kind == 'grey_featureless':
        path.write_bytes(_encoded(np.full((240, 320, 3), 128, np.uint8), '.jpg'))
    else:
        raise ValueError(f'unknown image fault {kind!r}; known: {sorted(IMAGE_FAULTS)}')


def _encoded(img: np.ndarray, ext: str = '.png') -> bytes:
    return cv2.imencode(ext, img)[1].tobytes()


def image_cases(folder: Path) -> dict[str, str]:
    """Write unusable image files into ``folder``: ``{file name: expected reason part}``."""
    folder = Path(folder)
    rng = np.random.default_rng(7)
    reasons: dict[str, str] = {}
    good_png = _encoded(rng.integers(0, 256, (120, 160, 3), dtype=np.uint8))
    for kind, why in IMAGE_FAULTS.items():
        for k in range({'truncated': 5, 'garbage': 10}.get(kind, 1) if why else 0):
            name = f'{kind}_{k}.png' if kind in ('truncated', 'garbage') else f'{kind}.png'
            write_image(kind, rng, good_png, folder / name)
            reasons[name] = why
    files: dict[str, tuple[bytes, str]] = {}
    for name, shape in (('one_row', (1, 1000, 3)), ('one_column', (1000, 1, 3)),
                        ('ten_pixels', (10, 10)), ('just_too_small', (62, 400))):
        files[f'{name}.png'] = (_encoded(rng.integers(0, 256, shape, dtype=np.uint8)),
                                'too small')
    files['one_pixel.jpg'] = (_encoded(np.zeros((1, 1, 3), np.uint8), '.jpg'), 'too small')
    files['one_pixel.bmp'] = (_encoded(np.zeros((1, 1, 3), np.uint8), '.bmp'), 'too small')
    files['html.png'] = (b'<html><body>404</body></html>', 'not a decodable image')
    for cut in (8, 16, 33, 60):
        files[f'cut_{cut}.png'] = (good_png[:cut], 'not a decodable image')
    files['bomb_wide.png'] = (png_header(2 ** 31 - 1, 1000), 'larger than')
    files['bomb_8001.png'] = (png_header(8001, 8000), 'larger than')
    files['bomb.jpg'] = (jpeg_header(60_000, 60_000), 'larger than')
    files['bomb.bmp'] = (bmp_header(100_000, -100_000), 'larger than')
    files['bomb.gif'] = (gif_header(65_535, 65_535), 'larger than')
    files['bomb.webp'] = (webp_header(16_383, 16_383), 'larger than')
    files['bomb.pgm'] = (b'P5\n# huge\n100000 100000\n255\n' + b'\x00' * 16, 'larger than')
    files['zero_size.png'] = (png_header(0, 0), 'not a decodable image')
    for name, (data, why) in files.items():
        (folder / name).write_bytes(data)
        reasons[name] = why
    with open(folder / 'sparse_300MB.png', 'wb') as f:
        f.truncate(300 * 1024 * 1024)          # no blocks on disk: refused by its size
    reasons['sparse_300MB.png'] = 'larger than an image file may be'
    return reasons
