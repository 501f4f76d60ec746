"""Run a campaign grid: resume what a folder holds, run the rest on a cluster, stream every
finished case to disk, and summarise with confidence intervals (``gnsscam_eval campaign``).
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..core.filter import FilterConfig
from ..io.atomic import write_csv_atomic, write_json_atomic
from .campaign import GNSS_CASES, METHODS, campaign_config, method_config
from .campaign_cluster import CaseRunner
from .campaign_grid import CaseKey, case_grid, case_tag, fingerprint, format_seeds
from .campaign_store import CampaignStore
from .campaign_summary import (INTERVAL_CSV_COLUMNS, campaign_intervals, interval_csv_rows,
                               run_csv)


def run_campaign(seeds=(1, 2, 3), base: FilterConfig | None = None, methods=METHODS,
                 cases=GNSS_CASES, out_dir: Path | None = None, restart: bool = False,
                 scheduler: str | None = None, workers: int | None = None,
                 sequential: bool = False, cache_dir: Path | None = None,
                 plots_dir: Path | None = None, epochs_dir: Path | None = None,
                 progress: bool = True, duration_s: float | None = None,
                 on_case=None) -> dict:
    """Run the grid seeds x GNSS cases x methods; returns the campaign summary.

    Args:
        seeds: Drive seeds.
        base: Base filter configuration (default :func:`.campaign.campaign_config`).
        methods: Methods (:func:`.campaign.method_config`).
        cases: GNSS cases ``(faults, bias_m)``.
        out_dir: Campaign folder (:mod:`.campaign_store`): finished cases found there
            are not recomputed, each new one is written as it finishes, and the summary
            (``campaign.json``, ``runs.csv``, ``intervals.csv``) at the end. None: keep
            everything in memory.
        restart: Discard the cases in ``out_dir`` first.
        scheduler: Address of an existing Dask scheduler (None: embedded cluster).
        workers: Worker processes of the embedded cluster (default: the cores).
        sequential: Run in this process, without Dask.
        cache_dir: Worker-side cache of map databases and camera matches (a path on every
            worker; None: each worker's default).
        plots_dir: Folder for the figures (None: none).
        epochs_dir: One per-epoch CSV per case here (written by this process).
        progress: A progress bar on stderr (cases done, epochs per second).
        duration_s: Cut every drive short (tests, quick looks).
        on_case: Called as ``on_case(key, metrics)`` after each new case is stored.

    Returns:
        ``{'cases': [metrics in grid order], 'intervals': ..., 'cluster': ...,
        'campaign': ..., 'config', 'method_configs', 'failed', ...}``.

    Raises:
        campaign_store.CampaignStoreError: ``out_dir`` holds another campaign.
        campaign_cluster.ClusterError: The cluster cannot be started or reached.
    """
    base = base or campaign_config()
    fp = fingerprint(base.as_flat(), duration_s)
    keys = case_grid(seeds, cases, methods)
    store = CampaignStore(out_dir, fp, restart) if out_dir is not None else None
    metrics = store.finished(keys) if store is not None else {}
    resumed = len(metrics)
    todo = [k for k in keys if k not in metrics]
    series: dict[CaseKey, dict] = {}
    failed, workers_used = [], set()
    start = time.monotonic()
    epochs_run = 0
    bar = tqdm(total=len(keys), initial=resumed, unit='case', disable=not progress,
               file=sys.stderr, dynamic_ncols=True, desc='campaign')
    try:
        # Nothing left to compute (a finished campaign run again): no cluster to start.
        with CaseRunner(None if not todo else scheduler, workers, sequential or not todo,
                        None if cache_dir is None else str(cache_dir)) as runner:
            bar.set_postfix_str(f"{runner.info['kind']}, {runner.info['workers']} workers")
            ready = time.monotonic()
            for key, result, error in runner.run(todo, base, duration_s,
                                                 want_epochs=epochs_dir is not None):
                if error is not None:
                    failed.append({**key.as_dict(), 'error': error})
                    bar.write(f'[campaign] {key.tag} failed: {error}')
                    continue
                # Where and how long it ran: bookkeeping, not a result of the case.
                result['metrics'].update(worker=result['worker'],
                                         wall_seconds=result['wall_seconds'])
                _keep(key, result, store, series, epochs_dir)
                metrics[key] = result['metrics']
                workers_used.add(result['worker'])
                epochs_run += result['metrics']['gnss_epochs']
                rate = epochs_run / max(time.monotonic() - ready, 1e-9)
                bar.update(1)
                bar.set_postfix_str(f'{rate:.1f} epochs/s, {runner.info["workers"]} workers')
                if on_case is not None:
                    on_case(key, result['metrics'])
            cluster = dict(runner.info) if todo else {
                'kind': 'none', 'scheduler': None, 'workers': 0, 'threads_per_worker': 0,
                'dask': None}
            running = time.monotonic() - ready
    finally:
        bar.close()
    seconds = time.monotonic() - start
    cluster['startup_seconds'] = ready - start
    cluster['workers_used'] = len(workers_used)
    out = _summary(keys, metrics, base, methods, cases, seeds, duration_s, fp)
    out.update({'cluster': cluster, 'workers': cluster['workers'], 'failed': failed,
                'resumed': resumed, 'computed': len(todo) - len(failed),
                'seconds': seconds, 'epochs_computed': epochs_run,
                'epochs_per_second': epochs_run / running if running > 0 else None,
                'out_dir': str(out_dir) if out_dir is not None else None})
    if store is not None:
        _write_summary(Path(out_dir), out)
    if plots_dir is not None:
        def load(key):
            return series[key] if key in series else store.series(key)
        done = [k for k in keys if k in metrics]
        out['plots'] = [str(p) for p in make_plots(done, load, Path(plots_dir), base,
                                                   out['intervals'])]
    return out


def _keep(key: CaseKey, result: dict, store, series: dict, epochs_dir) -> None:
    """Write what a finished case leaves behind (epochs CSV, then the case itself)."""
    if epochs_dir is not None:
        table = result['epochs']
        write_csv_atomic(Path(epochs_dir) / f'epochs_{key.tag}.csv',
                         list(table.CSV_COLUMNS), table.csv_rows(), force=True)
        result['metrics']['epochs_csv'] = str(Path(epochs_dir) / f'epochs_{key.tag}.csv')
    if store is not None:
        store.save(key, result)
    else:
        series[key] = result['series']


def _summary(keys, metrics, base, methods, cases, seeds, duration_s, fp) -> dict:
    cases_out = [metrics[k] for k in keys if k in metrics]
    alphas: dict[str, list] = {}
    for c in cases_out:
        for k, v in c.get('camera', {}).get('mean_alpha', {}).items():
            alphas.setdefault(k, []).append(v)
    return {
        'campaign': {'seeds': format_seeds(seeds), 'n_seeds': len(set(seeds)),
                     'gnss_cases': [list(c) for c in cases], 'methods': list(methods),
                     'runs': len(keys), 'duration_s': duration_s, 'fingerprint': fp},
        'cases': cases_out, 'seeds': sorted(set(int(s) for s in seeds)),
        'intervals': campaign_intervals(cases_out),
        'config': base.as_flat(),
        'method_configs': {m: method_config(m, base).as_flat() for m in methods},
        'camera_mean_alpha': {k: float(np.mean(v)) for k, v in alphas.items()},
        'epochs': int(sum(c['epochs'] for c in cases_out))}


def _write_summary(folder: Path, out: dict) -> None:
    write_json_atomic(folder / 'campaign.json', out, force=True)
    header, rows = run_csv(out['cases'])
    write_csv_atomic(folder / 'runs.csv', header, rows, force=True)
    write_csv_atomic(folder / 'intervals.csv', INTERVAL_CSV_COLUMNS,
                     interval_csv_rows(out['intervals']), force=True)


def make_plots(keys: list[CaseKey], load, plots_dir: Path, base: FilterConfig,
               intervals: dict) -> list[Path]:
    """The rates with their intervals per method, a Stanford diagram per method pooled
    over every seed and case (alert limit of the flag), and trajectory, risk and error/PL
    figures of the first seed of every case (``load(key)`` gives a case's series)."""
    # matplotlib takes ~0.7 s to import: only when figures are asked for.
    from . import plots as figures
    paths = []
    limit = float(base.alert_limit_m)
    for method in dict.fromkeys(k.method for k in keys):
        mine = [k for k in keys if k.method == method]
        runs = [load(k) for k in mine]
        err = np.concatenate([s['error_m'] for s in runs])
        pl = np.concatenate([s['protection_level_m'] for s in runs])
        path = plots_dir / f'stanford_{method}_al{limit:g}.png'
        mi = intervals['by_method'][method]['rates']['mi_rate']
        title = f'{method}: {len({k.seed for k in mine})} seeds, every case pooled'
        if mi['ci95'] is not None:
            title += (f"\nMI rate {mi['rate']:.4f}, 95 % CI [{mi['ci95'][0]:.4f}, "
                      f"{mi['ci95'][1]:.4f}] ({mi['count']}/{mi['n']})")
        figures.stanford_diagram(path, title, err, pl, limit)
        paths.append(path)
        groups = [g for g in intervals['by_case'] if g['method'] == method]
        paths.append(figures.interval_plot(
            plots_dir / f'intervals_{method}_al{limit:g}.png',
            f'{method}: rates with 95 % intervals', groups, intervals['by_method'][method],
            f'{limit:g}'))
    first_seed = min(k.seed for k in keys)
    by_case: dict[tuple, dict] = {}
    for k in keys:
        if k.seed == first_seed:
            by_case.setdefault((k.faults, k.bias_m), {})[k.method] = load(k)
    for (faults, bias), series in sorted(by_case.items()):
        tag = case_tag(faults, bias)
        name = f'{faults} faults, {bias:g} m bias' if faults else 'NLOS only'
        any_series = next(iter(series.values()))
        paths.append(figures.trajectory_plot(
            plots_dir / f'trajectory_{tag}.png', f'{name} (seed {first_seed})',
            any_series['truth'], {k: v['estimate'] for k, v in series.items()},
            base.alert_limit_m))
        for method, s in series.items():
            for a, al in enumerate(base.alert_limits_m):
                paths.append(figures.risk_plot(
                    plots_dir / f'risk_{tag}_{method}_al{al:g}.png',
                    f'{method}, {name}', s['t_s'], s['bound'][:, a], s['reference'][:, a],
                    al, base.target_risk))
            paths.append(figures.error_pl_timeline(
                plots_dir / f'error_pl_{tag}_{method}.png',
                f'{method}, {name} (seed {first_seed})', s['t_s'], s['error_m'],
                s['protection_level_m'], base.alert_limit_m, s['integrity']))
    return paths
