"""The paper's evaluation campaign on the emulated drive (paper §7-8, Tables 2-4): the cases.

For every seed (a different drive, satellite faults and camera faults), every GNSS case
(NLOS only; 2, 4, 6, 9 faulty satellites of 12 with 100 m and 200 m bias) and every method
(Particle RAIM: GNSS only with the paper's mixture likelihood; fused: GNSS + camera with
the KL mixture of experts; and gnss_robust, the fused filter without the camera, which
isolates what the camera adds), run the filter and score it. This module holds what one
case needs, made from its arguments alone so that it runs on any worker of a cluster: the
drive is generated from its seed, and camera matching (which does not depend on the GNSS
case) is done once per seed (:func:`camera_matches_for_seed`) and shipped to the seed's
fused cases as a few arrays. Running a whole grid: :mod:`.campaign_run`.
"""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np

from ..core.engine import best_match
from ..core.filter import PARTICLE_RAIM, FilterConfig
from ..datasets.emulated.drive import make_emulated_drive
from ..datasets.emulated.map_database import build_emulated_map_database, default_cache_dir
from ..datasets.emulated.render import RENDER_VERSION
from ..datasets.emulated.scenario import scenario_of
from ..datasets.emulated.views import route_range_of
from ..io.atomic import write_npz_atomic
from .campaign_grid import CaseKey
from .runner import offline_camera_matches, run_filter, summarize

GNSS_CASES = [(0, 0.0)] + [(f, b) for b in (100.0, 200.0) for f in (2, 4, 6, 9)]
METHODS = ('particle_raim', 'gnss_robust', 'fused')
ALERT_LIMITS_M = (8.0, 16.0)
FAULT_NAMES = {0: 'clean', 1: 'blur', 2: 'occlusion'}
# Database pass: the streets within this distance of the route (both directions and the
# turn arcs, 3 m spacing). Wider margins add distractors but cost build time per seed.
DATABASE_MARGIN_M = 40.0


def campaign_config(**overrides) -> FilterConfig:
    """The campaign's base configuration: the package defaults (integrity included: the
    exact inverse Bernoulli, M posteriors with bias hypotheses) with risk bounds at the
    alert limits 8 and 16 m. The other inverse Bernoulli method is reported next to it;
    availability at 25 and 50 m comes from the protection level."""
    return FilterConfig(alert_limit_m=ALERT_LIMITS_M[0], extra_alert_limits_m=ALERT_LIMITS_M[1:],
                        **overrides)


def method_config(method: str, base: FilterConfig) -> FilterConfig:
    """The filter configuration of a method.

    particle_raim: the paper's GNSS mixture, epochs as independent evidence, no camera.
    fused: the package default (robust GNSS likelihood, tempered) plus the camera.
    gnss_robust: the fused method's GNSS part alone (isolates the camera's contribution).
    """
    if method == 'particle_raim':
        return replace(base, likelihood=PARTICLE_RAIM, error_correlation_time_s=0.0,
                       use_camera=False)
    if method == 'fused':
        return replace(base, use_camera=True)
    if method == 'gnss_robust':
        return replace(base, use_camera=False)
    raise ValueError(f'unknown method {method!r}')


@dataclass(frozen=True)
class CameraMatches:
    """The best database match of every camera frame of a seed's drive, as arrays.

    This is what a worker ships to the workers that run the seed's fused cases: a few
    hundred kB (no images, no database), made once per seed and campaign.

    Attributes:
        stamp_ns: (K,) image stamps [ns].
        position_enu_m: (K, 3) position of the best match, map frame [m].
        score: (K,) its retrieval score.
        frame_id: (K,) the frame's index in the camera stream.
        frame_fault: (F,) fault code of every frame (0 clean, 1 blur, 2 occlusion).
    """

    stamp_ns: np.ndarray
    position_enu_m: np.ndarray
    score: np.ndarray
    frame_id: np.ndarray
    frame_fault: np.ndarray

    def measurements(self) -> tuple[list, dict]:
        """``(matches, faults)``: a CameraMeasurement per matched frame and
        ``{frame_id: fault code}`` of every frame."""
        matches = [best_match(t, p[None], np.array([sc]), f) for t, p, sc, f in
                   zip(self.stamp_ns, self.position_enu_m, self.score, self.frame_id)]
        return matches, {i: int(c) for i, c in enumerate(self.frame_fault)}

    def nbytes(self) -> int:
        """Size of the arrays [bytes] (what a transfer carries, pickling aside)."""
        return sum(getattr(self, f.name).nbytes for f in fields(self))


def camera_cache_key(seed: int, duration_s: float | None = None) -> str:
    """Content key of a seed's camera matches: what decides them (drive seed and length,
    render version, database pass margin, matching top-k, file format)."""
    text = json.dumps({'seed': int(seed), 'duration_s': duration_s,
                       'render_version': RENDER_VERSION, 'margin_m': DATABASE_MARGIN_M,
                       'top_k': 1, 'format': 2}, sort_keys=True)
    return f's{int(seed)}_{hashlib.sha256(text.encode()).hexdigest()[:16]}'


def camera_matches_for_seed(seed: int, cache_dir: str | os.PathLike | None = None,
                            duration_s: float | None = None) -> CameraMatches:
    """Render and match every camera frame of a seed's drive, cached by content.

    Runs where it is called (a campaign runs it on a worker): the cache folder is that
    machine's (None: :func:`~gnsscam_ros.datasets.emulated.map_database.default_cache_dir`,
    i.e. ``$GNSSCAM_CACHE_DIR`` or ``~/.cache/gnsscam_ros``), and the file name is the
    content key (:func:`camera_cache_key`), so a stale file is never read. The map
    database comes from the seed's own database pass (other lighting and viewpoints,
    ``datasets.emulated.views``; for a cut drive only the route it covers); each frame's
    best match (top-1) is kept.
    """
    folder = Path(cache_dir if cache_dir is not None else default_cache_dir())
    path = folder / f'camera_matches_{camera_cache_key(seed, duration_s)}.npz'
    if path.exists():
        try:
            with np.load(path, allow_pickle=False) as data:
                return CameraMatches(**{f.name: data[f.name] for f in fields(CameraMatches)})
        except (OSError, KeyError, ValueError):
            pass                       # unreadable (a foreign or damaged file): rebuild
    drive = make_emulated_drive(seed, camera=True, duration_s=duration_s)
    stream = drive.camera
    scenario = scenario_of(drive)
    route = route_range_of(scenario, drive) if duration_s is not None else None
    db = build_emulated_map_database(scenario, cache_dir=folder, margin_m=DATABASE_MARGIN_M,
                                     route_range_m=route)
    found = offline_camera_matches(stream, db, top_k=1)
    out = CameraMatches(
        stamp_ns=np.array([m.stamp_ns for m in found], np.int64),
        position_enu_m=np.array([m.position_enu_m for m in found], float).reshape(-1, 3),
        score=np.array([m.score for m in found], float),
        frame_id=np.array([m.frame_id for m in found], np.int64),
        frame_fault=np.asarray(stream.fault, dtype=np.int8))
    write_npz_atomic(path, **{f.name: getattr(out, f.name) for f in fields(out)})
    return out


def run_case(seed: int, faults: int, bias_m: float, method: str, base: FilterConfig,
             matches: list | None, frame_faults: dict | None,
             duration_s: float | None = None) -> dict:
    """One (seed, GNSS case, method) run, made entirely from its arguments.

    Returns:
        ``{'metrics': ..., 'series': ..., 'epochs': EpochTable}``: the metrics the
        campaign records, the per-epoch arrays of its figures and the per-epoch table of
        ``--epochs-csv`` (one row per GNSS epoch). ``duration_s`` cuts the drive short.
    """
    drive = make_emulated_drive(seed, faults=faults, bias_m=bias_m, duration_s=duration_s)
    config = method_config(method, base)
    record = run_filter(drive, config, seed=seed,
                        camera_matches=matches if config.use_camera else None)
    metrics = summarize(record, config)
    out = {'faults': faults, 'bias_m': bias_m, 'method': method, 'seed': seed,
           'rmse_3d_m': metrics['rmse_3d_m'], 'rmse_2d_m': metrics['rmse_2d_m'],
           'epochs': metrics['epochs'], 'integrity': metrics['integrity'],
           'integrity_by_inverse_bernoulli': metrics['integrity_by_inverse_bernoulli'],
           'protection_level': metrics['protection_level'],
           'gnss_epochs': len(drive.gnss), 'filter_seconds': metrics['filter_seconds']}
    if config.use_camera and frame_faults:
        by_fault: dict[str, list[float]] = {}
        for frame_id, alpha in record.camera_alpha.items():
            by_fault.setdefault(FAULT_NAMES[frame_faults.get(frame_id, 0)], []).append(alpha)
        out['camera'] = {
            'epochs_with_camera': record.camera_epochs,
            'epochs_camera_excluded': record.camera_excluded_epochs,
            'mean_alpha': {k: float(np.mean(v)) for k, v in by_fault.items()},
            'frames': {k: len(v) for k, v in by_fault.items()}}
    t_s = ((record.stamp_ns - record.stamp_ns[0]) * 1e-9 if len(record.stamp_ns)
           else np.zeros(0))
    series = {'t_s': t_s, 'estimate': record.estimate_enu_m, 'truth': record.truth_enu_m,
              'bound': record.risk_bound[config.inverse_bernoulli],
              'reference': record.reference_risk,
              'error_m': np.hypot(*(record.estimate_enu_m - record.truth_enu_m)[:, :2].T),
              'protection_level_m': record.protection_level_m,
              'integrity': np.where(record.integrity_ok, 'OK', 'ERROR')}
    return {'metrics': out, 'series': series, 'epochs': record.epochs}


def case_task(key: CaseKey, base: FilterConfig, camera: CameraMatches | None,
              duration_s: float | None = None, want_epochs: bool = False) -> dict:
    """What a worker runs for one case: :func:`run_case` with the seed's camera matches
    (shipped to it); the per-epoch table only when asked (it is shipped back)."""
    matches, frame_faults = camera.measurements() if camera is not None else (None, None)
    out = run_case(key.seed, key.faults, key.bias_m, key.method, base, matches,
                   frame_faults, duration_s=duration_s)
    if not want_epochs:
        out.pop('epochs')
    return out


def uses_camera(method: str, base: FilterConfig) -> bool:
    """Whether a method's cases need the seed's camera matches."""
    return method_config(method, base).use_camera
