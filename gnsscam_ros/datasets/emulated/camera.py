"""Camera stream of the emulated drive: rendered frames with recorded camera faults.

The forward camera of the emulated drive sees the procedural city of :mod:`..city`
rendered by :mod:`.render`: real images on which ORB finds and matches features. The
stream (:func:`make_camera_stream`) is the drive itself at ``rate_hz`` (10 Hz), camera at
the truth pose (antenna position, level, looking along the direction of travel), one
lighting for the whole drive (sunny by default) with a slow per-frame exposure drift and
sensor noise. Camera faults as in the paper (§7.2) hit random frames: a 21x21 Gaussian
blur, or an occlusion, a filled rectangle of 25-50 % of the image height and width at a
random place. Which frames are faulty, and how, is drawn up front from the seeded
``'camera'`` stream and recorded (:attr:`CameraStream.fault`,
:attr:`CameraStream.fault_box`), so the evaluation knows them. Images are rendered lazily
by :meth:`CameraStream.image` (a drive has ~2,000-4,500 frames; they are never all held in
memory) and are a deterministic function of the frame index.

The map database the frames are matched against is another pass through the city
(:mod:`.views`, :mod:`.map_database`).
"""
from __future__ import annotations

import dataclasses
import math
import threading
from dataclasses import dataclass, field
from typing import Iterator

import cv2
import numpy as np

from ...core.rng import spawn
from ...core.types import Drive
from .config import stream_rng
from .optics import CameraIntrinsics, Lighting
from .render import RENDER_VERSION, StreetRenderer
from .scenario import Scenario, scenario_of, seed_of

FAULT_CLEAN, FAULT_BLUR, FAULT_OCCLUSION = 0, 1, 2
FAULT_NAMES = ('clean', 'blur', 'occlusion')


def blur_sigma(ksize: int) -> float:
    """Gaussian std [px] OpenCV uses for ``cv2.GaussianBlur(img, (k, k), 0)``."""
    return 0.3 * ((ksize - 1) * 0.5 - 1.0) + 0.8


@dataclass(eq=False)
class CameraStream:
    """Camera frames of an emulated drive, rendered on demand.

    Attributes:
        stamp_ns: (n,) frame times [ns] (same clock as the drive).
        pose: (n, 4) true camera poses ``(east_m, north_m, up_m, yaw_rad)`` in the drive's
            ENU ``map`` frame (yaw counter-clockwise from east).
        fault: (n,) int8 fault code per frame: 0 clean, 1 blur, 2 occlusion
            (:data:`FAULT_NAMES`).
        fault_box: (n, 4) int32 occluding rectangle ``(x, y, w, h)`` [px] of occluded
            frames, -1 elsewhere.
        fault_colour: (n, 3) uint8 BGR colour of the occluding rectangle.
        blur_ksize: Gaussian blur kernel size of blurred frames [px].
        blur_sigma: Gaussian blur std [px].
        gain: (n,) per-frame exposure multiplier (auto-exposure drift).
        noise_index: (n,) sensor-noise frame of the renderer's bank used by each frame.
        lighting: Lighting of the pass.
        intrinsics: Camera model.
        city: The city rendered.
        seed: Seed of the stream.
        info: Provenance (seed, rates, fault counts, parameters).
    """

    stamp_ns: np.ndarray
    pose: np.ndarray
    fault: np.ndarray
    fault_box: np.ndarray
    fault_colour: np.ndarray
    blur_ksize: int
    blur_sigma: float
    gain: np.ndarray
    noise_index: np.ndarray
    lighting: Lighting
    intrinsics: CameraIntrinsics
    city: object = field(repr=False)
    seed: int = 0
    info: dict = field(default_factory=dict)
    _renderer: StreetRenderer | None = field(default=None, init=False, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, init=False, repr=False)

    def __len__(self) -> int:
        return int(self.stamp_ns.shape[0])

    def __getstate__(self) -> dict:
        # Picklable for worker processes: the renderer (texture caches) and the lock are
        # rebuilt on demand in the receiving process.
        state = self.__dict__.copy()
        state['_renderer'] = None
        del state['_lock']
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()

    @property
    def renderer(self) -> StreetRenderer:
        """The (lazily created) renderer of this stream."""
        with self._lock:
            if self._renderer is None:
                self._renderer = StreetRenderer(self.city, self.intrinsics, self.lighting,
                                                seed=self.seed)
            return self._renderer

    def fault_name(self, i: int) -> str:
        """``'clean'``, ``'blur'`` or ``'occlusion'`` for frame ``i``."""
        return FAULT_NAMES[int(self.fault[i])]

    def frames_with(self, kind: str | int) -> np.ndarray:
        """Indices of the frames with fault ``kind`` (a name or a code)."""
        code = FAULT_NAMES.index(kind) if isinstance(kind, str) else int(kind)
        return np.flatnonzero(self.fault == code)

    def clean_image(self, i: int) -> np.ndarray:
        """Frame ``i`` without its fault, (H, W, 3) uint8 BGR."""
        i = self._check(i)
        return self.renderer.render(self.pose[i], gain=float(self.gain[i]),
                                    noise_index=int(self.noise_index[i]))

    def image(self, i: int, faults: bool = True) -> np.ndarray:
        """Frame ``i`` as the camera delivers it, (H, W, 3) uint8 BGR.

        Deterministic: the same index always gives the same image, in any order.

        Args:
            i: Frame index (negative counts from the end).
            faults: Apply the frame's recorded fault (False: the clean frame).
        """
        img = self.clean_image(i)
        if faults:
            img = self.apply_fault(img, i)
        return img

    def apply_fault(self, img: np.ndarray, i: int) -> np.ndarray:
        """Apply frame ``i``'s recorded fault to ``img`` (returns a new array when faulty)."""
        i = self._check(i)
        code = int(self.fault[i])
        if code == FAULT_BLUR:
            return cv2.GaussianBlur(img, (self.blur_ksize, self.blur_ksize), self.blur_sigma)
        if code == FAULT_OCCLUSION:
            x, y, w, h = (int(v) for v in self.fault_box[i])
            out = img.copy()
            cv2.rectangle(out, (x, y), (x + w - 1, y + h - 1),
                          tuple(int(c) for c in self.fault_colour[i]), -1)
            return out
        return img

    def frames(self, start: int = 0, stop: int | None = None,
               step: int = 1) -> Iterator[tuple[int, int, np.ndarray]]:
        """Iterate ``(index, stamp_ns, image)`` over a range of frames, rendering lazily."""
        for i in range(*slice(start, stop, step).indices(len(self))):
            yield i, int(self.stamp_ns[i]), self.image(i)

    def _check(self, i: int) -> int:
        n = len(self)
        i = int(i)
        if not -n <= i < n:
            raise IndexError(f'frame {i} out of range for {n} frames')
        return i % n


def make_camera_stream(scenario: Scenario, seed: int | None = None, rate_hz: float = 10.0,
                       fault_fraction: float = 0.2,
                       fault_kinds: tuple[str, ...] = ('blur', 'occlusion'),
                       blur_ksize: int = 21,
                       occlusion_frac: tuple[float, float] = (0.25, 0.5),
                       duration_s: float | None = None,
                       intrinsics: CameraIntrinsics | None = None,
                       lighting: Lighting | None = None,
                       exposure_std: float = 0.04) -> CameraStream:
    """The seeded camera stream of an emulated drive (frames are rendered lazily).

    Random draws come from the drive's ``'camera'`` stream, split into independent
    children for lighting, faults and exposure, so changing the fault fraction does not
    change the lighting and vice versa. Each frame is faulty with probability
    ``fault_fraction``, the kind drawn uniformly from ``fault_kinds``; an occlusion box
    has width ``U(occlusion_frac) * W`` and height ``U(occlusion_frac) * H`` at a uniform
    position inside the image and a uniform random colour.

    Args:
        scenario: The drive's scenario (:func:`.scenario.make_scenario`).
        seed: Seed of the camera randomness (default: the scenario's seed).
        rate_hz: Frame rate [Hz].
        fault_fraction: Probability that a frame is faulty, in [0, 1].
        fault_kinds: Fault kinds to draw from (``'blur'``, ``'occlusion'``).
        blur_ksize: Gaussian kernel size of the blur fault [px] (odd).
        occlusion_frac: (min, max) occluder size as a fraction of the image height/width.
        duration_s: Keep frames up to this time from the start [s] (None: whole drive).
        intrinsics: Camera model (default 640x480, 80 deg HFOV).
        lighting: Lighting (default: a sunny lighting drawn from the seed).
        exposure_std: Std of the slow log-exposure drift (AR(1), 5 s correlation time).

    Returns:
        The stream.

    Raises:
        ValueError: on out-of-range parameters.
    """
    _check_stream_args(rate_hz, fault_fraction, fault_kinds, blur_ksize, occlusion_frac)
    seed = seed_of(scenario, seed)
    intrinsics = intrinsics or CameraIntrinsics()
    rng_light, rng_fault, rng_exp = spawn(stream_rng(seed, 'camera'), 3)
    if lighting is None:
        lighting = Lighting.sunny(rng_light)
    t_end = scenario.duration_s if duration_s is None else min(float(duration_s),
                                                               scenario.duration_s)
    t = np.arange(int(math.floor(t_end * rate_hz + 1e-9)) + 1) / rate_hz
    n = len(t)
    p = scenario.pose_at(t)
    pose = np.column_stack([p.enu_m, p.yaw_rad])

    fault, box, colour = _draw_faults(rng_fault, n, fault_fraction, fault_kinds,
                                      occlusion_frac, intrinsics)
    gain, noise_index = _exposure(rng_exp, n, rate_hz, exposure_std)

    info = {'generator': 'gnsscam_ros.datasets.emulated.camera.make_camera_stream',
            'seed': seed, 'scenario_seed': int(scenario.seed), 'rate_hz': float(rate_hz),
            'fault_fraction': float(fault_fraction), 'fault_kinds': list(fault_kinds),
            'blur_ksize': int(blur_ksize),
            'occlusion_frac': [float(v) for v in occlusion_frac],
            'n_frames': n, 'fault_counts': {name: int(np.sum(fault == c))
                                            for c, name in enumerate(FAULT_NAMES)},
            'intrinsics': intrinsics.as_dict(), 'lighting': lighting.as_dict(),
            'render_version': RENDER_VERSION}
    return CameraStream(stamp_ns=scenario.stamps_ns(t), pose=pose, fault=fault,
                        fault_box=box, fault_colour=colour, blur_ksize=int(blur_ksize),
                        blur_sigma=blur_sigma(int(blur_ksize)), gain=gain,
                        noise_index=noise_index, lighting=lighting, intrinsics=intrinsics,
                        city=scenario.city, seed=seed, info=info)


def _check_stream_args(rate_hz: float, fault_fraction: float, fault_kinds: tuple[str, ...],
                       blur_ksize: int, occlusion_frac: tuple[float, float]) -> None:
    """Raise ValueError for out-of-range :func:`make_camera_stream` parameters."""
    if rate_hz <= 0:
        raise ValueError(f'rate_hz must be positive, got {rate_hz}')
    if not 0.0 <= fault_fraction <= 1.0:
        raise ValueError(f'fault_fraction must be in [0, 1], got {fault_fraction}')
    bad = [k for k in fault_kinds if k not in FAULT_NAMES[1:]]
    if bad or not fault_kinds:
        raise ValueError(f'fault_kinds must be a non-empty subset of {FAULT_NAMES[1:]}, '
                         f'got {fault_kinds}')
    if blur_ksize < 1 or blur_ksize % 2 == 0:
        raise ValueError(f'blur_ksize must be odd and positive, got {blur_ksize}')
    lo, hi = occlusion_frac
    if not 0.0 < lo <= hi <= 1.0:
        raise ValueError(f'occlusion_frac must satisfy 0 < min <= max <= 1, got '
                         f'{occlusion_frac}')


def _draw_faults(rng: np.random.Generator, n: int, fault_fraction: float,
                 fault_kinds: tuple[str, ...], occlusion_frac: tuple[float, float],
                 intrinsics: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fault code, occlusion box and box colour of ``n`` frames.

    Returns:
        ``(fault (n,) int8, box (n, 4) int32 (x, y, w, h), colour (n, 3) uint8)``; box and
        colour are -1 and 0 on frames that are not occluded.
    """
    lo, hi = occlusion_frac
    # Faults: drawn for every frame in a fixed order so that the kinds and boxes of a frame
    # do not depend on the fraction (nested fault sets for growing fractions).
    u = rng.random(n)
    kind_draw = rng.integers(0, len(fault_kinds), n)
    size = rng.uniform(lo, hi, (n, 2))
    where = rng.random((n, 2))
    colour = rng.integers(0, 256, (n, 3)).astype(np.uint8)
    codes = np.array([FAULT_NAMES.index(k) for k in fault_kinds], np.int8)
    fault = np.where(u < fault_fraction, codes[kind_draw], FAULT_CLEAN).astype(np.int8)
    W, H = intrinsics.width, intrinsics.height
    bw = np.maximum(1, np.rint(size[:, 0] * W)).astype(np.int32)
    bh = np.maximum(1, np.rint(size[:, 1] * H)).astype(np.int32)
    bx = np.floor(where[:, 0] * (W - bw + 1)).astype(np.int32)
    by = np.floor(where[:, 1] * (H - bh + 1)).astype(np.int32)
    box = np.column_stack([bx, by, bw, bh])
    occ = fault == FAULT_OCCLUSION
    box[~occ] = -1
    colour[~occ] = 0
    return fault, box, colour


def _exposure(rng: np.random.Generator, n: int, rate_hz: float,
              exposure_std: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame exposure gain and sensor-noise frame of ``n`` frames.

    Returns:
        ``(gain (n,), noise_index (n,))``.
    """
    # Exposure: AR(1) drift of the log gain, stationary from the first frame.
    phi = math.exp(-1.0 / (5.0 * rate_hz))
    w = rng.normal(0.0, exposure_std, n)
    w[1:] *= math.sqrt(1.0 - phi ** 2)
    x = np.empty(n)
    acc = 0.0
    for k in range(n):
        acc = w[k] if k == 0 else phi * acc + w[k]
        x[k] = acc
    noise_index = rng.integers(0, 1 << 16, n)
    return np.exp(x), noise_index


def with_camera(drive: Drive, seed: int | None = None, **kwargs) -> Drive:
    """A copy of an emulated drive with its camera stream attached (``drive.camera``).

    Args:
        drive: Drive from :func:`.drive.make_emulated_drive`.
        seed: Camera seed (default: the drive's seed).
        **kwargs: Passed to :func:`make_camera_stream` (``duration_s`` defaults to the
            drive's duration).

    Returns:
        The drive with ``camera`` set and ``info['camera']`` describing the stream.
    """
    sc = scenario_of(drive)
    kwargs.setdefault('duration_s', drive.info.get('duration_s'))
    stream = make_camera_stream(sc, seed=seed, **kwargs)
    return dataclasses.replace(drive, camera=stream, info={**drive.info, 'camera': stream.info})
