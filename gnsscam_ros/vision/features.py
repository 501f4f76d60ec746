"""ORB feature extraction with fixed parameters shared by database build and query.

The same :class:`OrbParams` must be used to build a database and to query it (a different
pyramid or feature count changes the descriptor statistics), so the database stores them.
"""
from __future__ import annotations

import os
import stat
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from .errors import ImageError

DESCRIPTOR_BYTES = 32   # ORB: 256 binary tests packed into 32 bytes

#: Largest image file read [bytes]: a 64 Mpx PNG is ~100-200 MB; more is not a photo.
MAX_IMAGE_FILE_BYTES = 256 * 1024 * 1024
#: Largest image decoded [pixels] (8000 x 8000): checked from the file's header before
#: decoding (PNG, JPEG, BMP, GIF, WebP, PNM), so a "decompression bomb" (a small file that
#: declares a huge image) is refused before its pixels are allocated. Other formats are
#: checked after decoding (OpenCV's own limit, 2**30 pixels, bounds them meanwhile).
MAX_IMAGE_PIXELS = 64_000_000

_SCORE_TYPES = {'harris': cv2.ORB_HARRIS_SCORE, 'fast': cv2.ORB_FAST_SCORE}


@dataclass(frozen=True)
class OrbParams:
    """ORB detector settings (see ``cv2.ORB_create``).

    Attributes:
        nfeatures: Maximum number of features per image; fixed so that every image gets a
            comparable term-frequency budget.
        scale_factor: Pyramid decimation ratio between levels (> 1).
        n_levels: Number of pyramid levels.
        edge_threshold: Border without features [px]; also the descriptor patch size.
        fast_threshold: FAST corner intensity threshold [grey levels].
        score_type: ``'harris'`` (more repeatable) or ``'fast'`` (slightly quicker) ranking.
    """

    nfeatures: int = 1000
    scale_factor: float = 1.2
    n_levels: int = 8
    edge_threshold: int = 31
    fast_threshold: int = 20
    score_type: str = 'harris'

    def __post_init__(self):
        # Upper bounds too: OpenCV takes C ints, and a database file carries these values
        # (an absurd one would fail in ORB_create at the first query, not at load).
        if not 1 <= self.nfeatures <= 1_000_000:
            raise ValueError(f'nfeatures must be in [1, 1000000], got {self.nfeatures}')
        if not 1.0 < self.scale_factor <= 4.0:
            raise ValueError(f'scale_factor must be in (1, 4], got {self.scale_factor}')
        if not 1 <= self.n_levels <= 32:
            raise ValueError(f'n_levels must be in [1, 32], got {self.n_levels}')
        if not 1 <= self.edge_threshold <= 1000:
            raise ValueError(f'edge_threshold must be in [1, 1000], got {self.edge_threshold}')
        if not 0 <= self.fast_threshold <= 255:
            raise ValueError(f'fast_threshold must be in [0, 255], got {self.fast_threshold}')
        if self.score_type not in _SCORE_TYPES:
            raise ValueError(f'score_type must be one of {sorted(_SCORE_TYPES)}, '
                             f'got {self.score_type!r}')

    def as_dict(self) -> dict:
        return asdict(self)


def to_gray(image: np.ndarray, encoding: str = 'bgr8') -> np.ndarray:
    """Convert an 8-bit image to a contiguous single-channel (H, W) uint8 array.

    Args:
        image: (H, W) or (H, W, 1) mono8, (H, W, 3) colour or (H, W, 4) colour + alpha,
            dtype uint8.
        encoding: Channel order of colour images: ``'bgr8'`` (OpenCV) or ``'rgb8'``
            (as in many ``sensor_msgs/Image`` streams); ignored for mono images.

    Returns:
        (H, W) uint8 grey image.

    Raises:
        ImageError: for a non-uint8 dtype or an unsupported shape.
    """
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise ImageError(f'expected a uint8 image, got dtype {img.dtype}')
    if img.size == 0:
        raise ImageError(f'empty image {img.shape}')
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 2:
        return np.ascontiguousarray(img)
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        raise ImageError(f'expected (H, W), (H, W, 3) or (H, W, 4) image, got {img.shape}')
    if encoding not in ('bgr8', 'rgb8'):
        raise ImageError(f"encoding must be 'bgr8' or 'rgb8', got {encoding!r}")
    rgb = encoding == 'rgb8'
    if img.shape[2] == 3:
        code = cv2.COLOR_RGB2GRAY if rgb else cv2.COLOR_BGR2GRAY
    else:
        code = cv2.COLOR_RGBA2GRAY if rgb else cv2.COLOR_BGRA2GRAY
    return cv2.cvtColor(np.ascontiguousarray(img), code)


def header_size(head: bytes) -> tuple[int, int] | None:
    """``(width, height)`` declared by an image file's first bytes, without decoding.

    Knows PNG, JPEG, BMP, GIF, WebP and PNM; None for other formats or a header it cannot
    read (decoding then decides).
    """
    try:
        if head[:8] == b'\x89PNG\r\n\x1a\n' and head[12:16] == b'IHDR':
            return int.from_bytes(head[16:20], 'big'), int.from_bytes(head[20:24], 'big')
        if head[:2] == b'\xff\xd8':
            return _jpeg_size(head)
        if head[:2] == b'BM' and len(head) >= 26:
            return (abs(int.from_bytes(head[18:22], 'little', signed=True)),
                    abs(int.from_bytes(head[22:26], 'little', signed=True)))
        if head[:6] in (b'GIF87a', b'GIF89a'):
            return int.from_bytes(head[6:8], 'little'), int.from_bytes(head[8:10], 'little')
        if head[:4] == b'RIFF' and head[8:12] == b'WEBP':
            return _webp_size(head)
        if len(head) > 2 and head[:1] == b'P' and head[1:2] in b'123456':
            return _pnm_size(head)
    except (IndexError, ValueError):
        return None
    return None


def _jpeg_size(head: bytes) -> tuple[int, int] | None:
    """Size from the first SOF segment (markers C0-CF except C4, C8, CC)."""
    i = 2
    while i + 9 < len(head):
        if head[i] != 0xFF:
            return None
        marker = head[i + 1]
        if marker == 0xFF:                # fill byte
            i += 1
            continue
        if marker in (0x01, 0xD8) or 0xD0 <= marker <= 0xD7:
            i += 2                        # markers without a length
            continue
        length = int.from_bytes(head[i + 2:i + 4], 'big')
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            return (int.from_bytes(head[i + 7:i + 9], 'big'),
                    int.from_bytes(head[i + 5:i + 7], 'big'))
        if marker == 0xDA or length < 2:  # scan data before a frame header: corrupt
            return None
        i += 2 + length
    return None


def _webp_size(head: bytes) -> tuple[int, int] | None:
    chunk = head[12:16]
    if chunk == b'VP8X':
        return (int.from_bytes(head[24:27], 'little') + 1,
                int.from_bytes(head[27:30], 'little') + 1)
    if chunk == b'VP8L':
        bits = int.from_bytes(head[21:25], 'little')
        return (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1
    if chunk == b'VP8 ':
        return (int.from_bytes(head[26:28], 'little') & 0x3FFF,
                int.from_bytes(head[28:30], 'little') & 0x3FFF)
    return None


def _pnm_size(head: bytes) -> tuple[int, int] | None:
    """Width and height: the first two numbers after the magic (comments skipped)."""
    text = b'\n'.join(line.split(b'#', 1)[0] for line in head[2:].split(b'\n'))
    numbers = text.split()
    if len(numbers) < 2:
        return None
    return int(numbers[0]), int(numbers[1])


def _check_pixels(path: str, width: int, height: int, when: str) -> None:
    if width * height > MAX_IMAGE_PIXELS:
        raise ImageError(f'{path}: {width}x{height} px image ({when}) is larger than '
                         f'{MAX_IMAGE_PIXELS / 1e6:g} Mpx')


def load_gray(path: str | os.PathLike) -> np.ndarray:
    """Read an image file as (H, W) uint8 grey.

    Files larger than :data:`MAX_IMAGE_FILE_BYTES`, images larger than
    :data:`MAX_IMAGE_PIXELS` (judged from the header when the format allows, before
    decoding) and anything but a regular file are refused.

    Raises:
        ImageError: naming the file when it is missing, unreadable, not an image or too
            large.
    """
    path = os.fspath(path)
    try:
        info = os.stat(path)
        if not stat.S_ISREG(info.st_mode):
            # A device (/dev/zero) or a pipe would be read without end.
            raise ImageError(f'{path}: not a regular file')
        if info.st_size > MAX_IMAGE_FILE_BYTES:
            raise ImageError(f'{path}: {info.st_size / 1e6:.0f} MB is larger than an image '
                             f'file may be ({MAX_IMAGE_FILE_BYTES / 1e6:.0f} MB)')
        # Read bytes ourselves: cv2.imread returns None for both "missing" and "corrupt",
        # and the build report must say which.
        raw = np.fromfile(path, dtype=np.uint8, count=MAX_IMAGE_FILE_BYTES + 1)
    except FileNotFoundError as err:
        raise ImageError(f'{path}: no such image file') from err
    except (OSError, ValueError) as err:   # ValueError: a NUL byte in the name
        raise ImageError(f'{path}: cannot read image '
                         f'({getattr(err, "strerror", None) or err})') from err
    if raw.size > MAX_IMAGE_FILE_BYTES:       # grew while being read
        raise ImageError(f'{path}: larger than an image file may be '
                         f'({MAX_IMAGE_FILE_BYTES / 1e6:.0f} MB)')
    declared = header_size(raw[:65536].tobytes())
    if declared is not None:
        _check_pixels(path, *declared, 'declared in its header')
    # Decode to BGR and convert with to_gray() rather than IMREAD_GRAYSCALE: the codecs'
    # own grey conversions (libpng's rgb_to_gray, JPEG's luma plane) differ from
    # cvtColor by a grey level here and there, which changes ORB descriptors, and the
    # camera node converts its BGR frames with cvtColor.
    try:
        img = cv2.imdecode(raw, cv2.IMREAD_COLOR) if raw.size else None
    except cv2.error as err:             # a codec's assertion on a corrupt file
        raise ImageError(f'{path}: not a decodable image ({raw.size} bytes): '
                         f'{_cv_message(err)}') from err
    if img is None:
        raise ImageError(f'{path}: not a decodable image ({raw.size} bytes)')
    _check_pixels(path, img.shape[1], img.shape[0], 'decoded')
    return to_gray(img)


def _cv_message(err: Exception) -> str:
    """The reason in an OpenCV error, on one line (OpenCV's text spans several)."""
    text = ' '.join(str(err).split())
    return text.split(') ', 1)[-1] if text.startswith('OpenCV(') else text


def min_image_side(params: 'OrbParams') -> int:
    """Smallest width and height [px] in which ORB can place a feature: its border of
    ``edge_threshold`` pixels on both sides plus one (smaller images have none, and
    OpenCV's pyramid asserts on 1-pixel ones)."""
    return 2 * int(params.edge_threshold) + 1


class OrbExtractor:
    """ORB keypoints and descriptors with fixed :class:`OrbParams`.

    One instance is not safe to share between threads (OpenCV keeps per-call state in the
    detector object); create one per thread.
    """

    def __init__(self, params: OrbParams | None = None):
        self.params = params or OrbParams()
        p = self.params
        self._orb = cv2.ORB_create(
            nfeatures=int(p.nfeatures), scaleFactor=float(p.scale_factor),
            nlevels=int(p.n_levels), edgeThreshold=int(p.edge_threshold),
            patchSize=int(p.edge_threshold), fastThreshold=int(p.fast_threshold),
            scoreType=_SCORE_TYPES[p.score_type])

    def detect_and_compute(self, image: np.ndarray, encoding: str = 'bgr8'
                           ) -> tuple[tuple, np.ndarray]:
        """Keypoints and (n, 32) uint8 descriptors of an image (mono8 or colour).

        Raises:
            ImageError: Unsupported layout, or an image smaller than
                :func:`min_image_side` on a side (too small for any ORB feature).
        """
        gray = to_gray(image, encoding)
        side = min_image_side(self.params)
        if gray.shape[0] < side or gray.shape[1] < side:
            raise ImageError(f'{gray.shape[1]}x{gray.shape[0]} px image is too small for ORB '
                             f'features (at least {side}x{side} px)')
        try:
            kps, desc = self._orb.detectAndCompute(gray, None)
        except cv2.error as err:      # never an OpenCV assertion with a C++ traceback
            raise ImageError(f'ORB failed on a {gray.shape[1]}x{gray.shape[0]} px image: '
                             f'{_cv_message(err)}') from err
        if desc is None:   # OpenCV returns None, not an empty array, when nothing is found
            return (), np.zeros((0, DESCRIPTOR_BYTES), np.uint8)
        return kps, desc

    def descriptors(self, image: np.ndarray, encoding: str = 'bgr8') -> np.ndarray:
        """(n, 32) uint8 ORB descriptors of an image, n <= ``params.nfeatures`` (about)."""
        return self.detect_and_compute(image, encoding)[1]
