"""Synthetic street images for the vision tests and benchmarks (no rendering of a city).

:func:`synthetic_scene` draws a seeded street-facade image in a few milliseconds;
:func:`perturb_view` turns it into another view of the same place. They exercise the ORB
features and the map database (retrieval, ambiguity, speed) without the emulated city's
renderer (:mod:`..datasets.emulated.render`).
"""
from __future__ import annotations

import cv2
import numpy as np


def synthetic_scene(index: int, seed: int = 0, shape: tuple[int, int] = (480, 640),
                    n_styles: int = 40) -> np.ndarray:
    """A seeded synthetic street-facade image (BGR uint8) for tests and benchmarks.

    Buildings draw their window grid from a small shared set of styles, so different
    images repeat the same facade patterns (ambiguous, as real streets); shop signs with
    image-specific text, poles and clutter make each image identifiable.
    """
    h, w = shape
    rng = np.random.default_rng([seed, index])
    img = np.empty((h, w, 3), np.uint8)
    sky = np.linspace(230, 150, h // 4)[:, None, None]
    img[:h // 4] = (sky * np.array([1.0, 0.9, 0.75])).astype(np.uint8)
    img[h // 4:] = (90, 90, 95)
    x = int(rng.integers(-80, 0))
    while x < w:
        style = int(rng.integers(n_styles))
        srng = np.random.default_rng([seed, 1_000_003, style])
        bw = int(srng.integers(140, 320))
        top = int(srng.integers(h // 12, h // 3))
        wall = tuple(int(c) for c in srng.integers(60, 220, 3))
        cv2.rectangle(img, (x, top), (x + bw, h - h // 8), wall, -1)
        ww, wh = int(srng.integers(14, 30)), int(srng.integers(18, 40))
        gx, gy = ww + int(srng.integers(8, 24)), wh + int(srng.integers(12, 30))
        glass = tuple(int(c) for c in srng.integers(0, 120, 3))
        frame = tuple(int(c) for c in srng.integers(150, 256, 3))
        for yy in range(top + 12, h - h // 8 - wh - 40, gy):
            for xx in range(x + 10, x + bw - ww - 6, gx):
                cv2.rectangle(img, (xx, yy), (xx + ww, yy + wh), glass, -1)
                cv2.rectangle(img, (xx, yy), (xx + ww, yy + wh), frame, 2)
        # Unique per image: shop sign with text, door, clutter.
        sy = h - h // 8 - 40 - int(rng.integers(0, 30))
        sx = x + int(rng.integers(0, max(1, bw - 120)))
        cv2.rectangle(img, (sx, sy), (sx + 120, sy + 30),
                      tuple(int(c) for c in rng.integers(0, 256, 3)), -1)
        text = ''.join(rng.choice(list('ABCDEFGHKMNPRSTUVWXYZ0123456789'), 5))
        cv2.putText(img, text, (sx + 6, sy + 23), cv2.FONT_HERSHEY_SIMPLEX, 0.7,
                    tuple(int(c) for c in rng.integers(0, 256, 3)), 2, cv2.LINE_AA)
        x += bw + int(rng.integers(0, 20))
    for _ in range(int(rng.integers(4, 10))):
        px = int(rng.integers(0, w))
        cv2.line(img, (px, int(rng.integers(h // 3, h // 2))), (px, h),
                 tuple(int(c) for c in rng.integers(20, 90, 3)), int(rng.integers(3, 9)))
    for _ in range(int(rng.integers(10, 25))):
        c = (int(rng.integers(0, w)), int(rng.integers(h // 2, h)))
        cv2.circle(img, c, int(rng.integers(3, 15)),
                   tuple(int(v) for v in rng.integers(0, 256, 3)), -1)
    fonts = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX,
             cv2.FONT_HERSHEY_TRIPLEX, cv2.FONT_HERSHEY_SCRIPT_SIMPLEX)
    for _ in range(int(rng.integers(4, 9))):       # posters and graffiti
        org = (int(rng.integers(0, w - 60)), int(rng.integers(h // 4, h - 10)))
        text = ''.join(rng.choice(list('abcdefghijkmnopqrstuvwxyz0123456789'), 4))
        cv2.putText(img, text, org, fonts[int(rng.integers(len(fonts)))],
                    float(rng.uniform(0.5, 1.2)),
                    tuple(int(c) for c in rng.integers(0, 256, 3)), int(rng.integers(1, 3)),
                    cv2.LINE_AA)
    for _ in range(int(rng.integers(2, 5))):       # parked cars: polygon body + wheels
        cx, cy = int(rng.integers(0, w)), int(rng.integers(h - h // 6, h - 10))
        cw, ch = int(rng.integers(60, 130)), int(rng.integers(25, 45))
        body = np.array([[cx, cy], [cx + cw, cy], [cx + cw - 10, cy - ch],
                         [cx + int(cw * 0.3), cy - ch - int(rng.integers(0, 15))],
                         [cx + 8, cy - ch // 2]], np.int32)
        cv2.fillPoly(img, [body], tuple(int(c) for c in rng.integers(0, 256, 3)))
        for wx in (cx + cw // 5, cx + 4 * cw // 5):
            cv2.circle(img, (wx, cy), ch // 3, (20, 20, 20), -1)
    noise = rng.normal(0.0, 4.0, img.shape)
    return np.clip(img + noise, 0, 255).astype(np.uint8)


def perturb_view(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Another view of a scene: shift, scale, roll, brightness/contrast, noise, slight blur."""
    h, w = image.shape[:2]
    m = cv2.getRotationMatrix2D((w / 2, h / 2), rng.uniform(-3, 3), rng.uniform(0.9, 1.1))
    m[:, 2] += rng.uniform(-25, 25, 2)
    out = cv2.warpAffine(image, m, (w, h), borderMode=cv2.BORDER_REFLECT)
    out = cv2.convertScaleAbs(out, alpha=rng.uniform(0.7, 1.3), beta=rng.uniform(-30, 30))
    if rng.random() < 0.5:
        out = cv2.GaussianBlur(out, (3, 3), 0)
    return np.clip(out + rng.normal(0, 3, out.shape), 0, 255).astype(np.uint8)
