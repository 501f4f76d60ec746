"""ORB feature extraction with fixed parameters shared by database build and query.

The same :class:`OrbParams` must be used to build a database and to query it (a different
pyramid or feature count changes the descriptor statistics), so the database stores them.
"""
from __future__ import annotations

import os
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from .errors import ImageError

DESCRIPTOR_BYTES = 32   # ORB: 256 binary tests packed into 32 bytes

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
        if self.nfeatures < 1:
            raise ValueError(f'nfeatures must be >= 1, got {self.nfeatures}')
        if not self.scale_factor > 1.0:
            raise ValueError(f'scale_factor must be > 1, got {self.scale_factor}')
        if self.n_levels < 1:
            raise ValueError(f'n_levels must be >= 1, got {self.n_levels}')
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


def load_gray(path: str | os.PathLike) -> np.ndarray:
    """Read an image file as (H, W) uint8 grey.

    Raises:
        ImageError: naming the file when it is missing, unreadable or not an image.
    """
    path = os.fspath(path)
    try:
        # Read bytes ourselves: cv2.imread returns None for both "missing" and "corrupt",
        # and the build report must say which.
        raw = np.fromfile(path, dtype=np.uint8)
    except FileNotFoundError as err:
        raise ImageError(f'{path}: no such image file') from err
    except OSError as err:
        raise ImageError(f'{path}: cannot read image ({err.strerror or err})') from err
    # Decode to BGR and convert with to_gray() rather than IMREAD_GRAYSCALE: the codecs'
    # own grey conversions (libpng's rgb_to_gray, JPEG's luma plane) differ from
    # cvtColor by a grey level here and there, which changes ORB descriptors, and the
    # camera node converts its BGR frames with cvtColor.
    img = cv2.imdecode(raw, cv2.IMREAD_COLOR) if raw.size else None
    if img is None:
        raise ImageError(f'{path}: not a decodable image ({raw.size} bytes)')
    return to_gray(img)


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
        """Keypoints and (n, 32) uint8 descriptors of an image (mono8 or colour)."""
        kps, desc = self._orb.detectAndCompute(to_gray(image, encoding), None)
        if desc is None:   # OpenCV returns None, not an empty array, when nothing is found
            return (), np.zeros((0, DESCRIPTOR_BYTES), np.uint8)
        return kps, desc

    def descriptors(self, image: np.ndarray, encoding: str = 'bgr8') -> np.ndarray:
        """(n, 32) uint8 ORB descriptors of an image, n <= ``params.nfeatures`` (about)."""
        return self.detect_and_compute(image, encoding)[1]
