"""Corrupt inputs for the command-line tools, and the checks every refusal must pass.

Shared by test_tools_robustness.py (gnsscam_eval, gnsscam_convert, gnsscam_mapdb, partial
outputs) and test_tools_robustness_ros.py (gnsscam_replay, gnsscam_record). Each table
entry is cheap to make, so the tests try many variants in-process through the tools'
``main(argv)``.
"""
from __future__ import annotations

import os
import struct
import tempfile
import zlib
from pathlib import Path

import numpy as np
import pytest

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


def unwritable_folder(tmp_path: Path) -> Path:
    """A folder nobody may create files in: a read-only one, or (as root, whom permission
    bits do not stop) sysfs, which refuses even root; skips the test when neither works."""
    ro = tmp_path / 'read_only'
    ro.mkdir()
    ro.chmod(0o555)
    try:
        probe = tempfile.mkdtemp(dir=ro)
    except OSError:
        return ro
    os.rmdir(probe)
    ro.chmod(0o755)
    try:
        probe = tempfile.mkdtemp(dir='/sys')
    except OSError:
        return Path('/sys')
    os.rmdir(probe)
    pytest.skip('no folder here refuses writes')


def dead_pid() -> int:
    """The pid of a process that has ended (a partial output's writer that was killed)."""
    import subprocess
    import sys
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


def librsf_cases() -> list[tuple[str, str, str, str]]:
    """``(id, input text, truth text or '', expected message part)``: malformed files.

    The bad line is always line 3 of the input (line 2 of the truth) unless the case says
    otherwise; the expected part is matched in the error line.
    """
    pr = ' '.join(PR)
    cases = []
    for tag, fields in (('pseudorange3', PR), ('odom3', ODOM)):
        for n in (1, 2, len(fields) // 2, len(fields) - 1, len(fields) + 1):
            line = ' '.join((fields * 2)[:n]) + '\n'
            cases.append((f'{tag}-{n}-fields', GOOD_INPUT + line, '', ':3:'))
    cases += [
        ('unknown-tag', GOOD_INPUT + 'gyro3 0 1 2 3\n', '', "unknown record type 'gyro3'"),
        ('long-line', GOOD_INPUT + 'pseudorange3 ' + '1' * 10000 + '\n', '', 'longer than'),
        ('nul-byte', GOOD_INPUT + pr.replace('25', '2\x005') + '\n', '', 'NUL'),
        ('latin1', GOOD_INPUT + 'odom3 0 \xe9\n', '', 'not a text file'),
        ('epochs-back', GOOD_INPUT.replace('pseudorange3 0', 'pseudorange3 5') + pr + '\n', '',
         'not in time order'),
        ('odom-repeated', GOOD_INPUT + ' '.join(ODOM) + '\n', '', 'not increasing'),
        ('sv-id-fraction', GOOD_INPUT + line_with(PR, 7, '12.5'), '', 'not an integer'),
        ('system-fraction', GOOD_INPUT + line_with(PR, 8, '1.5'), '', 'not an integer'),
        ('sv-id-65536', GOOD_INPUT + line_with(PR, 7, '65536'), '', 'outside'),
        ('satellite-at-centre', GOOD_INPUT + ' '.join(PR[:4] + ['0', '0', '0'] + PR[7:])
         .replace('pseudorange3 0', 'pseudorange3 1') + '\n', '', "Earth's centre"),
        ('satellite-beyond-1e8', GOOD_INPUT + line_with(PR, 4, '9.9e7').replace(
            '2809850.97', '9.9e7'), '', "Earth's centre"),
        ('variance-zero', GOOD_INPUT + line_with(PR, 3, '0'), '', 'variance'),
        ('variance-negative', GOOD_INPUT + line_with(PR, 3, '-25'), '', 'variance'),
        ('pseudorange-negative', GOOD_INPUT + line_with(PR, 2, '-2e7'), '', 'pseudorange'),
        ('elevation-91', GOOD_INPUT + line_with(PR, 9, '91'), '', 'elevation'),
        ('cn0-negative', GOOD_INPUT + line_with(PR, 10, '-1'), '', 'C/N0'),
        ('speed-101', GOOD_INPUT + line_with(ODOM, 2, '101'), '', 'vx'),
        ('yaw-rate-11', GOOD_INPUT + line_with(ODOM, 7, '11'), '', 'wz'),
        ('time-negative', ' '.join(ODOM) + '\n' + ' '.join(PR).replace(
            'pseudorange3 0', 'pseudorange3 -1') + '\n', '', 'time'),
        ('time-beyond-int32', GOOD_INPUT + line_with(PR, 1, '3e9'), '', 'time'),
        ('too-many-satellites', GOOD_INPUT + line_with(PR, 1, '1') * 257, '',
         '257 pseudoranges in one epoch'),
        ('no-pseudoranges', ' '.join(ODOM) + '\n', '', 'no pseudorange3 lines'),
        ('empty', '', '', 'no pseudorange3 lines'),
        ('comments-only', '# nothing\n# here\n', '', 'no pseudorange3 lines'),
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
    rng = np.random.default_rng(12)
    for seed in range(8):
        junk = rng.integers(0, 256, 64 + 97 * seed, dtype=np.uint8).tobytes()
        cases.append((f'binary-{seed}', junk.decode('latin-1'), '', ''))
    return cases


# ---------------------------------------------------------------------- image files
def png_header(width: int, height: int) -> bytes:
    """A PNG that declares ``width x height`` (8-bit grey) and holds one tiny IDAT."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack('>I', len(data)) + kind + data
                + struct.pack('>I', zlib.crc32(kind + data) & 0xFFFFFFFF))
    ihdr = struct.pack('>IIBBBBB', width, height, 8, 0, 0, 0, 0)
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


def image_cases(folder: Path) -> dict[str, str]:
    """Write unusable image files into ``folder``: ``{file name: expected reason part}``."""
    import cv2
    folder = Path(folder)
    rng = np.random.default_rng(7)
    files: dict[str, tuple[bytes, str]] = {}

    def encoded(img, ext='.png') -> bytes:
        return cv2.imencode(ext, img)[1].tobytes()

    noise = rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)
    for name, shape in (('one_pixel', (1, 1, 3)), ('one_row', (1, 1000, 3)),
                        ('one_column', (1000, 1, 3)), ('ten_pixels', (10, 10)),
                        ('just_too_small', (62, 400)), ('grey_2x2', (2, 2))):
        files[f'{name}.png'] = (encoded(rng.integers(0, 256, shape, dtype=np.uint8)),
                                'too small')
    files['one_pixel.jpg'] = (encoded(np.zeros((1, 1, 3), np.uint8), '.jpg'), 'too small')
    files['one_pixel.bmp'] = (encoded(np.zeros((1, 1, 3), np.uint8), '.bmp'), 'too small')
    good_png = encoded(noise)
    files['empty.png'] = (b'', 'not a decodable image')
    files['text.jpg'] = (b'hello, world\n', 'not a decodable image')
    files['html.png'] = (b'<html><body>404</body></html>', 'not a decodable image')
    for cut in (8, 16, 33, 60, len(good_png) // 3):
        files[f'cut_{cut}.png'] = (good_png[:cut], 'not a decodable image')
    for seed in range(10):
        junk = rng.integers(0, 256, 200 + 300 * seed, dtype=np.uint8).tobytes()
        files[f'garbage_{seed}.png'] = (junk, 'not a decodable image')
    files['bomb.png'] = (png_header(100_000, 100_000), 'larger than')
    files['bomb_wide.png'] = (png_header(2 ** 31 - 1, 1000), 'larger than')
    files['bomb_8001.png'] = (png_header(8001, 8000), 'larger than')
    files['bomb.jpg'] = (jpeg_header(60_000, 60_000), 'larger than')
    files['bomb.bmp'] = (bmp_header(100_000, -100_000), 'larger than')
    files['bomb.gif'] = (gif_header(65_535, 65_535), 'larger than')
    files['bomb.webp'] = (webp_header(16_383, 16_383), 'larger than')
    files['bomb.pgm'] = (b'P5\n# huge\n100000 100000\n255\n' + b'\x00' * 16, 'larger than')
    files['zero_size.png'] = (png_header(0, 0), 'not a decodable image')
    for name, (data, _) in files.items():
        (folder / name).write_bytes(data)
    (folder / 'a_folder.png').mkdir()
    reasons = {name: why for name, (_, why) in files.items()}
    reasons['a_folder.png'] = 'not a regular file'
    with open(folder / 'sparse_300MB.png', 'wb') as f:
        f.truncate(300 * 1024 * 1024)          # no blocks on disk: refused by its size
    reasons['sparse_300MB.png'] = 'larger than an image file may be'
    return reasons
