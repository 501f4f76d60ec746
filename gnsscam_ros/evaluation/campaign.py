"""The paper's evaluation campaign on the emulated drive (paper §7-8, Tables 2-4).

For every seed (a different drive, satellite faults and camera faults), every GNSS case
(NLOS only; 2, 4, 6, 9 faulty satellites of 12 with 100 m and 200 m bias) and both methods
(Particle RAIM: GNSS only with the paper's mixture likelihood; fused: GNSS + camera with
the KL mixture of experts; and gnss_robust, the fused filter without the camera, which
isolates what the camera adds), run the filter and score it. Camera matching does not depend
on the GNSS case, so each seed's images are rendered and matched once, in parallel, and
the matches are reused by every case. Runs are spread over all cores.
"""
from __future__ import annotations

import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..core.engine import best_match
from ..core.filter import PARTICLE_RAIM, FilterConfig
from ..datasets.emulated.map_database import build_emulated_map_database
from ..datasets.emulated.scenario import scenario_of
from ..datasets.emulated.drive import make_emulated_drive
from ..io.atomic import write_csv_atomic, write_npz_atomic
from ..io.tables import format_table
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


def camera_matches_for_seed(seed: int, cache_dir: Path) -> tuple[list, dict]:
    """Render and match every camera frame of a seed's drive (cached on disk).

    The map database comes from the seed's own database pass (other lighting and
    viewpoints, ``datasets.emulated.views``); each frame's best match (top-1) is kept.

    Returns:
        ``(matches, faults)``: a CameraMeasurement per frame with a match (position at the
        image time) and ``{frame_id: fault code}`` (0 clean, 1 blur, 2 occlusion).
    """
    cache_dir = Path(cache_dir)
    drive = make_emulated_drive(seed, camera=True)
    stream = drive.camera
    key = f"camera_matches_s{seed}_{stream.info.get('render_version', 0)}_{len(stream)}.npz"
    path = cache_dir / key
    if path.exists():
        data = np.load(path, allow_pickle=False)
        stamps, positions, scores, frame_ids = (data['stamp_ns'], data['position_enu_m'],
                                                data['score'], data['frame_id'])
    else:
        db = build_emulated_map_database(scenario_of(drive), cache_dir=cache_dir,
                                         margin_m=DATABASE_MARGIN_M)
        found = offline_camera_matches(stream, db, top_k=1)
        stamps = np.array([m.stamp_ns for m in found], np.int64)
        positions = np.array([m.position_enu_m for m in found]).reshape(-1, 3)
        scores = np.array([m.score for m in found], float)
        frame_ids = np.array([m.frame_id for m in found], np.int64)
        write_npz_atomic(path, stamp_ns=stamps, position_enu_m=positions, score=scores,
                         frame_id=frame_ids)
    matches = [best_match(t, p[None], np.array([sc]), f)
               for t, p, sc, f in zip(stamps, positions, scores, frame_ids)]
    return matches, {int(i): int(c) for i, c in enumerate(stream.fault)}


def case_tag(faults: int, bias_m: float) -> str:
    """Short file-name tag of a GNSS case."""
    return f'f{faults}_b{bias_m:g}' if faults else 'nlos'


def run_case(seed: int, faults: int, bias_m: float, method: str, base: FilterConfig,
             matches: list | None, frame_faults: dict | None,
             epochs_dir: Path | None = None, force: bool = False,
             duration_s: float | None = None) -> dict:
    """One (seed, GNSS case, method) run; returns metrics plus the series for plots.

    With ``epochs_dir`` the run's per-epoch table is written there as
    ``epochs_s<seed>_<case>_<method>.csv`` (one row per GNSS epoch, as ``--epochs-csv``).
    ``duration_s`` cuts the drive short (tests).
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
    if epochs_dir is not None:
        path = Path(epochs_dir) / f'epochs_s{seed}_{case_tag(faults, bias_m)}_{method}.csv'
        write_csv_atomic(path, list(record.epochs.CSV_COLUMNS), record.epochs.csv_rows(),
                         force=force)
        out['epochs_csv'] = str(path)
    if config.use_camera and frame_faults:
        by_fault: dict[str, list[float]] = {}
        for frame_id, alpha in record.camera_alpha.items():
            by_fault.setdefault(FAULT_NAMES[frame_faults.get(frame_id, 0)], []).append(alpha)
        out['camera'] = {
            'epochs_with_camera': record.camera_epochs,
            'epochs_camera_excluded': record.camera_excluded_epochs,
            'mean_alpha': {k: float(np.mean(v)) for k, v in by_fault.items()},
            'frames': {k: len(v) for k, v in by_fault.items()}}
    series = {'t_s': (record.stamp_ns - record.stamp_ns[0]) * 1e-9 if len(record.stamp_ns)
              else record.stamp_ns, 'estimate': record.estimate_enu_m,
              'truth': record.truth_enu_m,
              'bound': record.risk_bound[config.inverse_bernoulli],
              'reference': record.reference_risk,
              'error_m': np.hypot(*(record.estimate_enu_m - record.truth_enu_m)[:, :2].T),
              'protection_level_m': record.protection_level_m,
              'integrity': np.where(record.integrity_ok, 'OK', 'ERROR')}
    return {'metrics': out, 'series': series}


def _mean(values):
    values = [v for v in values if v is not None]
    return float(np.mean(values)) if values else None


def campaign_tables(cases: list[dict]) -> str:
    """Table 2 (RMSE of every method) and Tables 3-4 (integrity of the fused method)."""
    def select(**kw):
        return [c for c in cases if all(c[k] == v for k, v in kw.items())]

    methods = [m for m in METHODS if select(method=m)]
    rows = []
    for faults, bias in GNSS_CASES:
        rmse = {}
        for m in methods:
            runs = select(faults=faults, bias_m=bias, method=m)
            rmse[m] = (_mean([c['rmse_3d_m'] for c in runs]),
                       _mean([c['rmse_2d_m'] for c in runs]))
        row = [f'{bias:g}' if faults else 'NLOS only', faults]
        for m in methods:
            row += list(rmse[m])
        fused, praim = rmse.get('fused', (None,))[0], rmse.get('particle_raim', (None,))[0]
        row.append(fused / praim if fused is not None and praim else None)
        rows.append(row)
    headers = ['bias [m]', 'faults']
    for m in methods:
        headers += [f'{m} 3D', f'{m} 2D']
    text = ['Table 2: RMSE [m] (mean over seeds)',
            format_table(headers + ['fused/PRAIM 3D'], rows)]
    for limit in ('8', '16'):
        rows = []
        for faults, bias in GNSS_CASES:
            fu = select(faults=faults, bias_m=bias, method='fused')
            ints = [c['integrity'][limit] for c in fu]
            rows.append([f'{bias:g}' if faults else 'NLOS only', faults] + [
                _mean([m[k] for m in ints]) for k in
                ('p_fa', 'p_mi', 'failure_ratio', 'failure_error_m', 'bound_gap')])
        text += ['', f'Table {3 if limit == "8" else 4}: integrity of the fused filter, '
                     f'alert limit {limit} m (mean over seeds)',
                 format_table(['bias [m]', 'faults', 'P_FA', 'P_MI', 'fail ratio',
                               'fail err [m]', 'bound gap'], rows)]
    rows = []
    for faults, bias in GNSS_CASES:
        row = [f'{bias:g}' if faults else 'NLOS only', faults]
        for m in methods:
            pls = [c['protection_level'] for c in select(faults=faults, bias_m=bias, method=m)
                   if 'protection_level' in c]
            row += [_mean([p['mi_rate'] for p in pls]),
                    _mean([p['availability'].get('8') for p in pls]),
                    _mean([p['median_m'] for p in pls])]
        rows.append(row)
    headers = ['bias [m]', 'faults']
    for m in methods:
        headers += [f'{m} MI', f'{m} av8', f'{m} PL50']
    text += ['', 'Protection level: MI rate (error > PL), availability at 8 m (PL <= 8 m), '
                 'median PL [m] (mean over seeds)', format_table(headers, rows)]
    return '\n'.join(text)


def run_campaign(seeds=(1, 2, 3), base: FilterConfig | None = None,
                 methods=METHODS, cases=GNSS_CASES, workers: int | None = None,
                 cache_dir: Path = Path('.cache/gnsscam'), plots_dir: Path | None = None,
                 progress: bool = True, epochs_dir: Path | None = None, force: bool = False,
                 duration_s: float | None = None) -> dict:
    """Run the whole campaign; returns ``{'cases': [...], 'config': {...}, ...}``.

    ``config`` is the base configuration (FilterConfig fields), ``method_configs`` what
    each method ran; every case carries ``protection_level``
    (:func:`.metrics.protection_level_metrics`). ``epochs_dir``: one per-epoch CSV per run;
    ``duration_s`` cuts every drive short (tests; the camera needs the whole drive).
    """
    base = base or campaign_config()
    workers = workers or os.cpu_count() or 1
    start = time.monotonic()
    need_camera = any(method_config(m, base).use_camera for m in methods)
    camera: dict[int, tuple] = {}
    with ProcessPoolExecutor(max_workers=workers) as pool:
        if need_camera:
            futures = {s: pool.submit(camera_matches_for_seed, s, cache_dir) for s in seeds}
            for s, fut in futures.items():
                camera[s] = fut.result()
                if progress:
                    print(f'[campaign] seed {s}: {len(camera[s][0])} camera frames matched '
                          f'({time.monotonic() - start:.0f} s)', file=sys.stderr)
        jobs = []
        for s in seeds:
            matches, frame_faults = camera.get(s, (None, None))
            for faults, bias in cases:
                for method in methods:
                    jobs.append(pool.submit(run_case, s, faults, bias, method, base,
                                            matches, frame_faults, epochs_dir, force,
                                            duration_s))
        results = []
        for i, job in enumerate(jobs):
            results.append(job.result())
            if progress:
                m = results[-1]['metrics']
                print(f'[campaign] {i + 1}/{len(jobs)} seed {m["seed"]} faults {m["faults"]} '
                      f'bias {m["bias_m"]:g} {m["method"]}: 3D RMSE {m["rmse_3d_m"]:.1f} m '
                      f'({time.monotonic() - start:.0f} s)', file=sys.stderr)
    cases_out = [r['metrics'] for r in results]
    alphas = {}
    for c in cases_out:
        for k, v in c.get('camera', {}).get('mean_alpha', {}).items():
            alphas.setdefault(k, []).append(v)
    out = {'cases': cases_out, 'seeds': list(seeds), 'config': base.as_flat(),
           'method_configs': {m: method_config(m, base).as_flat() for m in methods},
           'camera_mean_alpha': {k: float(np.mean(v)) for k, v in alphas.items()},
           'seconds': time.monotonic() - start, 'workers': workers}
    if plots_dir is not None:
        out['plots'] = [str(p) for p in make_plots(results, Path(plots_dir), base)]
    return out


def make_plots(results: list[dict], plots_dir: Path, base: FilterConfig) -> list[Path]:
    """Trajectory, risk and error/PL figures for the first seed of every case, and a
    Stanford diagram per method pooled over every seed and case (alert limit 8 m)."""
    # matplotlib takes ~0.7 s to import: only when figures are asked for.
    from .plots import error_pl_timeline, risk_plot, stanford_diagram, trajectory_plot
    paths = []
    limit = float(base.alert_limit_m)
    for method in dict.fromkeys(r['metrics']['method'] for r in results):
        runs = [r['series'] for r in results if r['metrics']['method'] == method]
        err = np.concatenate([s['error_m'] for s in runs])
        pl = np.concatenate([s['protection_level_m'] for s in runs])
        path = plots_dir / f'stanford_{method}_al{limit:g}.png'
        stanford_diagram(path, f'{method}: every seed and case pooled', err, pl, limit)
        paths.append(path)
    first_seed = min(r['metrics']['seed'] for r in results)
    by_case: dict[tuple, dict] = {}
    for r in results:
        m = r['metrics']
        if m['seed'] == first_seed:
            by_case.setdefault((m['faults'], m['bias_m']), {})[m['method']] = r['series']
    for (faults, bias), series in sorted(by_case.items()):
        tag = case_tag(faults, bias)
        name = f'{faults} faults, {bias:g} m bias' if faults else 'NLOS only'
        any_series = next(iter(series.values()))
        paths.append(trajectory_plot(plots_dir / f'trajectory_{tag}.png',
                                     f'{name} (seed {first_seed})', any_series['truth'],
                                     {k: v['estimate'] for k, v in series.items()}))
        for method, s in series.items():
            for a, limit in enumerate(base.alert_limits_m):
                paths.append(risk_plot(
                    plots_dir / f'risk_{tag}_{method}_al{limit:g}.png',
                    f'{method}, {name}', s['t_s'], s['bound'][:, a], s['reference'][:, a],
                    limit, base.target_risk))
            paths.append(error_pl_timeline(
                plots_dir / f'error_pl_{tag}_{method}.png',
                f'{method}, {name} (seed {first_seed})', s['t_s'], s['error_m'],
                s['protection_level_m'], base.alert_limit_m, s['integrity']))
    return paths
