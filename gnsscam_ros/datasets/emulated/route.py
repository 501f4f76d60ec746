"""Route of the emulated drive: a lane-centre path through the street grid.

A random walk over the interior intersections of the city (:mod:`..city`) picks the
streets; the path follows the lane centre (driving on the right) as straight lines joined
by circular turn arcs at the intersections, and records where it passes each node and
where the stop line before it is.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..city import City
from .config import EmulationConfig


@dataclass(frozen=True)
class Route:
    """A planar path made of straight lines (``kappa = 0``) and circular arcs.

    Primitive ``i`` starts at arc length ``s0_m[i]`` at point ``p0_m[i]`` with heading
    ``psi0_rad[i]`` (ENU, counter-clockwise from east) and has constant curvature
    ``kappa_pm[i]`` (positive = left turn) over ``len_m[i]``.

    Attributes:
        s0_m: (P,) start arc length [m].
        len_m: (P,) length [m].
        p0_m: (P, 2) start point (east, north) [m].
        psi0_rad: (P,) start heading [rad].
        kappa_pm: (P,) curvature [1/m].
        node_s_m: (N,) arc length where the route passes each grid node it visits [m].
        stop_s_m: (N,) arc length of the stop line before each node [m].
    """

    s0_m: np.ndarray
    len_m: np.ndarray
    p0_m: np.ndarray
    psi0_rad: np.ndarray
    kappa_pm: np.ndarray
    node_s_m: np.ndarray
    stop_s_m: np.ndarray

    @property
    def length_m(self) -> float:
        """Total length [m]."""
        return float(self.s0_m[-1] + self.len_m[-1])

    def evaluate(self, s_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Point, heading and curvature at arc lengths ``s_m``.

        Args:
            s_m: (n,) arc lengths [m], clipped to ``[0, length_m]``.

        Returns:
            ``(en (n, 2) [m], psi (n,) [rad, unwrapped], kappa (n,) [1/m])``.
        """
        s = np.clip(np.asarray(s_m, dtype=float), 0.0, self.length_m)
        i = np.clip(np.searchsorted(self.s0_m, s, side='right') - 1, 0, len(self.s0_m) - 1)
        u = s - self.s0_m[i]
        k, psi0 = self.kappa_pm[i], self.psi0_rad[i]
        psi = psi0 + k * u
        straight = k == 0.0
        k_safe = np.where(straight, 1.0, k)
        de = np.where(straight, u * np.cos(psi0), (np.sin(psi) - np.sin(psi0)) / k_safe)
        dn = np.where(straight, u * np.sin(psi0), -(np.cos(psi) - np.cos(psi0)) / k_safe)
        return self.p0_m[i] + np.column_stack([de, dn]), psi, k


_DIRS = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])   # E, N, W, S; +1 index = left turn


def _walk_nodes(city: City, rng: np.random.Generator, min_len_m: float):
    """Random walk over interior street nodes: no U-turns, revisited streets discouraged.

    Returns:
        (m+1, 2) node grid indices and (m,) direction indices (into ``_DIRS``) of the edges.
    """
    nx, ny = len(city.street_e_m) - 1, len(city.street_n_m) - 1
    # Interior streets only, so that the route always runs in a canyon.
    node = np.array([rng.integers(1, nx), rng.integers(1, ny)])
    d = int(rng.integers(4))
    nodes, dirs, visited = [node.copy()], [], set()
    length = 0.0
    while True:
        options, weights = [], []
        for turn, w in ((0, 0.45), (1, 0.275), (-1, 0.275)):
            dn = (d + turn) % 4
            nxt = node + _DIRS[dn]
            if 1 <= nxt[0] <= nx - 1 and 1 <= nxt[1] <= ny - 1:
                edge = frozenset((tuple(node), tuple(nxt)))
                options.append(dn)
                weights.append(w * (0.1 if edge in visited else 1.0))
        if not options:
            raise RuntimeError('street grid too small for a route')
        weights = np.asarray(weights) / np.sum(weights)
        d = options[int(rng.choice(len(options), p=weights))]
        nxt = node + _DIRS[d]
        visited.add(frozenset((tuple(node), tuple(nxt))))
        nodes.append(nxt.copy())
        dirs.append(d)
        node = nxt
        length += city.pitch_m
        if length >= min_len_m:
            return np.asarray(nodes), np.asarray(dirs)


def _build_route(city: City, nodes: np.ndarray, dirs: np.ndarray, cfg: EmulationConfig,
                 length_m: float) -> Route:
    """Lane-centre path (drive on the right) with fillet arcs at the turns, cut to length."""
    r, off = cfg.turn_radius_m, cfg.lane_offset_m
    stop_back = 0.5 * city.street_width_m + 1.0   # stop line before the crossing street

    def right(k):
        v = _DIRS[k].astype(float)
        return np.array([v[1], -v[0]])

    prims = []    # (p0, psi0, kappa, length)
    node_s, stop_s = [], []
    centre = np.array([city.street_e_m[nodes[0][0]], city.street_n_m[nodes[0][1]]])
    p = centre + off * right(dirs[0])
    s = 0.0
    for i in range(1, len(nodes)):
        d_in = dirs[i - 1]
        centre = np.array([city.street_e_m[nodes[i][0]], city.street_n_m[nodes[i][1]]])
        u_in = _DIRS[d_in].astype(float)
        psi_in = np.arctan2(u_in[1], u_in[0])
        d_out = dirs[i] if i < len(dirs) else d_in
        turn = (d_out - d_in) % 4          # 0 straight, 1 left, 3 right
        if turn == 0:
            # Straight on: the line simply continues; close it at the node for bookkeeping.
            end = centre + off * right(d_in)
            seg = float(np.dot(end - p, u_in))
            prims.append((p, psi_in, 0.0, seg))
            s += seg
            node_s.append(s)
            stop_s.append(s - stop_back)
            p = end
            continue
        corner = centre + off * right(d_in) + off * right(d_out)
        a_start = corner - r * u_in
        seg = float(np.dot(a_start - p, u_in))
        prims.append((p, psi_in, 0.0, seg))
        s += seg
        # Stop line, measured along the incoming lane, never inside the arc.
        along_start = float(np.dot(a_start - centre, u_in))
        stop_s.append(s + min(0.0, -stop_back - along_start))
        kappa = 1.0 / r if turn == 1 else -1.0 / r
        arc = 0.5 * np.pi * r
        prims.append((a_start, psi_in, kappa, arc))
        node_s.append(s + 0.5 * arc)
        s += arc
        p = corner + r * _DIRS[d_out].astype(float)
    s0 = np.concatenate([[0.0], np.cumsum([q[3] for q in prims])[:-1]])
    lens = np.array([q[3] for q in prims])
    keep = s0 < length_m
    lens = np.minimum(lens[keep], length_m - s0[keep])
    node_s, stop_s = np.asarray(node_s), np.asarray(stop_s)
    inside = node_s < length_m - 1.0
    return Route(s0_m=s0[keep], len_m=lens,
                 p0_m=np.array([q[0] for q in prims])[keep],
                 psi0_rad=np.array([q[1] for q in prims])[keep],
                 kappa_pm=np.array([q[2] for q in prims])[keep],
                 node_s_m=node_s[inside], stop_s_m=np.maximum(stop_s[inside], 0.0))


def make_route(city: City, rng: np.random.Generator, cfg: EmulationConfig) -> Route:
    """The random lane-centre route of ``cfg.route_length_m`` through ``city``.

    Args:
        city: The city whose street grid is driven.
        rng: The drive's ``'route'`` stream (the speed profile draws from it next).
        cfg: Parameters (length, lane offset, turn radius).

    Returns:
        The route, cut to ``cfg.route_length_m``.
    """
    nodes, dirs = _walk_nodes(city, rng, cfg.route_length_m + 2 * city.pitch_m)
    return _build_route(city, nodes, dirs, cfg, cfg.route_length_m)
