"""Renderer of the procedural street imagery of the emulated city (:mod:`..city`).

Real rendered images, not labels: ORB has to find and match features on them exactly as on
camera frames. A view is composed, far to near, of

* a **sky** gradient above the horizon;
* the **ground**: the periodic road tile (:func:`.textures.ground_tile`) that repeats with
  the street grid, drawn as a plane homography in a few distance bands with a mip level
  each (no aliasing near the horizon);
* the **facades** within ``max_range_m`` that face the camera, each a procedural texture
  (:func:`.textures.facade_texture`) mapped onto its wall rectangle with
  ``cv2.warpPerspective``. Walls are sorted by a visibility order (painter's algorithm),
  cut at the near plane, and drawn from a mip level chosen per depth strip.

The camera model and the lighting are in :mod:`.optics`; the renderer shades each facade
texture by the lighting before it caches it.

Rendering cost is dominated by the warps; textures are generated once and kept in LRU
caches, and everything is drawn into a 4-channel canvas (OpenCV's 4-channel warp is about
3x faster than the 3-channel one). A frame takes ~5 ms along a drive (texture generation
included), ~4 ms once the textures are cached (``python -m gnsscam_ros.bench.emulation``
measures it).
"""
from __future__ import annotations

import math
import threading
from collections import OrderedDict

import cv2
import numpy as np

from .optics import CameraIntrinsics, Lighting
from .textures import GROUND_PX_PER_M, PX_PER_M, facade_texture, ground_tile, mip_pyramid

#: Bump when rendering changes, so that cached map databases are rebuilt.
RENDER_VERSION = 1


def _translation(x0: float, y0: float) -> np.ndarray:
    return np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])


def visibility_order(seg_xz: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Far-to-near drawing order of vertical walls seen from the camera (painter's order).

    Walls stand on the ground, so occlusion is decided in the top view: wall ``i`` hides
    wall ``j`` where a ray from the camera meets both, ``i`` first. For disjoint segments
    in front of the camera that relation has no cycles; it is evaluated at the middle of
    the overlap of their image-column intervals and sorted topologically (Kahn), farthest
    first among the walls that are free to draw.

    Args:
        seg_xz: (m, 2, 2) wall ground segments in camera coordinates ``(x right,
            z forward)`` [m], clipped to ``z > 0``.
        dist: (m,) tie-break distance (larger is drawn first) [m].

    Returns:
        (m,) indices in drawing order.
    """
    m = len(seg_xz)
    if m <= 1:
        return np.arange(m)
    a, b = seg_xz[:, 0], seg_xz[:, 1]
    ua, ub = a[:, 0] / a[:, 1], b[:, 0] / b[:, 1]
    lo, hi = np.minimum(ua, ub), np.maximum(ua, ub)
    ov_lo = np.maximum(lo[:, None], lo[None, :])
    ov_hi = np.minimum(hi[:, None], hi[None, :])
    overlap = (ov_hi - ov_lo) > 1e-9
    um = 0.5 * (ov_lo + ov_hi)
    d = b - a
    # Ray t (um, 1) meets wall i at a_i + s d_i: s = (um za - xa) / (dx - um dz).
    with np.errstate(divide='ignore', invalid='ignore'):
        s = ((um * a[:, 1][:, None] - a[:, 0][:, None])
             / (d[:, 0][:, None] - um * d[:, 1][:, None]))
        t = a[:, 1][:, None] + s * d[:, 1][:, None]             # (i, pair) depth of wall i
    ti, tj = t, t.T
    hides = overlap & np.isfinite(ti) & np.isfinite(tj) & (ti < tj)   # i hides j
    np.fill_diagonal(hides, False)
    # j must be drawn before i when i hides j: count, for each wall, walls it must wait for.
    waiting = hides.sum(axis=1)
    order, done = [], np.zeros(m, bool)
    far_first = np.argsort(-dist, kind='stable')
    for _ in range(m):
        free = far_first[(waiting[far_first] == 0) & ~done[far_first]]
        k = int(free[0]) if len(free) else int(far_first[~done[far_first]][0])   # cycle
        order.append(k)
        done[k] = True
        waiting -= hides[:, k]
        waiting[k] = -1
    return np.asarray(order)


class StreetRenderer:
    """Renders views of one city under one lighting (textures cached per instance).

    The lighting's response (gain, colour cast, gamma) is baked into the cached textures,
    sky and ground, so a frame costs only the warps; a per-frame exposure ``gain`` is one
    saturating multiply. The texture cache is guarded by a lock, but one instance should
    still not render from two threads at once (OpenCV output buffers are per call, the
    numbers are fine, the cache churn is not): use one renderer per thread.

    Args:
        city: The city (``datasets.city.City``).
        intrinsics: Camera model (default :class:`CameraIntrinsics`).
        lighting: Illumination (default :class:`Lighting`).
        max_range_m: Facades farther than this are not drawn [m].
        near_m: Near clipping plane [m].
        noise_std: Std of the additive sensor noise [grey levels] (0: none).
        cache_size: Number of facades whose lit mip pyramids are kept.
        seed: Seed of the sensor noise bank.
    """

    def __init__(self, city, intrinsics: CameraIntrinsics | None = None,
                 lighting: Lighting | None = None, max_range_m: float = 150.0,
                 near_m: float = 0.3, noise_std: float = 2.0, cache_size: int = 96,
                 seed: int = 0):
        self.city = city
        self.intrinsics = intrinsics or CameraIntrinsics()
        self.lighting = lighting or Lighting()
        self.max_range_m = float(max_range_m)
        self.near_m = float(near_m)
        self.noise_std = float(noise_std)
        self._cache: OrderedDict[int, list[np.ndarray]] = OrderedDict()
        self._cache_size = int(cache_size)
        self._lock = threading.Lock()
        self._lut = self.lighting.lut()
        self._K = self.intrinsics.matrix
        heights = city.blocks[:, 4] if len(city.blocks) else np.array([20.0])
        self._caster_m = float(min(self.lighting.shadow_caster_m, np.median(heights)))
        self._background = self._make_background()
        tile = cv2.LUT(ground_tile(float(city.pitch_m), float(city.street_width_m),
                                   GROUND_PX_PER_M), self._lut)
        self._ground_ppm = tile.shape[0] / float(city.pitch_m)
        self._ground = mip_pyramid(cv2.cvtColor(np.tile(tile, (3, 3, 1)), cv2.COLOR_BGR2BGRA),
                                   min_side=16)
        self._noise = self._make_noise(seed)

    # ------------------------------------------------------------------ fixed layers
    def _make_background(self) -> np.ndarray:
        """(H, W, 4) sky gradient above the horizon, far-ground colour below."""
        cam = self.intrinsics
        h, w = cam.height, cam.width
        bgr = np.empty((h, w, 3), np.uint8)
        horizon = int(math.floor(cam.cy)) + 1
        top = np.asarray(self.lighting.sky_zenith_bgr, np.float64)
        bot = np.asarray(self.lighting.sky_horizon_bgr, np.float64)
        k = (np.arange(horizon) / max(horizon - 1, 1))[:, None] ** 0.7
        sky = top * (1 - k) + bot * k
        bgr[:horizon] = np.rint(sky).astype(np.uint8)[:, None, :]
        bgr[horizon:] = (112, 114, 116)
        return cv2.cvtColor(cv2.LUT(bgr, self._lut), cv2.COLOR_BGR2BGRA)

    def _make_noise(self, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """A small bank of sensor noise frames (positive and negative parts, uint8)."""
        if self.noise_std <= 0:
            return []
        rng = np.random.default_rng([int(seed), 0x401CE])
        cam = self.intrinsics
        bank = []
        for _ in range(4):
            n = np.rint(rng.normal(0.0, self.noise_std, (cam.height, cam.width, 3)))
            n = np.clip(n, -255, 255)
            bank.append((np.maximum(n, 0).astype(np.uint8), np.maximum(-n, 0).astype(np.uint8)))
        return bank

    # ------------------------------------------------------------------ facade textures
    def _facade_levels(self, i: int) -> list[np.ndarray]:
        """Lit BGRA mip pyramid of facade ``i`` (LRU cached)."""
        with self._lock:
            levels = self._cache.get(i)
            if levels is not None:
                self._cache.move_to_end(i)
                return levels
        f = self.city.facades
        width_m = float(np.linalg.norm(f.p1_m[i] - f.p0_m[i]))
        height_m = float(f.height_m[i])
        tex = facade_texture(int(f.style_id[i]), width_m, height_m)
        lit = cv2.LUT(self._light_facade(tex, f.normal[i], height_m), self._lut)
        levels = mip_pyramid(cv2.cvtColor(lit, cv2.COLOR_BGR2BGRA))
        with self._lock:
            self._cache[i] = levels
            while len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        return levels

    def _light_facade(self, tex: np.ndarray, normal: np.ndarray, height_m: float) -> np.ndarray:
        """Shade a texture: Lambert term of the wall orientation, shadow band at the bottom.

        The buildings across the street (``shadow_caster_m`` high, one street width away)
        shade a sunlit wall up to ``h_caster - d tan(el)`` where ``d`` is the distance to
        them measured along the sun's azimuth.
        """
        li = self.lighting
        sun_h = np.array([math.cos(li.sun_azimuth_rad), math.sin(li.sun_azimuth_rad)])
        cos_inc = float(np.dot(normal, sun_h))
        lambert = max(0.0, cos_inc) * math.cos(li.sun_elevation_rad)
        sunlit = li.ambient + (1.0 - li.ambient) * min(1.0, 1.6 * lambert)
        scale = 1.0 / (li.ambient + 0.6 * (1.0 - li.ambient))     # keep mean brightness
        out = cv2.convertScaleAbs(tex, alpha=min(sunlit * scale, 1.6))
        if lambert > 0.0 and li.ambient < 0.95:
            d = self.city.street_width_m / max(cos_inc, 0.15)
            shadow_m = self._caster_m - d * math.tan(li.sun_elevation_rad)
            if shadow_m > 0.0:
                rows = min(tex.shape[0], int(round(shadow_m * tex.shape[0] / height_m)))
                top = tex.shape[0] - rows
                out[top:] = cv2.convertScaleAbs(tex[top:], alpha=li.ambient * scale)
        return out

    # ------------------------------------------------------------------ geometry
    @staticmethod
    def _rotation(yaw: float) -> np.ndarray:
        """World (ENU) -> camera (x right, y down, z forward) for a level camera."""
        c, s = math.cos(yaw), math.sin(yaw)
        return np.array([[s, -c, 0.0], [0.0, 0.0, -1.0], [c, s, 0.0]])

    def _draw_ground(self, canvas: np.ndarray, centre: np.ndarray, R: np.ndarray) -> None:
        cam = self.intrinsics
        h_cam = float(centre[2])
        if h_cam <= 0.05:
            return
        city = self.city
        pitch = float(city.pitch_m)
        # Tile origin: the nearest intersection sits in the middle period of the 3x3 tile.
        i = int(np.argmin(np.abs(city.street_e_m - centre[0])))
        j = int(np.argmin(np.abs(city.street_n_m - centre[1])))
        e0 = city.street_e_m[i] - 1.5 * pitch
        n0 = city.street_n_m[j] - 1.5 * pitch
        horizon = int(math.floor(cam.cy)) + 1
        # Distance bands with a mip level each: depth d seen at row y is fy h / (y - cy);
        # the texture is minified by ~ppm d^1.5 / (f sqrt(h)) (geometric mean of the
        # lateral and depth compressions), so each doubling band takes the next level.
        bounds_m = (1e9, 120.0, 64.0, 36.0, 20.0, 11.0, 0.0)
        levels = (None, 4, 3, 2, 1, 0)
        KR = self._K @ R
        off = 0.5 / self._ground_ppm
        for (d_far, d_near), lvl in zip(zip(bounds_m[:-1], bounds_m[1:]), levels):
            if lvl is None:
                continue
            lvl = min(lvl, len(self._ground) - 1)
            y0 = max(horizon, int(math.ceil(cam.cy + cam.fy * h_cam / d_far)))
            y1 = (cam.height if d_near <= 0 else
                  min(cam.height, int(math.ceil(cam.cy + cam.fy * h_cam / d_near))))
            if y1 <= y0:
                continue
            s = (2 ** lvl) / self._ground_ppm
            # Tile pixel (c, r) of level lvl -> world (e0 + 2^l c / ppm + off, ..., 0).
            M = np.array([[s, 0.0, e0 + off - centre[0]], [0.0, s, n0 + off - centre[1]],
                          [0.0, 0.0, -h_cam]])
            H = _translation(0.0, y0) @ KR @ M
            cv2.warpPerspective(self._ground[lvl], H, (cam.width, y1 - y0),
                                dst=canvas[y0:y1], flags=cv2.INTER_LINEAR,
                                borderMode=cv2.BORDER_TRANSPARENT)

    def _draw_facades(self, canvas: np.ndarray, centre: np.ndarray, R: np.ndarray) -> int:
        """Draw the facades in view far to near; returns how many were drawn."""
        cam = self.intrinsics
        f = self.city.facades
        idx = self.city.facades_near(centre, self.max_range_m, facing=True)
        if len(idx) == 0:
            return 0
        # Ground segments in camera coordinates (x right, z forward); level camera, so
        # depth z does not depend on height and the near plane cuts walls vertically.
        cz, sz = R[2, 0], R[2, 1]
        r0, r1 = f.p0_m[idx] - centre[:2], f.p1_m[idx] - centre[:2]
        x0, z0 = sz * r0[:, 0] - cz * r0[:, 1], cz * r0[:, 0] + sz * r0[:, 1]
        x1, z1 = sz * r1[:, 0] - cz * r1[:, 1], cz * r1[:, 0] + sz * r1[:, 1]
        near = self.near_m
        dz = z1 - z0
        with np.errstate(divide='ignore', invalid='ignore'):
            t_near = np.where(np.abs(dz) > 1e-12, (near - z0) / dz, np.nan)
        # Visible parameter range [ta, tb] along p0 -> p1 (z >= near).
        ta = np.clip(np.where(z0 >= near, 0.0, np.where(dz > 0, t_near, 2.0)), 0.0, 1.0)
        tb = np.clip(np.where(z1 >= near, 1.0, np.where(dz < 0, t_near, -1.0)), 0.0, 1.0)
        xa, za = x0 + ta * (x1 - x0), z0 + ta * dz
        xb, zb = x0 + tb * (x1 - x0), z0 + tb * dz
        ok = (tb - ta) > 1e-6
        with np.errstate(divide='ignore', invalid='ignore'):
            ua = cam.fx * xa / za + cam.cx
            ub = cam.fx * xb / zb + cam.cx
        # Horizontal frustum cull with the image-column interval of the visible part.
        ok &= (np.maximum(ua, ub) >= -1) & (np.minimum(ua, ub) <= cam.width)
        if not ok.any():
            return 0
        sel = np.flatnonzero(ok)
        seg = np.stack([np.column_stack([xa[sel], za[sel]]),
                        np.column_stack([xb[sel], zb[sel]])], axis=1)
        o = sel[visibility_order(seg, np.minimum(za[sel], zb[sel]))]
        gi = idx[o]
        m = len(gi)
        # Per wall, vectorised: texture size, texture -> image homography, and at 9
        # columns of its visible part the mip level and the screen extent.
        d01 = f.p1_m[gi] - f.p0_m[gi]
        width = np.hypot(d01[:, 0], d01[:, 1])
        height = f.height_m[gi]
        w_px = np.maximum(8, np.rint(width * PX_PER_M)).astype(int)
        h_px = np.maximum(8, np.rint(height * PX_PER_M)).astype(int)
        # Texture (c, r) of level 0 -> world: top-left + (c + .5) a + (r + .5) b.
        a = np.zeros((m, 3))
        a[:, :2] = d01 / w_px[:, None]
        b = np.zeros((m, 3))
        b[:, 2] = -height / h_px
        tl = np.column_stack([f.p0_m[gi] - centre[:2], height - centre[2]]) + 0.5 * (a + b)
        H0 = np.einsum('ij,mjk->mik', self._K @ R, np.stack([a, b, tl], axis=2))
        t = ta[o][:, None] + (tb - ta)[o][:, None] * np.linspace(0.0, 1.0, 9)[None, :]
        x = x0[o][:, None] + t * (x1 - x0)[o][:, None]
        z = z0[o][:, None] + t * dz[o][:, None]
        ax, az = ((x1 - x0)[o] / width)[:, None], (dz[o] / width)[:, None]
        # Minification ~ ppm / sqrt(vertical * horizontal image px per metre) at depth z:
        # vertical fy / z, horizontal fx |ax z - x az| / z^2 along the wall (ax, az).
        h_pxm = cam.fx * np.abs(ax * z - x * az) / (z * z)
        ratio = (w_px / width)[:, None] / np.sqrt((cam.fy / z) * np.maximum(h_pxm, 1e-6))
        lvl = np.clip(np.floor(np.log2(np.maximum(ratio, 1e-9)) + 0.25), 0, 15).astype(int)
        u = cam.fx * x / z + cam.cx
        y_top = cam.cy + cam.fy * (centre[2] - height)[:, None] / z
        y_bot = cam.cy + cam.fy * centre[2] / z
        col = t * w_px[:, None]                                    # level-0 columns
        drawn = 0
        for k in range(m):
            drawn += self._draw_wall(canvas, int(gi[k]), H0[k], lvl[k].tolist(),
                                     col[k].tolist(), u[k].tolist(), y_top[k].tolist(),
                                     y_bot[k].tolist(), bool(ta[o[k]] > 0),
                                     bool(tb[o[k]] < 1))
        return drawn

    def _draw_wall(self, canvas, i, H0, lvl, col, u, y_top, y_bot, cut_lo, cut_hi) -> int:
        """Warp one wall, strip by strip of constant mip level, into the canvas.

        ``lvl``, ``col``, ``u``, ``y_top``, ``y_bot`` are sampled at the same 9 columns of
        the visible part; strips run between samples where the level changes.
        """
        cam = self.intrinsics
        levels = self._facade_levels(i)
        bounds = [0] + [k for k in range(1, len(lvl)) if lvl[k] != lvl[k - 1]] + [len(lvl) - 1]
        drawn = 0
        for k0, k1 in zip(bounds[:-1], bounds[1:]):
            L = min(lvl[k0], len(levels) - 1)
            bx0 = max(0, int(math.floor(min(u[k0], u[k1]))) - 1)
            bx1 = min(cam.width, int(math.ceil(max(u[k0], u[k1]))) + 2)
            by0 = max(0, int(math.floor(min(y_top[k0], y_top[k1]))) - 1)
            by1 = min(cam.height, int(math.ceil(max(y_bot[k0], y_bot[k1]))) + 2)
            if bx1 <= bx0 or by1 <= by0:
                continue
            tex = levels[L]
            sc = 1 << L
            # Crop the texture to the strip's columns (one column of overlap with the
            # next strip): where the wall is cut by the near plane, pixels whose rays meet
            # the wall's plane behind the camera then map outside the crop, and
            # BORDER_TRANSPARENT leaves them alone.
            c0 = max(0, int(math.floor(col[k0] / sc)) - 1)
            c1 = min(tex.shape[1], int(math.ceil(col[k1] / sc)) + 1)
            if cut_lo:
                c0 = max(c0, int(math.ceil(col[0] / sc)))
            if cut_hi:
                c1 = min(c1, int(math.floor(col[-1] / sc)) + 1)
            if c1 - c0 < 2:
                continue
            # H = T(-bx0, -by0) H0 S, S: crop (c, r) of level L -> level-0 (sc (c + c0), sc r).
            H = H0 * np.array([sc, sc, 1.0])
            H[:, 2] += H0[:, 0] * (sc * c0)
            H[0] -= bx0 * H[2]
            H[1] -= by0 * H[2]
            cv2.warpPerspective(tex[:, c0:c1], H, (bx1 - bx0, by1 - by0),
                                dst=canvas[by0:by1, bx0:bx1], flags=cv2.INTER_LINEAR,
                                borderMode=cv2.BORDER_TRANSPARENT)
            drawn = 1
        return drawn

    # ------------------------------------------------------------------ public
    def render(self, pose, gain: float = 1.0, noise_index: int | None = None,
               stats: dict | None = None) -> np.ndarray:
        """Render the view from a camera pose.

        Args:
            pose: ``(east_m, north_m, up_m, yaw_rad)`` of the camera centre in the city's
                ENU frame; yaw counter-clockwise from east.
            gain: Extra exposure multiplier for this frame (auto-exposure jitter).
            noise_index: Which frame of the sensor-noise bank to add (None: no noise).
            stats: Optional dict that receives ``n_facades`` (walls drawn).

        Returns:
            (H, W, 3) uint8 BGR image.

        Raises:
            ValueError: for a non-finite pose or gain.
        """
        e, n, u, yaw = (float(v) for v in pose)
        if not all(math.isfinite(v) for v in (e, n, u, yaw, gain)):
            raise ValueError(f'pose and gain must be finite, got {pose}, {gain}')
        centre = np.array([e, n, u])
        R = self._rotation(yaw)
        canvas = self._background.copy()
        self._draw_ground(canvas, centre, R)
        drawn = self._draw_facades(canvas, centre, R)
        out = cv2.cvtColor(canvas, cv2.COLOR_BGRA2BGR)
        if abs(gain - 1.0) > 1e-4:
            out = cv2.convertScaleAbs(out, alpha=gain)
        if noise_index is not None and self._noise:
            pos, neg = self._noise[int(noise_index) % len(self._noise)]
            cv2.add(out, pos, dst=out)
            cv2.subtract(out, neg, dst=out)
        if stats is not None:
            stats['n_facades'] = drawn
        return out


_RENDERERS: OrderedDict = OrderedDict()


def render_view(city, pose, intrinsics: CameraIntrinsics | None = None,
                lighting: Lighting | None = None,
                rng: np.random.Generator | None = None) -> np.ndarray:
    """Render one view of ``city`` (convenience wrapper around :class:`StreetRenderer`).

    Renderers (and their texture caches) are kept for the last few (city, camera,
    lighting) combinations, so repeated calls are fast.

    Args:
        city: The city.
        pose: ``(east_m, north_m, up_m, yaw_rad)`` of the camera [m, m, m, rad].
        intrinsics: Camera model (default 640x480, 80 deg HFOV).
        lighting: Illumination (default :class:`Lighting`).
        rng: When given, draws the exposure jitter (1 % std) and the sensor-noise frame;
            None renders the noiseless nominal image.

    Returns:
        (H, W, 3) uint8 BGR image.
    """
    intrinsics = intrinsics or CameraIntrinsics()
    lighting = lighting or Lighting()
    key = (id(city), intrinsics, lighting)
    r = _RENDERERS.get(key)
    if r is None or r.city is not city:
        r = StreetRenderer(city, intrinsics, lighting)
        _RENDERERS[key] = r
        while len(_RENDERERS) > 4:
            _RENDERERS.popitem(last=False)
    _RENDERERS.move_to_end(key)
    if rng is None:
        return r.render(pose)
    gain = float(np.exp(rng.normal(0.0, 0.01)))
    return r.render(pose, gain=gain, noise_index=int(rng.integers(1 << 30)))
