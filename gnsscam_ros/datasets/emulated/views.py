"""Views of the map-database pass of the emulated city (the geotagged images' poses).

The database pass is another drive along the streets within ``margin_m`` of the route, in
both directions, every ``spacing_m`` metres, plus the turn arcs at the intersections (a
Street View panorama can be looked at in any direction), with other lighting (overcast by
default), lateral offsets up to +-1.5 m from the lane centre and heading offsets up to
+-5 deg. :func:`database_poses` places the views, :func:`map_database_views` renders them
lazily; :mod:`.map_database` turns them into a :class:`...vision.database.MapDatabase`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterator

import numpy as np
from scipy.spatial import cKDTree

from ...core.rng import spawn
from ...core.types import Drive
from .optics import CameraIntrinsics, Lighting
from .render import StreetRenderer
from .scenario import Scenario, seed_of

_DIRS = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])   # E, N, W, S

#: Added to the database pass's seed to seed its renderer's sensor noise, so that the query
#: and database passes of one seed get different noise banks.
NOISE_SEED_OFFSET = 7919


def _right(u: np.ndarray) -> np.ndarray:
    """Unit vector 90 deg clockwise of the (.., 2) direction ``u``."""
    return np.stack([u[..., 1], -u[..., 0]], axis=-1)


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
            for ``region='route'`` (e.g. a drive cut short, :func:`route_range_of`);
            None: the whole route.

    Returns:
        The poses.
    """
    if spacing_m <= 0:
        raise ValueError(f'spacing_m must be positive, got {spacing_m}')
    if region not in ('route', 'city'):
        raise ValueError(f"region must be 'route' or 'city', got {region!r}")
    seed = seed_of(scenario, seed)
    rng_light, rng = spawn(np.random.default_rng(np.random.SeedSequence([seed, 0xDA7AB])), 2)
    if lighting is None:
        lighting = Lighting.overcast(rng_light)
    # Views are drawn for the whole city, then filtered, so that the random offsets of a
    # view do not depend on the margin (databases for growing margins are nested).
    poses, kinds = _street_views(scenario, rng, spacing_m, lateral_m, heading_deg)
    if turns:
        turn_poses, turn_kinds = _turn_views(scenario, rng, spacing_m, lateral_m, heading_deg)
        poses += turn_poses
        kinds += turn_kinds
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


def _street_views(scenario: Scenario, rng: np.random.Generator, spacing_m: float,
                  lateral_m: float, heading_deg: float) -> tuple[list, list]:
    """Views along every street edge of the city, both directions (kind 0).

    Returns:
        Lists of (k, 4) pose arrays and of (k,) kind arrays, one pair per edge direction.
    """
    city, cfg = scenario.city, scenario.config
    se, sn = np.asarray(city.street_e_m), np.asarray(city.street_n_m)
    pitch = float(city.pitch_m)
    cam_h, off = float(cfg.antenna_height_m), float(cfg.lane_offset_m)
    # Edges: (start node (2,), unit direction (2,)); N-S then E-W, deterministic order.
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
    return poses, kinds


def _turn_views(scenario: Scenario, rng: np.random.Generator, spacing_m: float,
                lateral_m: float, heading_deg: float) -> tuple[list, list]:
    """Views along every left and right turn arc of every intersection (kind 1).

    Returns:
        Lists of (k, 4) pose arrays and of (k,) kind arrays, one pair per arc.
    """
    city, cfg = scenario.city, scenario.config
    se, sn = np.asarray(city.street_e_m), np.asarray(city.street_n_m)
    pitch = float(city.pitch_m)
    cam_h = float(cfg.antenna_height_m)
    off, r_turn = float(cfg.lane_offset_m), float(cfg.turn_radius_m)
    arc_len = 0.5 * math.pi * r_turn
    poses, kinds = [], []
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
    return poses, kinds


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
    noise_seed = seed_of(scenario, kwargs.get('seed')) + NOISE_SEED_OFFSET
    renderer = StreetRenderer(scenario.city, intrinsics, dbp.lighting, seed=noise_seed)
    for k, name in enumerate(dbp.names):
        e, n, u, _ = dbp.pose[k]
        yield name, renderer.render(dbp.pose[k], noise_index=k), float(e), float(n), float(u)


def route_range_of(scenario: Scenario, drive: Drive,
                   margin_m: float = 50.0) -> tuple[float, float]:
    """Arc lengths ``(0, s_end + margin)`` [m] of the route a (cut) emulated drive covers.

    The map database only needs the streets the drive passes: limiting it to them (the
    ``route_range_m`` of :func:`database_poses`) keeps the first build of a short drive
    within a minute or two instead of rendering the whole city.
    """
    duration_s = float(drive.info.get('duration_s', scenario.duration_s))
    s_end = float(np.interp(duration_s, scenario.t_s, scenario.s_m))
    return 0.0, min(s_end + margin_m, float(scenario.route.length_m))
