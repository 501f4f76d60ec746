"""Procedural textures of the emulated city: facades and the road tile.

A facade texture (:func:`facade_texture`) is a wall material (plaster, brick, stone or
glass, with weathering and grain) carrying window grids with frames, mullions, blinds and
curtains, balconies, shop fronts with signs and text, doors and posters. It depends only
on the facade's ``style_id`` and its size: facades that share a style (about a third of
them, see :func:`..city.make_city`) look the same, the deliberate repetition that makes
some images ambiguous. The road tile (:func:`ground_tile`: asphalt, curbs, pavements,
dashed lane lines, zebra crossings) is one period of the street grid. The renderer
(:mod:`.render`) draws both from mip levels (:func:`mip_pyramid`).
"""
from __future__ import annotations

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
def ground_tile(pitch_m: float, street_w_m: float, ppm: float, seed: int = 7) -> np.ndarray:
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


def mip_pyramid(img: np.ndarray, min_side: int = 4) -> list[np.ndarray]:
    """Mip levels: level k is ``img`` reduced by 2**k (``cv2.pyrDown``)."""
    levels = [img]
    while min(levels[-1].shape[:2]) >= 2 * min_side:
        levels.append(cv2.pyrDown(levels[-1]))
    return levels
