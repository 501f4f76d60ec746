"""Geotagged map database of the emulated city, rendered, described and cached on disk.

:func:`build_emulated_map_database` renders the database pass (:mod:`.views`), extracts
ORB descriptors from every view and builds a :class:`...vision.database.MapDatabase` over
them, cached under :func:`default_cache_dir` by a hash of everything that decides it.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from typing import Callable

import numpy as np

from ...vision.database import MapDatabase, PositionTable
from ...vision.errors import MapDatabaseError
from ...vision.features import OrbExtractor, OrbParams
from .optics import CameraIntrinsics
from .render import RENDER_VERSION, StreetRenderer
from .scenario import Scenario
from .views import NOISE_SEED_OFFSET, DatabasePass, database_poses


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
    the ORB and tree settings and :data:`.render.RENDER_VERSION`. Writes are atomic
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
                                       dbp.params['seed'] + NOISE_SEED_OFFSET, progress)
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
