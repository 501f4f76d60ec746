"""Throughput of the campaign on Dask: ``python -m gnsscam_ros.bench.campaign``.

Measures, on one small grid (``--seed``, NLOS only and 4 faults x 200 m, the methods of
``--methods``, whole drives):

* the per-case cost in this process (wall and filter seconds, GNSS epochs), and the
  per-seed camera matching (rendering, map database, retrieval; cold, in a fresh cache);
* what crosses the network per case: the task (its key, the configuration, the seed's
  camera matches for a fused case) and the result (metrics and per-epoch series), pickled;
* epochs per second of the same grid on an embedded cluster with 1 and with 2 workers
  (wall time from a started cluster to the last result);

and derives the scaling to expect per added worker: each worker adds
``epochs per case / (case seconds + transfer seconds)`` epochs per second, transfers at
``--bandwidth-mbit``, until the scheduler's per-task cost (a few ms, measured as the
1-worker wall time beyond the summed case times) or the per-seed camera task limits it.
"""
from __future__ import annotations

import argparse
import os
import pickle
import shutil
import sys
import tempfile
import time
from pathlib import Path

from ..evaluation.campaign import (camera_matches_for_seed, campaign_config, case_task,
                                   uses_camera)
from ..evaluation.campaign_cluster import CaseRunner
from ..evaluation.campaign_grid import case_grid
from ..io.atomic import write_json_atomic
from ..io.tables import format_table

CASES = [(0, 0.0), (4, 200.0)]


def _pickled(obj) -> int:
    return len(pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL))


def per_case(keys, base, camera, duration_s) -> list[dict]:
    """Each case run here: seconds, epochs and the pickled sizes of task and result."""
    rows = []
    for key in keys:
        cam = camera if uses_camera(key.method, base) else None
        start = time.perf_counter()
        out = case_task(key, base, cam, duration_s)
        wall = time.perf_counter() - start
        rows.append({'case': key.tag, 'wall_s': wall,
                     'filter_s': out['metrics']['filter_seconds'],
                     'epochs': out['metrics']['gnss_epochs'],
                     'task_bytes': _pickled((key, base, cam, duration_s, False)),
                     'result_bytes': _pickled(out)})
    return rows


def _warm_up() -> None:
    import gnsscam_ros.evaluation.campaign  # noqa: F401  (what the first task imports)


def on_cluster(keys, base, workers: int, cache_dir: str, duration_s) -> dict:
    """The grid on an embedded cluster: epochs per second from the started cluster."""
    with CaseRunner(workers=workers, cache_dir=cache_dir) as runner:
        runner.client.run(_warm_up)            # imports: not part of the throughput
        start = time.perf_counter()
        epochs = 0
        case_s = 0.0
        for _, result, error in runner.run(keys, base, duration_s):
            if error:
                raise RuntimeError(error)
            epochs += result['metrics']['gnss_epochs']
            case_s += result['wall_seconds']
        wall = time.perf_counter() - start
    return {'workers': workers, 'wall_s': wall, 'epochs': epochs,
            'epochs_per_s': epochs / wall, 'summed_case_s': case_s}


def bench(seed: int = 1, methods=('gnss_robust', 'fused'), particles: int | None = None,
          duration_s: float | None = None, bandwidth_mbit: float = 1000.0,
          cache_dir: str = '.cache/gnsscam', camera_cold: bool = True) -> dict:
    """Run the measurements (module docstring); returns the figures (``camera_cold``
    False: the camera matches from the cache, their cold cost not measured)."""
    base = campaign_config(**({'n_particles': particles} if particles else {}))
    keys = case_grid([seed], CASES, methods)
    camera_s = None
    cold = tempfile.mkdtemp(prefix='gnsscam-bench-camera-')
    try:
        start = time.perf_counter()
        camera = camera_matches_for_seed(seed, cold if camera_cold else cache_dir,
                                         duration_s)
        camera_s = time.perf_counter() - start if camera_cold else None
        os.makedirs(cache_dir, exist_ok=True)
        for path in Path(cold).glob('*.npz'):           # warm the clusters' cache
            if not (Path(cache_dir) / path.name).exists():
                shutil.move(str(path), str(Path(cache_dir) / path.name))
    finally:
        shutil.rmtree(cold, ignore_errors=True)
    cases = per_case(keys, base, camera, duration_s)
    clusters = [on_cluster(keys, base, w, os.path.abspath(cache_dir), duration_s)
                for w in (1, 2)]
    n = len(cases)
    case_s = sum(c['wall_s'] for c in cases) / n
    epochs = sum(c['epochs'] for c in cases) / n
    transfer_b = sum(c['task_bytes'] + c['result_bytes'] for c in cases) / n
    transfer_s = transfer_b * 8 / (bandwidth_mbit * 1e6)
    overhead_s = max(clusters[0]['wall_s'] - clusters[0]['summed_case_s'], 0.0) / n
    per_worker = epochs / (case_s + transfer_s)
    return {'seed': seed, 'methods': list(methods), 'n_particles': base.n_particles,
            'n_posteriors': base.n_posteriors, 'duration_s': duration_s,
            'camera_seconds_cold': camera_s, 'camera_bytes': camera.nbytes(),
            'camera_pickled_bytes': _pickled(camera), 'cases': cases,
            'clusters': clusters, 'cpu_count': os.cpu_count(),
            'model': {'case_seconds': case_s, 'epochs_per_case': epochs,
                      'transfer_bytes_per_case': transfer_b,
                      'bandwidth_mbit': bandwidth_mbit, 'transfer_seconds': transfer_s,
                      'overhead_seconds_per_case': overhead_s,
                      'epochs_per_second_per_worker': per_worker,
                      'speedup_2_workers': clusters[1]['epochs_per_s']
                      / clusters[0]['epochs_per_s'],
                      'workers_before_scheduler_bound': (case_s / overhead_s
                                                         if overhead_s > 0 else None)}}


def report(out: dict) -> str:
    rows = [[c['case'], c['epochs'], c['wall_s'], c['filter_s'], c['task_bytes'] / 1e3,
             c['result_bytes'] / 1e3] for c in out['cases']]
    text = [f"per case in this process (seed {out['seed']}, N = {out['n_particles']}, "
            f"M = {out['n_posteriors']}):",
            format_table(['case', 'epochs', 'wall [s]', 'filter [s]', 'task [kB]',
                          'result [kB]'], rows),
            'camera matching of the seed, cold: '
            + (f"{out['camera_seconds_cold']:.1f} s" if out['camera_seconds_cold'] else
               'not measured (--no-camera-cold)')
            + f", shipped as {out['camera_pickled_bytes'] / 1e3:.0f} kB", '',
            format_table(['workers', 'wall [s]', 'epochs', 'epochs/s'],
                         [[c['workers'], c['wall_s'], c['epochs'], c['epochs_per_s']]
                          for c in out['clusters']])]
    m = out['model']
    text += ['', f"speed-up with 2 workers on {out['cpu_count']} cores: "
                 f"{m['speedup_2_workers']:.2f}",
             f"per added worker (its own core): +{m['epochs_per_second_per_worker']:.1f} "
             f"epochs/s ({m['epochs_per_case']:.0f} epochs in {m['case_seconds']:.1f} s per "
             f"case, {m['transfer_bytes_per_case'] / 1e3:.0f} kB = "
             f"{m['transfer_seconds'] * 1e3:.2f} ms at {m['bandwidth_mbit']:g} Mbit/s); "
             f"scheduler and client {m['overhead_seconds_per_case'] * 1e3:.0f} ms per case"]
    return '\n'.join(text)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='python -m gnsscam_ros.bench.campaign',
                                     description=__doc__.split('\n')[0])
    parser.add_argument('--seed', type=int, default=1)
    parser.add_argument('--methods', nargs='+', default=['gnss_robust', 'fused'])
    parser.add_argument('--particles', type=int, default=None)
    parser.add_argument('--duration-s', type=float, default=None,
                        help='cut the drives short (a quick look; default: whole drives)')
    parser.add_argument('--bandwidth-mbit', type=float, default=1000.0)
    parser.add_argument('--cache', default='.cache/gnsscam')
    parser.add_argument('--no-camera-cold', action='store_true',
                        help="take the seed's camera matches from --cache (a rerun)")
    parser.add_argument('--json', type=Path, help='write the figures as JSON')
    args = parser.parse_args(argv)
    out = bench(args.seed, tuple(args.methods), args.particles, args.duration_s,
                args.bandwidth_mbit, args.cache, not args.no_camera_cold)
    print(report(out))
    if args.json:
        write_json_atomic(args.json, out, force=True)
        print(f'wrote {args.json}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
