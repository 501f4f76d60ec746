"""Procedural street imagery of the emulated city (:mod:`..datasets.city`).

Real rendered images, not labels: ORB has to find and match features on them exactly as on
camera frames. A view is composed, far to near, of

* a **sky** gradient above the horizon;
* the **ground**: a periodic road tile (asphalt, curbs, pavements, dashed lane lines,
  zebra crossings) that repeats with the street grid, drawn as a plane homography in a few
  distance bands with a mip level each (no aliasing near the horizon);
* the **facades** within ``max_range_m`` that face the camera, each a procedural texture
  (:func:`facade_texture`: wall material, window grids with frames, mullions, blinds and
  curtains, balconies, shop fronts with signs and text, doors, posters) mapped onto its
  wall rectangle with ``cv2.warpPerspective``. Walls are sorted by a visibility order
  (painter's algorithm), cut at the near plane, and drawn from a mip level chosen per
  depth strip.

Textures depend only on a facade's ``style_id`` and its size: facades that share a style
(about a third of them, see :func:`..datasets.city.make_city`) look the same, the deliberate
repetition that makes some images ambiguous. Lighting (:class:`Lighting`) shades walls by
their orientation to the sun, puts the lower part of sunlit walls in the shadow of the
buildings across the street, and applies a global exposure gain, gamma and colour cast.

Camera model: pinhole (:class:`CameraIntrinsics`, 640x480, 80 deg horizontal field of view
by default), level (no pitch or roll; the emulated ground is flat), looking along the yaw
``psi`` (ENU, counter-clockwise from east). Camera axes: x right, y down, z forward.

Rendering cost is dominated by the warps; textures are generated once and kept in LRU
caches, and everything is drawn into a 4-channel canvas (OpenCV's 4-channel warp is about
3x faster than the 3-channel one). A frame takes ~5 ms along a drive (texture generation
included), ~4 ms once the textures are cached.
"""
from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

PX_PER_M = 20.0          # facade texture resolution [px/m]
GROUND_PX_PER_M = 8.0    # ground tile resolution [px/m]
_STYLE_SALT = 0x5EED     # seeds facade styles: default_rng([style_id, salt, ...])

# Shop sign words; a random suffix makes most signs unique.
_WORDS = ('CAFE', 'BAKERY', 'APOTHEKE', 'HOTEL', 'BANK', 'PIZZA', 'KIOSK', 'MODE', 'BAR',
          'FRISEUR', 'OPTIK', 'BUCHHANDLUNG', 'BLUMEN', 'SPORT', 'TABAK', 'BISTRO', 'DELI',
          'SUSHI', 'REISEN', 'SCHUHE', 'PHOTO', 'WEIN', 'TEA', 'MARKT', 'BURGER', 'ASIA',
          'JUWELIER', 'GALERIE', 'POST', 'LOTTO', 'KEBAP', 'MUSIK', 'SPIELE', 'HANDY')
_FONTS = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX,
          cv2.FONT_HERSHEY_TRIPLEX, cv2.FONT_HERSHEY_PLAIN)


# ============================================================================ parameters
@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole camera with square pixels and the principal point at the image centre.

    Attributes:
        width: Image width [px].
        height: Image height [px].
        hfov_deg: Horizontal field of view [deg].
    """

    width: int = 640
    height: int = 480
    hfov_deg: float = 80.0

    def __post_init__(self):
        if self.width < 16 or self.height < 16:
            raise ValueError(f'image size must be at least 16x16, got '
                             f'{self.width}x{self.height}')
        if not 10.0 <= self.hfov_deg <= 150.0:
            raise ValueError(f'hfov_deg must be in [10, 150], got {self.hfov_deg}')

    @property
    def fx(self) -> float:
        """Focal length [px]."""
        return 0.5 * self.width / math.tan(math.radians(0.5 * self.hfov_deg))

    @property
    def fy(self) -> float:
        """Focal length [px] (square pixels)."""
        return self.fx

    @property
    def cx(self) -> float:
        """Principal point column [px] (pixel centres at integers)."""
        return 0.5 * (self.width - 1)

    @property
    def cy(self) -> float:
        """Principal point row [px]; also the horizon row of a level camera."""
        return 0.5 * (self.height - 1)

    @property
    def matrix(self) -> np.ndarray:
        """(3, 3) camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def as_dict(self) -> dict:
        return {'width': self.width, 'height': self.height, 'hfov_deg': self.hfov_deg,
                'fx': self.fx, 'fy': self.fy, 'cx': self.cx, 'cy': self.cy}


@dataclass(frozen=True)
class Lighting:
    """Scene illumination and camera response of one pass through the city.

    Attributes:
        gain: Global exposure multiplier (1 = nominal).
        gamma: Response exponent, ``out = 255 (gain * c * in / 255) ** gamma``.
        cast_bgr: Per-channel multipliers (colour cast, white balance error).
        sun_azimuth_rad: Sun direction, ENU, counter-clockwise from east [rad].
        sun_elevation_rad: Sun elevation above the horizon [rad].
        ambient: Brightness of shaded walls relative to a wall facing the sun (1 = diffuse,
            overcast light without shadows).
        shadow_caster_m: Typical height of the buildings across the street that cast the
            shadow band on sunlit walls [m].
        sky_zenith_bgr: Sky colour at the top of the image.
        sky_horizon_bgr: Sky colour at the horizon.
    """

    gain: float = 1.0
    gamma: float = 1.0
    cast_bgr: tuple[float, float, float] = (1.0, 1.0, 1.0)
    sun_azimuth_rad: float = 0.7
    sun_elevation_rad: float = 0.7
    ambient: float = 0.55
    shadow_caster_m: float = 22.0
    sky_zenith_bgr: tuple[int, int, int] = (205, 140, 85)
    sky_horizon_bgr: tuple[int, int, int] = (240, 220, 200)

    def __post_init__(self):
        if not (self.gain > 0 and self.gamma > 0 and 0 < self.ambient <= 1):
            raise ValueError('gain and gamma must be > 0 and ambient in (0, 1]')

    @classmethod
    def sunny(cls, rng: np.random.Generator) -> 'Lighting':
        """A random sunny daytime lighting (hard shadows, warm or neutral cast)."""
        return cls(gain=float(rng.uniform(0.95, 1.1)), gamma=float(rng.uniform(0.9, 1.05)),
                   cast_bgr=tuple(float(v) for v in rng.uniform([0.92, 0.97, 1.0],
                                                                [1.0, 1.0, 1.06])),
                   sun_azimuth_rad=float(rng.uniform(-np.pi, np.pi)),
                   sun_elevation_rad=float(rng.uniform(0.45, 1.0)),
                   ambient=float(rng.uniform(0.5, 0.65)),
                   sky_zenith_bgr=tuple(int(v) for v in rng.integers([190, 120, 60],
                                                                     [230, 160, 100])),
                   sky_horizon_bgr=tuple(int(v) for v in rng.integers([225, 205, 185],
                                                                      [250, 230, 215])))

    @classmethod
    def overcast(cls, rng: np.random.Generator) -> 'Lighting':
        """A random overcast lighting (no shadows, darker, bluish, flatter response)."""
        return cls(gain=float(rng.uniform(0.75, 0.9)), gamma=float(rng.uniform(1.05, 1.25)),
                   cast_bgr=tuple(float(v) for v in rng.uniform([1.0, 0.96, 0.88],
                                                                [1.06, 1.0, 0.95])),
                   sun_azimuth_rad=float(rng.uniform(-np.pi, np.pi)),
                   sun_elevation_rad=float(rng.uniform(0.3, 0.9)),
                   ambient=float(rng.uniform(0.85, 0.95)),
                   sky_zenith_bgr=tuple(int(v) for v in rng.integers([170, 165, 160],
                                                                     [190, 185, 180])),
                   sky_horizon_bgr=tuple(int(v) for v in rng.integers([215, 212, 208],
                                                                      [230, 228, 225])))

    def as_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}

    def lut(self, gain: float = 1.0) -> np.ndarray:
        """(1, 256, 3) uint8 per-channel response table for ``cv2.LUT`` (BGR images).

        Args:
            gain: Extra exposure multiplier (e.g. per-frame auto-exposure jitter).
        """
        v = np.arange(256, dtype=np.float64) / 255.0
        g = self.gain * gain * np.asarray(self.cast_bgr, dtype=np.float64)
        out = 255.0 * np.clip(v[:, None] * g[None, :], 0.0, 1.0) ** self.gamma
        return np.clip(np.rint(out), 0, 255).astype(np.uint8)[None, :, :]


# ============================================================================ textures
def _hsv_bgr(h: float, s: float, v: float) -> tuple[int, int, int]:
    """HSV in [0, 1] -> BGR ints."""
    px = np.uint8([[[round(h * 179) % 180, round(s * 255), round(v * 255)]]])
    b, g, r = cv2.cvtColor(px, cv2.COLOR_HSV2BGR)[0, 0]
    return int(b), int(g), int(r)


def _shade(c, f: float) -> tuple[int, int, int]:
    """Colour ``c`` scaled by ``f`` (clipped)."""
    return tuple(int(min(255, max(0, round(x * f)))) for x in c)


@dataclass(frozen=True)
class _Style:
    """Architectural parameters of one facade style (all lengths in metres)."""

    material: str
    wall: tuple
    trim: tuple
    frame: tuple
    glass: tuple
    shutter: tuple | None
    ground_h: float
    floor_h: float
    bay_w: float
    margin: float
    win_w: float
    win_h: float
    sill_h: float
    frame_t: float
    mullion: int          # 0 none, 1 vertical split, 2 cross, 3 six panes
    pediment: bool
    string_course: bool
    balcony_p: float
    shop: bool
    cornice_h: float
    pilaster: bool


@lru_cache(maxsize=4096)
def _style(style_id: int) -> _Style:
    """The (deterministic) style parameters of ``style_id``."""
    rng = np.random.default_rng([int(style_id), _STYLE_SALT])
    material = str(rng.choice(['plaster', 'brick', 'stone', 'glass'],
                              p=[0.45, 0.25, 0.15, 0.15]))
    if material == 'brick':
        wall = _hsv_bgr(rng.uniform(0.0, 0.07), rng.uniform(0.45, 0.75), rng.uniform(0.4, 0.7))
    elif material == 'stone':
        wall = _hsv_bgr(rng.uniform(0.05, 0.15), rng.uniform(0.05, 0.3), rng.uniform(0.55, 0.8))
    elif material == 'glass':
        wall = _hsv_bgr(rng.uniform(0.5, 0.65), rng.uniform(0.1, 0.4), rng.uniform(0.3, 0.55))
    else:
        wall = _hsv_bgr(rng.uniform(0.0, 1.0), rng.uniform(0.05, 0.45), rng.uniform(0.55, 0.92))
    trim = _shade(wall, rng.choice([0.7, 1.25, 1.4]))
    frame = tuple(int(v) for v in rng.choice([[245, 245, 245], [40, 40, 40], [30, 60, 90],
                                              [90, 110, 60], [200, 200, 190], [60, 40, 120]]))
    glass = _hsv_bgr(rng.uniform(0.5, 0.65), rng.uniform(0.1, 0.5), rng.uniform(0.12, 0.4))
    shutter = (_hsv_bgr(rng.uniform(0, 1), rng.uniform(0.3, 0.7), rng.uniform(0.3, 0.7))
               if material in ('plaster', 'stone') and rng.random() < 0.35 else None)
    floor_h = float(rng.uniform(3.0, 3.8))
    bay_w = float(rng.uniform(2.6, 4.6))
    return _Style(
        material=material, wall=wall, trim=trim, frame=frame, glass=glass, shutter=shutter,
        ground_h=float(rng.uniform(3.8, 5.0)), floor_h=floor_h, bay_w=bay_w,
        margin=float(rng.uniform(0.6, 1.8)),
        win_w=float(bay_w * rng.uniform(0.38, 0.62)),
        win_h=float(floor_h * rng.uniform(0.42, 0.62)),
        sill_h=float(rng.uniform(0.8, 1.0)), frame_t=float(rng.uniform(0.07, 0.14)),
        mullion=int(rng.integers(0, 4)), pediment=bool(rng.random() < 0.25),
        string_course=bool(rng.random() < 0.5), balcony_p=float(rng.choice([0.0, 0.15, 0.5])),
        shop=bool(rng.random() < 0.65), cornice_h=float(rng.uniform(0.5, 1.2)),
        pilaster=bool(rng.random() < 0.5))


def _noise_field(rng: np.random.Generator, h: int, w: int, cell_px: int) -> np.ndarray:
    """Smooth random field in [-1, 1] with features of ~``cell_px`` pixels, (h, w) float32."""
    small = rng.uniform(-1.0, 1.0, (h // cell_px + 2, w // cell_px + 2)).astype(np.float32)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)


@lru_cache(maxsize=1)
def _grain_tile() -> np.ndarray:
    """(128, 128) float32 fine grain (std 2.5 grey levels), tiled over every wall."""
    return np.random.default_rng(0x6A1A).normal(0.0, 2.5, (128, 128)).astype(np.float32)


def _masonry(rng: np.random.Generator, h: int, w: int, course: int, unit: int,
             jitter: float, joint: float) -> np.ndarray:
    """(h, w) float32 brightness offsets of a running-bond masonry wall.

    Each unit (``unit`` x ``course`` px) gets its own offset in ``[-jitter, jitter]``,
    odd courses are shifted by half a unit, joints get ``joint``. Built from repeats and
    tiles (no per-pixel index arithmetic), which keeps a facade texture at a few ms.
    """
    unit += unit % 2
    half = unit // 2
    n_r, n_c = h // course + 1, w // unit + 2
    cells = np.repeat(rng.uniform(-jitter, jitter, (n_r, n_c)).astype(np.float32), 2, axis=1)
    cells[1::2] = np.roll(cells[1::2], 1, axis=1)
    field = np.repeat(np.repeat(cells, course, axis=0), half, axis=1)[:h, :w]
    mask = np.zeros((2 * course, unit), bool)
    mask[0, :] = mask[course, :] = True
    mask[:course, 0] = mask[course:, half] = True
    field[np.tile(mask, (h // (2 * course) + 1, w // unit + 1))[:h, :w]] = joint
    return field


def _wall_material(st: _Style, rng: np.random.Generator, h: int, w: int,
                   ppm: float) -> np.ndarray:
    """(h, w, 3) uint8 bare wall of the style's material."""
    # Low-frequency weathering stains (low contrast: colour, not corners) and grain.
    off = _noise_field(rng, h, w, max(4, int(3 * ppm))) * 14.0
    grain = _grain_tile()
    off += np.tile(grain, (h // grain.shape[0] + 1, w // grain.shape[1] + 1))[:h, :w]
    if st.material == 'brick':
        off += _masonry(rng, h, w, max(2, int(round(0.16 * ppm))),
                        max(4, int(round(0.45 * ppm))), 18.0, 0.0)
        mortar = 0.45 * float(np.mean(st.wall))     # mortar: lighter than the bricks
        off[_masonry(rng, h, w, max(2, int(round(0.16 * ppm))),
                     max(4, int(round(0.45 * ppm))), 0.0, 1.0) > 0.5] += mortar
    elif st.material == 'stone':
        off += _masonry(rng, h, w, max(4, int(round(0.55 * ppm))),
                        max(8, int(round(1.1 * ppm))), 12.0, -0.28 * float(np.mean(st.wall)))
    return cv2.merge([np.clip(off + c, 0, 255).astype(np.uint8) for c in st.wall])


def _px(v_m: float, ppm: float) -> int:
    return int(round(v_m * ppm))


def _rect(img, x0, y0, x1, y1, colour, thickness=-1):
    cv2.rectangle(img, (int(x0), int(y0)), (int(x1) - 1, int(y1) - 1), colour, thickness)


def _window(img, st: _Style, rng: np.random.Generator, x0: int, y0: int, ww: int, wh: int,
            ppm: float, lit_p: float = 0.1) -> None:
    """One window with frame, mullions, glass content, sill and ornaments, in place."""
    ft = max(1, _px(st.frame_t, ppm))
    x1, y1 = x0 + ww, y0 + wh
    if st.shutter is not None and rng.random() < 0.8:
        sw = ww // 2
        colour = _shade(st.shutter, rng.uniform(0.9, 1.1))
        for sx in (x0 - sw - 1, x1 + 1):
            _rect(img, sx, y0, sx + sw, y1, colour)
            for yy in range(y0 + 3, y1 - 1, 4):     # slats
                cv2.line(img, (sx + 1, yy), (sx + sw - 2, yy), _shade(colour, 0.7), 1)
    if st.pediment:
        peak = max(3, wh // 5)
        pts = np.array([[x0 - ft * 2, y0 - ft], [x1 + ft * 2, y0 - ft],
                        [(x0 + x1) // 2, y0 - ft - peak]], np.int32)
        cv2.fillConvexPoly(img, pts, st.trim)
    else:
        _rect(img, x0 - ft, y0 - 2 * ft, x1 + ft, y0 - ft, st.trim)   # lintel
    glass = _shade(st.glass, rng.uniform(0.8, 1.25))
    if rng.random() < lit_p:
        glass = (80, 190, 235)      # a lit room, warm
    _rect(img, x0, y0, x1, y1, glass)
    # Inside: a reflection gradient, blinds, curtains: differs from window to window.
    if rng.random() < 0.5:
        yy = y0 + int(rng.uniform(0.1, 0.9) * wh)
        _rect(img, x0, y0, x1, yy, _shade(glass, 1.35))
    if rng.random() < 0.45:
        blind = y0 + int(rng.uniform(0.15, 0.9) * wh)
        bc = tuple(int(v) for v in rng.integers(150, 240, 3))
        _rect(img, x0, y0, x1, blind, bc)
        for yy in range(y0 + 2, blind, 3):
            cv2.line(img, (x0, yy), (x1 - 1, yy), _shade(bc, 0.82), 1)
    if rng.random() < 0.3:
        cc = tuple(int(v) for v in rng.integers(40, 240, 3))
        cw = max(2, int(ww * rng.uniform(0.15, 0.35)))
        _rect(img, x0, y0, x0 + cw, y1, cc)
        if rng.random() < 0.6:
            _rect(img, x1 - cw, y0, x1, y1, cc)
    # Frame and mullions.
    _rect(img, x0, y0, x1, y1, st.frame, ft)
    mt = max(1, ft - 1)
    if st.mullion in (1, 2, 3):
        xm = (x0 + x1) // 2
        _rect(img, xm - mt // 2, y0, xm - mt // 2 + mt, y1, st.frame)
    if st.mullion == 2:
        ym = y0 + wh // 3
        _rect(img, x0, ym, x1, ym + mt, st.frame)
    elif st.mullion == 3:
        for k in (1, 2):
            ym = y0 + k * wh // 3
            _rect(img, x0, ym, x1, ym + mt, st.frame)
    _rect(img, x0 - ft, y1, x1 + ft, y1 + max(2, ft + 1), st.trim)   # sill
    if rng.random() < 0.12:          # flower box
        by = y1 + max(2, ft + 1)
        _rect(img, x0, by, x1, by + max(3, _px(0.2, ppm)), (40, 70, 120))
        for _ in range(int(rng.integers(3, 7))):
            cx = int(rng.integers(x0, x1))
            colour = tuple(int(v) for v in rng.choice([[40, 40, 200], [60, 160, 60],
                                                      [200, 80, 200], [30, 200, 230]]))
            cv2.circle(img, (cx, by), max(1, _px(0.12, ppm)), colour, -1)


def _balcony(img, st: _Style, x0: int, x1: int, y_floor: int, ppm: float) -> None:
    """Railing in front of the lower part of a window bay, in place."""
    top = y_floor - _px(1.0, ppm)
    _rect(img, x0, y_floor - max(2, _px(0.15, ppm)), x1, y_floor, _shade(st.trim, 0.8))
    cv2.line(img, (x0, top), (x1, top), st.frame, max(1, _px(0.06, ppm)))
    step = max(3, _px(0.15, ppm))
    for x in range(x0, x1, step):
        cv2.line(img, (x, top), (x, y_floor), st.frame, 1)


def _sign_text(rng: np.random.Generator) -> str:
    word = str(rng.choice(_WORDS))
    r = rng.random()
    if r < 0.4:
        return f'{word} {int(rng.integers(1, 99))}'
    if r < 0.8:
        letters = ''.join(chr(int(c)) for c in rng.integers(65, 91, int(rng.integers(2, 5))))
        return f'{letters} {word}' if rng.random() < 0.5 else f'{word} {letters}'
    return word


def _put_text_fit(img, text: str, x0: int, y0: int, x1: int, y1: int, colour, font: int,
                  thickness: int = 1) -> None:
    """Draw ``text`` scaled to fit the box (centred), in place."""
    (tw, th), base = cv2.getTextSize(text, font, 1.0, thickness)
    scale = min((x1 - x0) * 0.9 / max(tw, 1), (y1 - y0) * 0.7 / max(th + base, 1))
    if scale <= 0.05:
        return
    (tw, th), base = cv2.getTextSize(text, font, scale, thickness)
    org = (int((x0 + x1 - tw) / 2), int((y0 + y1 + th) / 2))
    cv2.putText(img, text, org, font, scale, colour, thickness, cv2.LINE_AA)


def _shop_front(img, st: _Style, rng: np.random.Generator, x0: int, x1: int, y_top: int,
                y_bot: int, ppm: float) -> None:
    """A shop unit: sign band with text, display window with goods, door, awning."""
    sign_h = _px(rng.uniform(0.7, 1.1), ppm)
    sign_top = y_top + _px(0.3, ppm)
    sc = _hsv_bgr(rng.uniform(0, 1), rng.uniform(0.5, 1.0), rng.uniform(0.3, 0.95))
    tc = (255, 255, 255) if sum(sc) < 400 else (20, 20, 20)
    m = _px(0.2, ppm)
    _rect(img, x0 + m, sign_top, x1 - m, sign_top + sign_h, sc)
    _rect(img, x0 + m, sign_top, x1 - m, sign_top + sign_h, _shade(sc, 0.5), 1)
    thick = 2 if sign_h > 16 and rng.random() < 0.5 else 1
    _put_text_fit(img, _sign_text(rng), x0 + 2 * m, sign_top, x1 - 2 * m, sign_top + sign_h,
                  tc, int(rng.choice(_FONTS)), thick)
    win_top = sign_top + sign_h + _px(0.3, ppm)
    door_w = _px(rng.uniform(1.0, 1.4), ppm)
    door_left = rng.random() < 0.5
    dx0 = x0 + 2 * m if door_left else x1 - 2 * m - door_w
    # Display window: glass and goods (the unit's own random shapes).
    gx0, gx1 = (dx0 + door_w + m, x1 - 2 * m) if door_left else (x0 + 2 * m, dx0 - m)
    gy1 = y_bot - _px(0.45, ppm)
    if gx1 - gx0 > 8 and gy1 - win_top > 8:
        _rect(img, gx0, win_top, gx1, gy1, _shade(st.glass, 0.8))
        for _ in range(int(rng.integers(4, 14))):
            colour = tuple(int(v) for v in rng.integers(30, 256, 3))
            cx = int(rng.integers(gx0 + 2, gx1 - 2))
            cy = int(rng.integers(win_top + 2, gy1 - 2))
            r = int(rng.integers(2, max(3, _px(0.35, ppm))))
            if rng.random() < 0.5:
                cv2.circle(img, (cx, cy), r, colour, -1)
            else:
                _rect(img, cx - r, cy - r, cx + r, cy + int(r * rng.uniform(0.5, 2)), colour)
        if rng.random() < 0.5:
            _put_text_fit(img, str(rng.choice(['SALE', 'OPEN', '-50%', 'NEU', 'WLAN',
                                               'AKTION'])),
                          gx0, win_top, gx0 + (gx1 - gx0) // 2, win_top + _px(0.6, ppm),
                          (40, 40, 220), cv2.FONT_HERSHEY_SIMPLEX, 1)
        _rect(img, gx0, win_top, gx1, gy1, st.frame, max(1, _px(0.08, ppm)))
    _rect(img, dx0, win_top, dx0 + door_w, y_bot, _shade(st.glass, 0.6))
    _rect(img, dx0, win_top, dx0 + door_w, y_bot, st.frame, max(1, _px(0.08, ppm)))
    hy = (win_top + y_bot) // 2
    cv2.line(img, (dx0 + door_w - 4, hy - 4), (dx0 + door_w - 4, hy + 4), (200, 200, 200), 2)
    if rng.random() < 0.35:      # striped awning just below the sign
        ay0, ay1 = sign_top + sign_h, sign_top + sign_h + _px(0.5, ppm)
        ac = _hsv_bgr(rng.uniform(0, 1), 0.8, 0.7)
        stripe = max(2, _px(0.25, ppm))
        for k, x in enumerate(range(x0 + m, x1 - m, stripe)):
            _rect(img, x, ay0, min(x + stripe, x1 - m), ay1,
                  ac if k % 2 == 0 else (235, 235, 235))


def _residential_ground(img, st: _Style, rng: np.random.Generator, x0: int, x1: int,
                        y_top: int, y_bot: int, ppm: float) -> None:
    """Entrance door with house number and barred ground-floor windows."""
    door_w = _px(rng.uniform(1.3, 1.8), ppm)
    dx = int(rng.integers(x0, max(x0 + 1, x1 - door_w)))
    dy = y_bot - _px(2.6, ppm)
    wood = _hsv_bgr(rng.uniform(0.02, 0.1), rng.uniform(0.4, 0.8), rng.uniform(0.2, 0.5))
    _rect(img, dx - 3, dy - 3, dx + door_w + 3, y_bot, st.trim)
    _rect(img, dx, dy, dx + door_w, y_bot, wood)
    for k in range(2):
        for j in range(2):
            px0 = dx + 3 + k * (door_w - 6) // 2
            py0 = dy + 3 + j * (y_bot - dy - 6) // 2
            _rect(img, px0 + 2, py0 + 2, px0 + (door_w - 6) // 2 - 2,
                  py0 + (y_bot - dy - 6) // 2 - 2, _shade(wood, 1.3), 1)
    plate = (150, 60, 20)
    pw, ph = _px(0.45, ppm), _px(0.3, ppm)
    _rect(img, dx + door_w + 6, dy, dx + door_w + 6 + pw, dy + ph, plate)
    _put_text_fit(img, str(int(rng.integers(1, 200))), dx + door_w + 6, dy,
                  dx + door_w + 6 + pw, dy + ph, (255, 255, 255), cv2.FONT_HERSHEY_SIMPLEX)
    ww, wh = _px(st.win_w, ppm), _px(1.4, ppm)
    wy = y_bot - _px(2.4, ppm)
    x = x0 + _px(0.5, ppm)
    while x + ww < x1:
        if not (x + ww > dx - 6 and x < dx + door_w + 6 + pw):
            _window(img, st, rng, x, wy, ww, wh, ppm, lit_p=0.05)
            for bx in range(x + 3, x + ww, max(3, _px(0.15, ppm))):   # bars
                cv2.line(img, (bx, wy), (bx, wy + wh), (40, 40, 40), 1)
        x += _px(st.bay_w, ppm)


def _posters(img, rng: np.random.Generator, w: int, y_bot: int, ppm: float) -> None:
    """Posters and graffiti at street level (unique clutter)."""
    for _ in range(int(rng.integers(0, 3))):
        pw, ph = _px(rng.uniform(0.6, 1.2), ppm), _px(rng.uniform(0.8, 1.6), ppm)
        x = int(rng.integers(0, max(1, w - pw)))
        y = y_bot - ph - _px(rng.uniform(0.5, 1.0), ppm)
        bg = tuple(int(v) for v in rng.integers(0, 256, 3))
        _rect(img, x, y, x + pw, y + ph, bg)
        fg = tuple(255 - v for v in bg)
        _rect(img, x + 2, y + ph // 2, x + pw - 2, y + ph - 3,
              tuple(int(v) for v in rng.integers(0, 256, 3)))
        _put_text_fit(img, _sign_text(rng), x, y, x + pw, y + ph // 2, fg,
                      int(rng.choice(_FONTS)))
    if rng.random() < 0.3:
        colour = tuple(int(v) for v in rng.integers(0, 256, 3))
        pts = np.stack([rng.integers(0, w, 6), y_bot - rng.integers(4, _px(2.0, ppm), 6)], 1)
        cv2.polylines(img, [pts.astype(np.int32)], False, colour, max(2, _px(0.1, ppm)),
                      cv2.LINE_AA)


def _make_texture(style_id: int, w: int, h: int, ppm: float) -> np.ndarray:
    st = _style(style_id)
    # Elements are anchored at the left edge and seeded by (style, floor, bay): facades of
    # one style but different widths share their left part exactly (repetitions).
    rng = np.random.default_rng([int(style_id), _STYLE_SALT, 1, w, h])
    img = _wall_material(st, rng, h, w, ppm)
    ground = min(_px(st.ground_h, ppm), h)
    corn = _px(st.cornice_h, ppm)
    # Cornice at the top, a base band at the bottom.
    _rect(img, 0, 0, w, corn, st.trim)
    _rect(img, 0, corn, w, corn + max(2, corn // 4), _shade(st.trim, 0.7))
    if st.pilaster:
        pw = _px(0.45, ppm)
        _rect(img, 0, 0, pw, h, _shade(st.wall, 0.85))
        _rect(img, w - pw, 0, w, h, _shade(st.wall, 0.85))
    floor = _px(st.floor_h, ppm)
    bay = _px(st.bay_w, ppm)
    ww, wh = _px(st.win_w, ppm), _px(st.win_h, ppm)
    margin = _px(st.margin, ppm)
    n_bays = max(0, (w - margin - _px(0.6, ppm)) // max(bay, 1))
    y_floor = h - ground          # floor line of the first upper floor (row, grows down)
    f = 1
    while True:
        y_top = y_floor - floor
        if y_top < corn + _px(0.3, ppm):
            break
        if st.material == 'glass':
            # Curtain wall: one panel per bay, spandrel band between floors.
            _rect(img, 0, y_top, w, y_floor, _shade(st.wall, 0.9))
            for b in range(max(1, w // max(bay // 2, 1))):
                wrng = np.random.default_rng([int(style_id), _STYLE_SALT, 2, f, b])
                x0 = b * (bay // 2)
                _rect(img, x0 + 1, y_top + _px(0.5, ppm), x0 + bay // 2 - 1, y_floor - 1,
                      _shade(st.glass, wrng.uniform(0.7, 1.5)))
                if wrng.random() < 0.3:
                    yb = y_top + _px(wrng.uniform(0.6, 2.5), ppm)
                    _rect(img, x0 + 1, y_top + _px(0.5, ppm), x0 + bay // 2 - 1, yb,
                          tuple(int(v) for v in wrng.integers(150, 240, 3)))
                _rect(img, x0, y_top, x0 + bay // 2, y_floor, st.frame, 1)
        else:
            if st.string_course:
                _rect(img, 0, y_floor - max(2, _px(0.18, ppm)), w, y_floor, st.trim)
            balcony = np.random.default_rng([int(style_id), _STYLE_SALT, 3, f]).random()
            for b in range(n_bays):
                wrng = np.random.default_rng([int(style_id), _STYLE_SALT, 2, f, b])
                if wrng.random() < 0.04:
                    continue          # a bricked-up or missing window: irregularity
                x0 = margin + b * bay + (bay - ww) // 2
                y0 = y_floor - _px(st.sill_h, ppm) - wh
                _window(img, st, wrng, x0, y0, ww, wh, ppm)
                if balcony < st.balcony_p:
                    _balcony(img, st, x0 - 3, x0 + ww + 3, y_floor - 1, ppm)
        y_floor = y_top
        f += 1
    # Ground floor: shop units or a residential entrance.
    g_top = h - ground
    _rect(img, 0, g_top - max(2, _px(0.25, ppm)), w, g_top, _shade(st.trim, 0.85))
    if st.shop:
        x = 0
        k = 0
        while x < w - _px(3.0, ppm):
            urng = np.random.default_rng([int(style_id), _STYLE_SALT, 4, k])
            uw = _px(urng.uniform(5.0, 9.0), ppm)
            x1 = min(w, x + uw)
            if x1 - x > _px(3.0, ppm):
                _shop_front(img, st, urng, x, x1, g_top, h, ppm)
            x, k = x1, k + 1
    else:
        _residential_ground(img, st, np.random.default_rng([int(style_id), _STYLE_SALT, 5]),
                            0, w, g_top, h, ppm)
    _posters(img, np.random.default_rng([int(style_id), _STYLE_SALT, 6, w]), w, h, ppm)
    _rect(img, 0, h - max(2, _px(0.3, ppm)), w, h, _shade(st.wall, 0.6))   # plinth
    return img


@lru_cache(maxsize=128)
def _cached_texture(style_id: int, w: int, h: int, ppm: float) -> np.ndarray:
    tex = _make_texture(style_id, w, h, ppm)
    tex.setflags(write=False)
    return tex


def facade_texture(style_id: int, width_m: float, height_m: float,
                   px_per_m: float = PX_PER_M) -> np.ndarray:
    """Procedural texture of a facade (deterministic, cached per style and size).

    Row 0 is the top of the wall, column 0 its left end as seen from the street. Facades
    with the same ``style_id`` and size get the identical (shared, read-only) array; with
    the same style and another size, the elements anchored at the left edge coincide.

    Args:
        style_id: Facade style (``City.facades.style_id``).
        width_m: Wall width [m].
        height_m: Wall height [m].
        px_per_m: Texture resolution [px/m].

    Returns:
        (round(height_m * px_per_m), round(width_m * px_per_m), 3) uint8 BGR, read-only.
    """
    w = max(8, int(round(width_m * px_per_m)))
    h = max(8, int(round(height_m * px_per_m)))
    return _cached_texture(int(style_id), w, h, float(px_per_m))


# ============================================================================ ground
@lru_cache(maxsize=4)
def _ground_tile(pitch_m: float, street_w_m: float, ppm: float, seed: int = 7) -> np.ndarray:
    """One period of the street grid, intersection at the centre: (n, n, 3) uint8 BGR.

    Coordinates: column ~ east, row ~ north, both ``(px + 0.5) / ppm`` metres from the
    tile's south-west corner; street centre lines at ``pitch_m / 2``.
    """
    n = int(round(pitch_m * ppm / 16.0)) * 16       # divisible by 16 for the mip levels
    ppm = n / pitch_m
    rng = np.random.default_rng(seed)
    c = (np.arange(n) + 0.5) / ppm - 0.5 * pitch_m          # metres from the centre lines
    dx = np.abs(c)[None, :]                                  # to the N-S street (x = east)
    dy = np.abs(c)[:, None]                                  # to the E-W street
    half = 0.5 * street_w_m
    carriage = half - 6.0                                    # 6 m pavements
    img = np.empty((n, n, 3), np.float32)
    img[:] = (118, 124, 128)                                 # block interior: plaza stone
    pave = (dx < half) | (dy < half)
    img[pave] = (150, 152, 155)
    road_ns, road_ew = dx < carriage, dy < carriage
    road = road_ns | road_ew
    img[road] = (78, 80, 82)
    img += (_noise_field(rng, n, n, int(4 * ppm)) * 8.0)[..., None]
    img += rng.normal(0.0, 3.0, (n, n, 1)).astype(np.float32)
    # Curbs: a light line along the carriageway edges.
    curb_w = 0.25
    curb = (((np.abs(dx - carriage) < curb_w) & (dy > carriage))
            | ((np.abs(dy - carriage) < curb_w) & (dx > carriage)))
    img[curb] = (185, 188, 190)
    # Lane lines outside the intersection box: dashed centre line (3 m on, 6 m off), solid
    # edge lines 1 m inside the curb.
    xs = c[None, :] * np.ones((n, 1))
    ys = c[:, None] * np.ones((1, n))
    box = (dx < half) & (dy < half)
    white = (235, 235, 235)
    centre_ns = (dx < 0.08) & ((ys % 9.0) < 3.0) & ~box
    centre_ew = (dy < 0.08) & ((xs % 9.0) < 3.0) & ~box
    edge_ns = (np.abs(dx - (carriage - 1.0)) < 0.08) & (dy > half)
    edge_ew = (np.abs(dy - (carriage - 1.0)) < 0.08) & (dx > half)
    img[centre_ns | centre_ew | edge_ns | edge_ew] = white
    # Zebra crossings just outside the box, stripes 0.5 m wide every 1 m across the road.
    zebra_ns = (dx < carriage) & (dy > half + 0.5) & (dy < half + 4.0) & ((xs % 1.0) < 0.5)
    zebra_ew = (dy < carriage) & (dx > half + 0.5) & (dx < half + 4.0) & ((ys % 1.0) < 0.5)
    img[zebra_ns | zebra_ew] = (215, 215, 215)
    stop_ns = (dx < carriage) & (np.abs(dy - (half + 5.0)) < 0.25)
    stop_ew = (dy < carriage) & (np.abs(dx - (half + 5.0)) < 0.25)
    img[stop_ns | stop_ew] = white
    out = np.clip(img, 0, 255).astype(np.uint8)
    # A few manhole covers on the road.
    for _ in range(6):
        p = rng.integers(0, n, 2)
        if road[p[1], p[0]] and not box[p[1], p[0]]:
            cv2.circle(out, (int(p[0]), int(p[1])), int(0.35 * ppm), (55, 58, 60), -1)
            cv2.circle(out, (int(p[0]), int(p[1])), int(0.35 * ppm), (100, 100, 100), 1)
    out = cv2.GaussianBlur(out, (3, 3), 0)
    out.setflags(write=False)
    return out


def _pyramid(img: np.ndarray, min_side: int = 4) -> list[np.ndarray]:
    """Mip levels: level k is ``img`` reduced by 2**k (``cv2.pyrDown``)."""
    levels = [img]
    while min(levels[-1].shape[:2]) >= 2 * min_side:
        levels.append(cv2.pyrDown(levels[-1]))
    return levels


# ============================================================================ renderer
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
        tile = cv2.LUT(_ground_tile(float(city.pitch_m), float(city.street_width_m),
                                    GROUND_PX_PER_M), self._lut)
        self._ground_ppm = tile.shape[0] / float(city.pitch_m)
        self._ground = _pyramid(cv2.cvtColor(np.tile(tile, (3, 3, 1)), cv2.COLOR_BGR2BGRA),
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
        levels = _pyramid(cv2.cvtColor(lit, cv2.COLOR_BGR2BGRA))
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
