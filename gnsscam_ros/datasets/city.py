"""A Manhattan-style city model for the emulated urban drive.

The city is a regular grid of perimeter blocks (as in the centres of Frankfurt or Berlin)
separated by streets of constant width, expressed in the local ENU ``map`` frame [m] with the
ground at ``u = 0``. Every block is cut into a few buildings of different heights (12-45 m,
so the streets are canyons that mask much of the sky); a few blocks are left empty (squares,
parks) where the sky opens.

Two products matter to the rest of the package:

* **Buildings** (``City.blocks``): axis-aligned boxes used by :func:`los_blocked` to decide
  which satellite lines of sight are masked (NLOS) at every GNSS epoch.
* **Facades** (``City.facades``): the street-facing vertical wall rectangles, each with a
  ``style_id`` that seeds its texture when the camera images are rendered. Styles repeat on
  purpose (about a third of the facades share a handful of styles) so that, as in a real
  city, one image can match several places.

Street layout: street centre lines run north-south at ``e = street_e_m[i]`` and east-west at
``n = street_n_m[j]``; ``pitch_m = block_size_m + street_width_m`` apart. The intersection
``(street_e_m[i], street_n_m[j])`` is the grid node ``(i, j)``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Facades:
    """Street-facing vertical wall rectangles (all of them ``F`` in a city).

    A facade is the rectangle above the ground segment ``p0 -> p1`` from height 0 to
    ``height_m``. ``p0 -> p1`` runs left to right for a viewer standing in the street and
    looking at the wall, so ``normal`` (outward, towards the street) is ``p1 - p0`` turned
    clockwise by 90 degrees. A texture of width ``w`` and height ``h`` pixels maps to the wall
    with its column axis along ``p0 -> p1`` and its row axis from the top edge down, so the
    image corners (0, 0), (w, 0), (w, h), (0, h) go to :meth:`corners_enu` rows 3, 2, 1, 0.

    Attributes:
        p0_m: (F, 2) left ground end point (east, north) [m].
        p1_m: (F, 2) right ground end point (east, north) [m].
        height_m: (F,) wall height above ground [m].
        normal: (F, 2) outward horizontal unit normal (east, north).
        style_id: (F,) integer texture seed; equal ids render identically (repetitions).
        building: (F,) row of the building in ``City.blocks`` the facade belongs to.
    """

    p0_m: np.ndarray
    p1_m: np.ndarray
    height_m: np.ndarray
    normal: np.ndarray
    style_id: np.ndarray
    building: np.ndarray

    def __len__(self) -> int:
        return int(self.height_m.shape[0])

    @property
    def width_m(self) -> np.ndarray:
        """(F,) ground length of each facade [m]."""
        return np.linalg.norm(self.p1_m - self.p0_m, axis=1)

    @property
    def centre_enu_m(self) -> np.ndarray:
        """(F, 3) centre point of each facade rectangle in ENU [m]."""
        mid = 0.5 * (self.p0_m + self.p1_m)
        return np.column_stack([mid, 0.5 * self.height_m])

    def corners_enu(self, index: int | np.ndarray) -> np.ndarray:
        """ENU corners of one or several facades.

        Args:
            index: A facade index, or an integer/boolean index array.

        Returns:
            (4, 3) or (m, 4, 3) corners [m], in the order bottom-left, bottom-right,
            top-right, top-left as seen from the street.
        """
        p0, p1, h = self.p0_m[index], self.p1_m[index], self.height_m[index]
        p0, p1, h = np.atleast_2d(p0), np.atleast_2d(p1), np.atleast_1d(h)
        zero = np.zeros_like(h)
        out = np.stack([np.column_stack([p0, zero]), np.column_stack([p1, zero]),
                        np.column_stack([p1, h]), np.column_stack([p0, h])], axis=1)
        return out[0] if np.ndim(index) == 0 else out


@dataclass(frozen=True)
class City:
    """A grid city in the local ENU frame.

    Attributes:
        blocks: (B, 5) buildings as ``[e_min, n_min, e_max, n_max, height_m]`` [m]; boxes
            standing on the ground (``u`` from 0 to ``height_m``). The name follows the
            building-block sense; each row is one building, several make a city block.
        street_width_m: Distance between the facades on both sides of a street [m].
        block_size_m: Side of a (square) city block between streets [m].
        street_e_m: (nx+1,) east coordinates of the north-south street centre lines [m].
        street_n_m: (ny+1,) north coordinates of the east-west street centre lines [m].
        facades: The street-facing walls.
    """

    blocks: np.ndarray
    street_width_m: float
    block_size_m: float
    street_e_m: np.ndarray
    street_n_m: np.ndarray
    facades: Facades

    @property
    def pitch_m(self) -> float:
        """Distance between neighbouring parallel street centre lines [m]."""
        return self.block_size_m + self.street_width_m

    @property
    def max_height_m(self) -> float:
        """Tallest building [m] (0 for an empty city)."""
        return float(self.blocks[:, 4].max()) if len(self.blocks) else 0.0

    def facades_near(self, point_enu: np.ndarray, radius_m: float = 80.0,
                     facing: bool = True) -> np.ndarray:
        """Facades close to a point, e.g. candidates for a camera image.

        Occlusion between buildings is not handled; the renderer should draw the returned
        facades far to near (painter's algorithm) or use a depth buffer.

        Args:
            point_enu: (2,) or (3,) viewer position [m] (only east/north are used).
            radius_m: Maximum horizontal distance from the point to the facade segment [m].
            facing: Keep only facades whose outward side faces the point.

        Returns:
            Indices into ``facades``, sorted by increasing distance.
        """
        p = np.asarray(point_enu, dtype=float)[:2]
        f = self.facades
        seg = f.p1_m - f.p0_m
        seg_len2 = np.maximum(np.einsum('ij,ij->i', seg, seg), 1e-12)
        t = np.clip(np.einsum('ij,ij->i', p - f.p0_m, seg) / seg_len2, 0.0, 1.0)
        dist = np.linalg.norm(f.p0_m + t[:, None] * seg - p, axis=1)
        keep = dist <= radius_m
        if facing:
            keep &= np.einsum('ij,ij->i', p - f.p0_m, f.normal) > 0.0
        idx = np.flatnonzero(keep)
        return idx[np.argsort(dist[idx], kind='stable')]


_HEIGHT_BETA = (1.3, 3.0)   # building height = min + (max - min) * Beta(a, b)


def _cuts(rng: np.random.Generator, length: float, n_parts: int, min_part: float) -> np.ndarray:
    """Random cut positions splitting ``[0, length]`` into parts of at least ``min_part``."""
    spare = length - n_parts * min_part
    w = rng.dirichlet(np.full(n_parts, 2.0)) * spare + min_part
    return np.concatenate([[0.0], np.cumsum(w)])


def make_city(rng: np.random.Generator, n_blocks_e: int = 12, n_blocks_n: int = 12,
              block_size_m: float = 80.0, street_width_m: float = 30.0,
              height_range_m: tuple[float, float] = (12.0, 45.0),
              empty_block_prob: float = 0.08, shared_style_frac: float = 0.3,
              n_shared_styles: int = 6) -> City:
    """Generate a seeded grid city centred on the ENU origin.

    Each block is cut into ``k_e x k_n`` cells (2-3 each way, cut positions random, cells at
    least 14 m); the cells on the block perimeter are buildings, the centre cell of a 3x3
    cut is a courtyard. Building heights follow ``12 + 33 * Beta(1.3, 3.0)`` m with the
    default range (mean 22 m, mostly 4-8 storeys, a few towers up to 45 m); with 30 m wide
    streets about a third of the tracked satellites end up masked (NLOS), as in a European
    city centre. The street-facing walls of each building become facades. A fraction
    ``shared_style_frac`` of the facades draw their ``style_id`` from ``n_shared_styles``
    shared styles (ids ``0 .. n_shared_styles-1``); the rest get unique ids.

    Args:
        rng: Random generator (the only source of randomness).
        n_blocks_e: Number of blocks along east.
        n_blocks_n: Number of blocks along north.
        block_size_m: Side of a square block [m].
        street_width_m: Facade-to-facade street width [m].
        height_range_m: (min, max) building height [m].
        empty_block_prob: Probability that a block is an open square without buildings.
        shared_style_frac: Fraction of facades with a repeated (shared) style.
        n_shared_styles: Number of distinct shared styles.

    Returns:
        The city. Node (0, 0) of the street grid is at the south-west corner, the ENU origin
        is the intersection nearest to the grid centre.
    """
    pitch = block_size_m + street_width_m
    street_e = (np.arange(n_blocks_e + 1) - n_blocks_e // 2) * pitch
    street_n = (np.arange(n_blocks_n + 1) - n_blocks_n // 2) * pitch
    h_lo, h_hi = height_range_m
    half_w = 0.5 * street_width_m

    boxes, fac = [], []   # fac rows: e0, n0, e1, n1, height, nx, ny, building
    for bi in range(n_blocks_e):
        for bj in range(n_blocks_n):
            if rng.random() < empty_block_prob:
                continue
            e_lo, n_lo = street_e[bi] + half_w, street_n[bj] + half_w
            k_e, k_n = rng.integers(2, 4, size=2)
            ce = e_lo + _cuts(rng, block_size_m, k_e, 14.0)
            cn = n_lo + _cuts(rng, block_size_m, k_n, 14.0)
            for a in range(k_e):
                for b in range(k_n):
                    west, east = a == 0, a == k_e - 1
                    south, north = b == 0, b == k_n - 1
                    if not (west or east or south or north):
                        continue   # courtyard
                    h = h_lo + (h_hi - h_lo) * rng.beta(*_HEIGHT_BETA)
                    e0, e1, n0, n1 = ce[a], ce[a + 1], cn[b], cn[b + 1]
                    k = len(boxes)
                    boxes.append([e0, n0, e1, n1, h])
                    # Left-to-right as seen from the street, outward normal.
                    if south:
                        fac.append([e0, n0, e1, n0, h, 0.0, -1.0, k])
                    if north:
                        fac.append([e1, n1, e0, n1, h, 0.0, 1.0, k])
                    if west:
                        fac.append([e0, n1, e0, n0, h, -1.0, 0.0, k])
                    if east:
                        fac.append([e1, n0, e1, n1, h, 1.0, 0.0, k])
    blocks = np.asarray(boxes, dtype=float).reshape(-1, 5)
    f = np.asarray(fac, dtype=float).reshape(-1, 8)
    n_f = f.shape[0]
    shared = rng.random(n_f) < shared_style_frac
    style = np.where(shared, rng.integers(0, n_shared_styles, size=n_f),
                     n_shared_styles + np.arange(n_f))
    facades = Facades(p0_m=f[:, 0:2].copy(), p1_m=f[:, 2:4].copy(), height_m=f[:, 4].copy(),
                      normal=f[:, 5:7].copy(), style_id=style.astype(np.int64),
                      building=f[:, 7].astype(np.int64))
    for arr in (blocks, street_e, street_n, *facades.__dict__.values()):
        arr.setflags(write=False)   # the dataclass is frozen; keep its arrays frozen too
    return City(blocks=blocks, street_width_m=float(street_width_m),
                block_size_m=float(block_size_m), street_e_m=street_e, street_n_m=street_n,
                facades=facades)


def los_blocked(city: City, rx_enu: np.ndarray, dirs_enu: np.ndarray) -> np.ndarray:
    """Which lines of sight from a receiver are blocked by a building (slab method).

    A ray ``rx + t * d`` (``t > 0``) is blocked when it enters any building box. The test is
    vectorised over rays and buildings; buildings too far away to reach the lowest ray above
    the horizon are culled first, which keeps an epoch well under a millisecond.

    Args:
        city: The city.
        rx_enu: (3,) receiver (antenna) position in ENU [m].
        dirs_enu: (k, 3) directions towards the satellites in ENU (need not be unit).

    Returns:
        (k,) True where the line of sight hits a building. Rays at or below the horizon
        count as blocked (the ground or the buildings around mask them).
    """
    rx = np.asarray(rx_enu, dtype=float).reshape(3)
    d = np.atleast_2d(np.asarray(dirs_enu, dtype=float))
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    out = d[:, 2] <= 0.0
    up = ~out
    if not up.any() or len(city.blocks) == 0:
        return out
    b = city.blocks
    # Cull: a box of height h can only block a ray of elevation el if it lies within
    # h / tan(el) horizontally (for boxes higher than the antenna).
    horiz = np.linalg.norm(d[up, :2], axis=1)
    reach = (city.max_height_m - rx[2]) * np.max(horiz / d[up, 2])
    dx = np.maximum(np.maximum(b[:, 0] - rx[0], rx[0] - b[:, 2]), 0.0)
    dy = np.maximum(np.maximum(b[:, 1] - rx[1], rx[1] - b[:, 3]), 0.0)
    near = (np.hypot(dx, dy) <= reach) & (b[:, 4] > rx[2])
    if not near.any():
        return out
    b = b[near]
    lo = np.stack([b[:, 0], b[:, 1], np.zeros(len(b))], axis=1)   # (B, 3)
    hi = np.stack([b[:, 2], b[:, 3], b[:, 4]], axis=1)
    du = d[up]                                                     # (k, 3)
    with np.errstate(divide='ignore', invalid='ignore'):
        inv = 1.0 / du
        t1 = (lo[None, :, :] - rx) * inv[:, None, :]               # (k, B, 3)
        t2 = (hi[None, :, :] - rx) * inv[:, None, :]
    t_lo, t_hi = np.minimum(t1, t2), np.maximum(t1, t2)
    # A zero direction component: the slab is everything or nothing depending on whether
    # the receiver lies between its planes (avoids 0 * inf = NaN).
    par = (du == 0.0)[:, None, :]
    inside = ((rx >= lo) & (rx <= hi))[None, :, :]
    t_lo = np.where(par, np.where(inside, -np.inf, np.inf), t_lo)
    t_hi = np.where(par, np.where(inside, np.inf, -np.inf), t_hi)
    t_enter, t_exit = t_lo.max(axis=2), t_hi.min(axis=2)
    hit = (t_enter <= t_exit) & (t_exit > 0.0)
    out[up] = hit.any(axis=1)
    return out
