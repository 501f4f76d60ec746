"""Camera stream and geotagged map database of the emulated drive (rendered images).

The forward camera of the emulated drive sees the procedural city of :mod:`.city` rendered
by :mod:`.render`: real images on which ORB finds and matches features. Two passes
through the city are rendered:

* **Query pass** (:func:`make_camera_stream`): the drive itself at ``rate_hz`` (10 Hz),
  camera at the truth pose (antenna position, level, looking along the direction of
  travel), one lighting for the whole drive (sunny by default) with a slow per-frame
  exposure drift and sensor noise. Camera faults as in the paper (§7.2) hit random frames:
  a 21x21 Gaussian blur, or an occlusion, a filled rectangle of 25-50 % of the image
  height and width at a random place. Which frames are faulty, and how, is drawn up front
  from the seeded ``'camera'`` stream and recorded (:attr:`CameraStream.fault`,
  :attr:`CameraStream.fault_box`), so the evaluation knows them. Images are rendered
  lazily by :meth:`CameraStream.image` (a drive has ~2,000-4,500 frames; they are never
  all held in memory) and are a deterministic function of the frame index.
* **Database pass** (:func:`database_poses`, :func:`map_database_views`): another drive
  along the streets within ``margin_m`` of the route, in both directions, every
  ``spacing_m`` metres, plus the turn arcs at the intersections (a Street View panorama
  can be looked at in any direction), with other lighting (overcast by default), lateral
  offsets up to +-1.5 m from the lane centre and heading offsets up to +-5 deg.
  :func:`build_emulated_map_database` turns it into a :class:`..vision.database.MapDatabase`
  and caches it on disk.

Run ``python -m gnsscam_ros.datasets.emulated.camera --measure --seed 1`` to measure retrieval on
the full drive (top-1 match within 10 m of the truth, for clean, blurred and occluded
frames separately).
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import os
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Iterator

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ...core.types import Drive
from ...vision.database import MapDatabase, PositionTable
from ...vision.errors import MapDatabaseError
from ...vision.features import OrbExtractor, OrbParams
from .render import CameraIntrinsics, Lighting, StreetRenderer
from .drive import EmulationConfig, Scenario, make_scenario, stream_rng

FAULT_CLEAN, FAULT_BLUR, FAULT_OCCLUSION = 0, 1, 2
FAULT_NAMES = ('clean', 'blur', 'occlusion')

#: Bump when rendering changes, so that cached databases are rebuilt.
RENDER_VERSION = 1

_DIRS = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])   # E, N, W, S


def _right(u: np.ndarray) -> np.ndarray:
    """Unit vector 90 deg clockwise of the (.., 2) direction ``u``."""
    return np.stack([u[..., 1], -u[..., 0]], axis=-1)


def blur_sigma(ksize: int) -> float:
    """Gaussian std [px] OpenCV uses for ``cv2.GaussianBlur(img, (k, k), 0)``."""
    return 0.3 * ((ksize - 1) * 0.5 - 1.0) + 0.8


# ============================================================================ query pass
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


def _seed_of(scenario: Scenario, seed: int | None) -> int:
    return int(scenario.seed if seed is None else seed)


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
        scenario: The drive's scenario (:func:`.emulated.make_scenario`).
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
    seed = _seed_of(scenario, seed)
    intrinsics = intrinsics or CameraIntrinsics()
    children = stream_rng(seed, 'camera').bit_generator.seed_seq.spawn(3)
    rng_light, rng_fault, rng_exp = (np.random.default_rng(c) for c in children)
    if lighting is None:
        lighting = Lighting.sunny(rng_light)
    t_end = scenario.duration_s if duration_s is None else min(float(duration_s),
                                                               scenario.duration_s)
    t = np.arange(int(math.floor(t_end * rate_hz + 1e-9)) + 1) / rate_hz
    n = len(t)
    p = scenario.pose_at(t)
    pose = np.column_stack([p.enu_m, p.yaw_rad])

    # Faults: drawn for every frame in a fixed order so that the kinds and boxes of a frame
    # do not depend on the fraction (nested fault sets for growing fractions).
    u = rng_fault.random(n)
    kind_draw = rng_fault.integers(0, len(fault_kinds), n)
    size = rng_fault.uniform(lo, hi, (n, 2))
    where = rng_fault.random((n, 2))
    colour = rng_fault.integers(0, 256, (n, 3)).astype(np.uint8)
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

    # Exposure: AR(1) drift of the log gain, stationary from the first frame.
    phi = math.exp(-1.0 / (5.0 * rate_hz))
    w = rng_exp.normal(0.0, exposure_std, n)
    w[1:] *= math.sqrt(1.0 - phi ** 2)
    x = np.empty(n)
    acc = 0.0
    for k in range(n):
        acc = w[k] if k == 0 else phi * acc + w[k]
        x[k] = acc
    noise_index = rng_exp.integers(0, 1 << 16, n)

    info = {'generator': 'gnsscam_ros.datasets.emulated.camera.make_camera_stream',
            'seed': seed, 'scenario_seed': int(scenario.seed), 'rate_hz': float(rate_hz),
            'fault_fraction': float(fault_fraction), 'fault_kinds': list(fault_kinds),
            'blur_ksize': int(blur_ksize), 'occlusion_frac': [float(lo), float(hi)],
            'n_frames': n, 'fault_counts': {name: int(np.sum(fault == c))
                                            for c, name in enumerate(FAULT_NAMES)},
            'intrinsics': intrinsics.as_dict(), 'lighting': lighting.as_dict(),
            'render_version': RENDER_VERSION}
    return CameraStream(stamp_ns=scenario.stamps_ns(t), pose=pose, fault=fault,
                        fault_box=box, fault_colour=colour, blur_ksize=int(blur_ksize),
                        blur_sigma=blur_sigma(int(blur_ksize)), gain=np.exp(x),
                        noise_index=noise_index, lighting=lighting, intrinsics=intrinsics,
                        city=scenario.city, seed=seed, info=info)


def scenario_of(drive: Drive) -> Scenario:
    """Rebuild the scenario of an emulated drive from its ``info`` (seed and config)."""
    info = drive.info or {}
    if 'seed' not in info or 'config' not in info:
        raise ValueError(f'{drive.name}: not an emulated drive (info has no seed/config)')
    cfg = {k: (tuple(v) if isinstance(v, list) else v) for k, v in info['config'].items()}
    return make_scenario(int(info['seed']), EmulationConfig(**cfg))


def with_camera(drive: Drive, seed: int | None = None, **kwargs) -> Drive:
    """A copy of an emulated drive with its camera stream attached (``drive.camera``).

    Args:
        drive: Drive from :func:`.emulated.make_emulated_drive`.
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


# ============================================================================ database pass
@dataclass(frozen=True)
class DatabasePass:
    """Poses of the database pass.

    Attributes:
        names: (m,) image names.
        pose: (m, 4) camera poses ``(east_m, north_m, up_m, yaw_rad)``.
        kind: (m,) 0 on a street, 1 on a turn arc.
        lighting: Lighting of the pass.
        params: The parameters that produced it (for cache keys and provenance).
    """

    names: list[str]
    pose: np.ndarray
    kind: np.ndarray
    lighting: Lighting
    params: dict

    def __len__(self) -> int:
        return len(self.names)


def database_poses(scenario: Scenario, spacing_m: float = 3.0, margin_m: float = 120.0,
                   lateral_m: float = 1.5, heading_deg: float = 5.0, turns: bool = True,
                   region: str = 'route', seed: int | None = None,
                   lighting: Lighting | None = None,
                   route_range_m: tuple[float, float] | None = None) -> DatabasePass:
    """Poses of the database pass: lane centres of both directions plus turn arcs.

    Streets are cut into edges between neighbouring intersections. Along each edge and
    direction, views are taken every ``spacing_m`` from a random phase, on the lane centre
    (``config.lane_offset_m`` right of the street centre line) moved sideways by
    ``U(-lateral_m, lateral_m)`` and turned by ``U(-heading_deg, heading_deg)``. With
    ``turns``, every left and right turn arc (radius ``config.turn_radius_m``) of every
    intersection is sampled too. ``region='route'`` keeps the views within ``margin_m``
    of the route (the route's streets, and the parallel ones for margins above the block
    pitch), ``region='city'`` all of them.

    Args:
        scenario: The drive's scenario.
        spacing_m: Distance between views along a lane [m].
        margin_m: Keep streets within this distance of the route [m].
        lateral_m: Max lateral offset from the lane centre [m].
        heading_deg: Max heading offset [deg].
        turns: Add the turn arcs at intersections.
        region: ``'route'`` or ``'city'``.
        seed: Seed of the pass (default: the scenario's seed); the pass uses its own
            random stream, independent of the query pass.
        lighting: Lighting (default: an overcast lighting drawn from the seed).
        route_range_m: ``(s0, s1)`` arc lengths [m]: only this part of the route counts
            for ``region='route'`` (e.g. a drive cut short); None: the whole route.

    Returns:
        The poses.
    """
    if spacing_m <= 0:
        raise ValueError(f'spacing_m must be positive, got {spacing_m}')
    if region not in ('route', 'city'):
        raise ValueError(f"region must be 'route' or 'city', got {region!r}")
    seed = _seed_of(scenario, seed)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0xDA7AB])).spawn(2)
    rng_light, rng = rng
    if lighting is None:
        lighting = Lighting.overcast(rng_light)
    city, cfg = scenario.city, scenario.config
    se, sn = np.asarray(city.street_e_m), np.asarray(city.street_n_m)
    pitch = float(city.pitch_m)
    cam_h = float(cfg.antenna_height_m)
    off, r_turn = float(cfg.lane_offset_m), float(cfg.turn_radius_m)
    # Edges: (start node (2,), unit direction (2,)); N-S then E-W, deterministic order.
    # Views are drawn for the whole city, then filtered, so that the random offsets of a
    # view do not depend on the margin (databases for growing margins are nested).
    edges = []
    for i in range(len(se)):
        for j in range(len(sn) - 1):
            edges.append(((se[i], sn[j]), (0.0, 1.0)))
    for j in range(len(sn)):
        for i in range(len(se) - 1):
            edges.append(((se[i], sn[j]), (1.0, 0.0)))
    poses, kinds = [], []
    for start, along in edges:
        start, along = np.asarray(start), np.asarray(along)
        for sign in (1.0, -1.0):
            u = along * sign
            a = start if sign > 0 else start + pitch * along
            s = np.arange(rng.uniform(0.0, spacing_m), pitch, spacing_m)
            lat = rng.uniform(-lateral_m, lateral_m, len(s))
            dpsi = np.radians(rng.uniform(-heading_deg, heading_deg, len(s)))
            p = a + s[:, None] * u + (off + lat)[:, None] * _right(u)
            psi = math.atan2(u[1], u[0]) + dpsi
            poses.append(np.column_stack([p, np.full(len(s), cam_h), psi]))
            kinds.append(np.zeros(len(s), np.int8))
    if turns:
        arc_len = 0.5 * math.pi * r_turn
        for node in np.array([(x, y) for x in se for y in sn]):
            for d_in in range(4):
                u_in = _DIRS[d_in]
                for turn in (1, -1):                         # left, right
                    u_out = _DIRS[(d_in + turn) % 4]
                    before, after = node - pitch * u_in, node + pitch * u_out
                    if not (_inside(before, se, sn) and _inside(after, se, sn)):
                        continue
                    corner = node + off * _right(u_in) + off * _right(u_out)
                    a0 = corner - r_turn * u_in
                    psi0 = math.atan2(u_in[1], u_in[0])
                    kappa = turn / r_turn
                    s = np.arange(rng.uniform(0.0, spacing_m), arc_len, spacing_m)
                    psi = psi0 + kappa * s
                    p = a0 + np.column_stack([(np.sin(psi) - math.sin(psi0)) / kappa,
                                              -(np.cos(psi) - math.cos(psi0)) / kappa])
                    lat = rng.uniform(-lateral_m, lateral_m, len(s))
                    nrm = np.column_stack([np.sin(psi), -np.cos(psi)])      # right of travel
                    p = p + lat[:, None] * nrm
                    psi = psi + np.radians(rng.uniform(-heading_deg, heading_deg, len(s)))
                    poses.append(np.column_stack([p, np.full(len(s), cam_h), psi]))
                    kinds.append(np.ones(len(s), np.int8))
    pose = np.concatenate(poses) if poses else np.zeros((0, 4))
    pose[:, 3] = (pose[:, 3] + np.pi) % (2 * np.pi) - np.pi
    kind = np.concatenate(kinds) if kinds else np.zeros(0, np.int8)
    if region == 'route':
        s0, s1 = route_range_m or (0.0, scenario.route.length_m)
        route_pts = scenario.route.evaluate(np.append(np.arange(s0, s1, 2.0), s1))[0]
        keep = cKDTree(route_pts).query(pose[:, :2], k=1)[0] <= margin_m
        pose, kind = pose[keep], kind[keep]
    names = [f'db{k:06d}_{"turn" if kind[k] else "street"}.png' for k in range(len(pose))]
    params = {'seed': seed, 'spacing_m': float(spacing_m), 'margin_m': float(margin_m),
              'lateral_m': float(lateral_m), 'heading_deg': float(heading_deg),
              'turns': bool(turns), 'region': region, 'lighting': lighting.as_dict(),
              'route_range_m': None if route_range_m is None else [float(v) for v in
                                                                   route_range_m]}
    return DatabasePass(names=names, pose=pose, kind=kind, lighting=lighting, params=params)


def _inside(p: np.ndarray, se: np.ndarray, sn: np.ndarray) -> bool:
    return bool(se[0] - 1e-6 <= p[0] <= se[-1] + 1e-6 and sn[0] - 1e-6 <= p[1] <= sn[-1] + 1e-6)


def map_database_views(scenario: Scenario, intrinsics: CameraIntrinsics | None = None,
                       **kwargs) -> Iterator[tuple[str, np.ndarray, float, float, float]]:
    """Render the database pass lazily.

    Args:
        scenario: The drive's scenario.
        intrinsics: Camera model (default 640x480, 80 deg HFOV).
        **kwargs: Passed to :func:`database_poses`.

    Yields:
        ``(name, image (H, W, 3) uint8 BGR, east_m, north_m, up_m)`` per database view.
    """
    dbp = database_poses(scenario, **kwargs)
    renderer = StreetRenderer(scenario.city, intrinsics, dbp.lighting,
                              seed=_seed_of(scenario, kwargs.get('seed')) + 7919)
    for k, name in enumerate(dbp.names):
        e, n, u, _ = dbp.pose[k]
        yield name, renderer.render(dbp.pose[k], noise_index=k), float(e), float(n), float(u)


def default_cache_dir() -> str:
    """``$GNSSCAM_CACHE_DIR``, else ``$XDG_CACHE_HOME/gnsscam_ros`` (``~/.cache/...``)."""
    env = os.environ.get('GNSSCAM_CACHE_DIR')
    if env:
        return env
    base = os.environ.get('XDG_CACHE_HOME') or os.path.join(os.path.expanduser('~'), '.cache')
    return os.path.join(base, 'gnsscam_ros')


def _locality_order(pose: np.ndarray, cell_m: float) -> np.ndarray:
    """Visiting order of views that keeps neighbours together (serpentine over cells).

    Views in one cell see mostly the same facades, so rendering them one after the other
    keeps the renderer's texture cache warm (the database order itself is unchanged).
    """
    cx = np.floor(pose[:, 0] / cell_m).astype(np.int64)
    cy = np.floor(pose[:, 1] / cell_m).astype(np.int64)
    cy = np.where(cx % 2 == 0, cy, -cy)
    return np.lexsort((np.arange(len(pose)), cy, cx))


def _describe_images(dbp: DatabasePass, city, intrinsics: CameraIntrinsics,
                     orb_params: OrbParams, seed: int,
                     progress: Callable[[str, int, int], None] | None
                     ) -> tuple[list[np.ndarray], float]:
    """Render every database view and extract its ORB descriptors.

    Serial on purpose: OpenCV already spreads ORB over the cores, and the renderer's
    Python parts hold the GIL, so threads or processes made the build slower here.

    Returns:
        Per view (database order) its (n, 32) descriptors, and the total render time [s].
    """
    renderer = StreetRenderer(city, intrinsics, dbp.lighting, seed=seed)
    extractor = OrbExtractor(orb_params)
    n = len(dbp)
    out: list[np.ndarray | None] = [None] * n
    render_s = 0.0
    for j, k in enumerate(_locality_order(dbp.pose, 0.5 * float(city.pitch_m))):
        t0 = time.perf_counter()
        img = renderer.render(dbp.pose[k], noise_index=int(k))
        render_s += time.perf_counter() - t0
        out[k] = extractor.descriptors(img)
        if progress and ((j + 1) % 250 == 0 or j + 1 == n):
            progress('render', j + 1, n)
    return out, render_s


def build_emulated_map_database(scenario: Scenario, cache_dir: str | os.PathLike | None = None,
                                use_cache: bool = True,
                                intrinsics: CameraIntrinsics | None = None,
                                orb_params: OrbParams | None = None,
                                branching: int = 10, depth: int = 5,
                                max_train_descriptors: int | None = 200_000,
                                progress: Callable[[str, int, int], None] | None = None,
                                **pass_kwargs) -> MapDatabase:
    """Render the database pass and build (or load from the cache) its map database.

    The database is cached as ``<cache_dir>/emulated_mapdb_s<seed>_<hash>.npz``, the hash
    covering the scenario (seed and config), the database-pass parameters, the camera,
    the ORB and tree settings and :data:`RENDER_VERSION`. Writes are atomic
    (:meth:`MapDatabase.save` renames a temporary file), so concurrent campaign processes
    at worst build the same database twice. ``db.meta['emulated']`` records the pass
    parameters, the number of views and the build and render times.

    Args:
        scenario: The drive's scenario.
        cache_dir: Cache folder (default :func:`default_cache_dir`).
        use_cache: Read and write the cache (False: always build, write nothing).
        intrinsics: Camera model (default 640x480, 80 deg HFOV).
        orb_params: ORB settings (default :class:`OrbParams`).
        branching: Vocabulary tree branching factor.
        depth: Vocabulary tree depth.
        max_train_descriptors: Tree training subsample size.
        progress: Optional ``progress(stage, done, total)`` callback.
        **pass_kwargs: Passed to :func:`database_poses` (spacing_m, margin_m, ...).

    Returns:
        The database; image positions are in the drive's ENU ``map`` frame
        (``east_m, north_m, up_m`` columns).
    """
    intrinsics = intrinsics or CameraIntrinsics()
    orb_params = orb_params or OrbParams()
    dbp = database_poses(scenario, **pass_kwargs)
    tree_params = {'branching': int(branching), 'depth': int(depth),
                   'max_train_descriptors': max_train_descriptors}
    key = {'render_version': RENDER_VERSION, 'scenario_seed': int(scenario.seed),
           'config': dataclasses.asdict(scenario.config), 'pass': dbp.params,
           'intrinsics': intrinsics.as_dict(), 'orb': orb_params.as_dict(),
           'tree': tree_params}
    digest = hashlib.sha1(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()
    path = None
    if use_cache:
        folder = os.fspath(cache_dir) if cache_dir is not None else default_cache_dir()
        os.makedirs(folder, exist_ok=True)
        path = os.path.join(folder, f'emulated_mapdb_s{int(scenario.seed)}_{digest[:16]}.npz')
        if os.path.exists(path):
            try:
                return MapDatabase.load(path)
            except MapDatabaseError:
                pass          # unreadable (e.g. an older format): rebuild and replace it
    t0 = time.perf_counter()
    descs, render_s = _describe_images(dbp, scenario.city, intrinsics, orb_params,
                                       dbp.params['seed'] + 7919, progress)
    t1 = time.perf_counter()
    positions = PositionTable.from_columns(('east_m', 'north_m', 'up_m'), dbp.pose[:, :3])
    db = MapDatabase.build(descs, dbp.names, positions, orb_params=orb_params,
                           seed=int(dbp.params['seed']), progress=progress, **tree_params)
    t2 = time.perf_counter()
    db.meta['emulated'] = {'key': key, 'n_views': len(dbp), 'n_turn_views': int(dbp.kind.sum()),
                           'yaw_rad': dbp.pose[:, 3].tolist(), 'features_s': t1 - t0,
                           'render_s': render_s, 'tree_s': t2 - t1, 'build_s': t2 - t0}
    if path is not None:
        db.save(path, overwrite=True)
    return db


# ============================================================================ evaluation
def evaluate_retrieval(stream: CameraStream, db: MapDatabase, frames=None,
                       radius_m: float = 10.0, top_k: int = 5,
                       progress: Callable[[str, int, int], None] | None = None) -> dict:
    """Top-1 (and top-k) retrieval accuracy of a camera stream against a database.

    A frame counts as correct when its best match lies within ``radius_m`` (horizontal
    distance) of the true camera position; frames without any match count as wrong. A
    frame is *ambiguous* when another of its top-k matches, more than ``2 radius_m`` away
    from the best one, scores at least 80 % of the best score (another place looks alike).

    Args:
        stream: The camera stream (faults applied as recorded).
        db: The map database (positions in the same frame as ``stream.pose``).
        frames: Frame indices to use (default: all).
        radius_m: Correctness radius [m].
        top_k: Also report whether any of the first ``top_k`` matches is within the radius.
        progress: Optional ``progress(stage, done, total)`` callback.

    Returns:
        ``{'frames', 'error_m' (per frame, inf when no match), 'top1_ok', 'topk_ok',
        'ambiguous', 'fault', 'by_kind': {name: {'n', 'top1', 'topk', 'ambiguous',
        'median_error_m'}}, 'top1', 'render_ms', 'query_ms'}`` with fractions in [0, 1].
    """
    idx = np.arange(len(stream)) if frames is None else np.asarray(frames, dtype=int)
    err = np.full(len(idx), np.inf)
    ok_k = np.zeros(len(idx), bool)
    ambiguous = np.zeros(len(idx), bool)
    render_s = query_s = 0.0
    for j, i in enumerate(idx):
        t0 = time.perf_counter()
        img = stream.image(int(i))
        t1 = time.perf_counter()
        matches = db.query(img, top_k=top_k)
        query_s += time.perf_counter() - t1
        render_s += t1 - t0
        if matches:
            d = [float(np.hypot(*(m.position_enu_m[:2] - stream.pose[i, :2]))) for m in matches]
            err[j] = d[0]
            ok_k[j] = min(d) <= radius_m
            best = matches[0]
            ambiguous[j] = any(
                m.score >= 0.8 * best.score
                and np.hypot(*(m.position_enu_m[:2] - best.position_enu_m[:2])) > 2 * radius_m
                for m in matches[1:])
        if progress and ((j + 1) % 250 == 0 or j + 1 == len(idx)):
            progress('query', j + 1, len(idx))
    ok1 = err <= radius_m
    fault = stream.fault[idx]
    by_kind = {}
    for code, name in enumerate(FAULT_NAMES):
        m = fault == code
        by_kind[name] = {'n': int(m.sum()),
                         'top1': float(ok1[m].mean()) if m.any() else float('nan'),
                         'topk': float(ok_k[m].mean()) if m.any() else float('nan'),
                         'ambiguous': float(ambiguous[m].mean()) if m.any() else float('nan'),
                         'median_error_m': float(np.median(err[m])) if m.any() else float('nan')}
    n = max(len(idx), 1)
    return {'frames': idx, 'error_m': err, 'top1_ok': ok1, 'topk_ok': ok_k,
            'ambiguous': ambiguous, 'fault': fault,
            'by_kind': by_kind, 'top1': float(ok1.mean()) if len(idx) else float('nan'),
            'radius_m': float(radius_m), 'top_k': int(top_k),
            'render_ms': 1e3 * render_s / n, 'query_ms': 1e3 * query_s / n}


# ============================================================================ CLI
def _progress(stage: str, done: int, total: int) -> None:
    print(f'  {stage}: {done}/{total}', file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> int:
    """``python -m gnsscam_ros.datasets.emulated.camera --measure --seed 1``: retrieval figures."""
    ap = argparse.ArgumentParser(prog='python -m gnsscam_ros.datasets.emulated.camera',
                                 description='Emulated camera stream and map database.')
    ap.add_argument('--measure', action='store_true',
                    help='build/load the database and measure top-1 retrieval on the drive')
    ap.add_argument('--seed', type=int, default=1, help='drive seed (default 1)')
    ap.add_argument('--cache-dir', default=None, help='database cache folder '
                    '(default $GNSSCAM_CACHE_DIR or ~/.cache/gnsscam_ros)')
    ap.add_argument('--no-cache', action='store_true', help='always rebuild, write nothing')
    ap.add_argument('--spacing', type=float, default=3.0, help='database spacing [m]')
    ap.add_argument('--margin', type=float, default=120.0,
                    help='database streets within this distance of the route [m]')
    ap.add_argument('--region', choices=('route', 'city'), default='route')
    ap.add_argument('--every', type=int, default=1, help='use every k-th frame')
    ap.add_argument('--fault-fraction', type=float, default=0.2)
    ap.add_argument('--radius', type=float, default=10.0, help='correct-match radius [m]')
    ap.add_argument('--save-frames', default=None,
                    help='folder to write a few example frames (PNG) into')
    ap.add_argument('--json', default=None, help='also write the figures to this JSON file')
    args = ap.parse_args(argv)
    if not args.measure and not args.save_frames:
        ap.print_help()
        return 0
    sc = make_scenario(args.seed)
    stream = make_camera_stream(sc, fault_fraction=args.fault_fraction)
    if args.save_frames:
        os.makedirs(args.save_frames, exist_ok=True)
        for i in np.linspace(0, len(stream) - 1, 8).astype(int):
            cv2.imwrite(os.path.join(args.save_frames,
                                     f'frame{i:05d}_{stream.fault_name(i)}.png'),
                        stream.image(int(i)))
        for k, (name, img, *_) in enumerate(map_database_views(sc, margin_m=args.margin)):
            if k % 200 == 0:
                cv2.imwrite(os.path.join(args.save_frames, name), img)
            if k >= 1000:
                break
    if not args.measure:
        return 0
    print(f'seed {args.seed}: {len(stream)} frames at 10 Hz, '
          f'{stream.info["fault_counts"]}', flush=True)
    t0 = time.perf_counter()
    db = build_emulated_map_database(sc, cache_dir=args.cache_dir, use_cache=not args.no_cache,
                                     spacing_m=args.spacing, margin_m=args.margin,
                                     region=args.region, progress=_progress)
    t_db = time.perf_counter() - t0
    meta = db.meta.get('emulated', {})
    res = evaluate_retrieval(stream, db, frames=np.arange(0, len(stream), args.every),
                             radius_m=args.radius, progress=_progress)
    print(f'database: {len(db)} images ({meta.get("n_turn_views", "?")} on turn arcs), '
          f'{int(db.n_features.sum())} descriptors; build {meta.get("build_s", float("nan")):.1f}'
          f' s (render+ORB {meta.get("features_s", float("nan")):.1f} s, tree '
          f'{meta.get("tree_s", float("nan")):.1f} s); this run {t_db:.1f} s')
    if meta.get('render_s') is not None and meta.get('n_views'):
        print(f'database render: {1e3 * meta["render_s"] / meta["n_views"]:.1f} ms/image')
    print(f'query frames: render {res["render_ms"]:.1f} ms/frame (incl. faults), '
          f'ORB+query {res["query_ms"]:.1f} ms/frame')
    print(f'top-1 within {args.radius:g} m:')
    for name, r in res['by_kind'].items():
        print(f'  {name:10s} n={r["n"]:5d}  top-1 {100 * r["top1"]:5.1f} %  '
              f'top-5 {100 * r["topk"]:5.1f} %  ambiguous {100 * r["ambiguous"]:5.1f} %  '
              f'median error {r["median_error_m"]:.1f} m')
    print(f'  {"all":10s} n={len(res["frames"]):5d}  top-1 {100 * res["top1"]:5.1f} %')
    if args.json:
        out = {'seed': args.seed, 'n_db': len(db), 'db_meta': {k: v for k, v in meta.items()
                                                               if k != 'yaw_rad'},
               'by_kind': res['by_kind'], 'top1': res['top1'], 'render_ms': res['render_ms'],
               'query_ms': res['query_ms'], 'radius_m': args.radius}
        with open(args.json, 'w') as f:
            json.dump(out, f, indent=2, default=str)
    return 0


if __name__ == '__main__':
    sys.exit(main())
