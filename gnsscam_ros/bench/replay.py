"""Benchmark: replay through the nodes (``python -m gnsscam_ros.bench.replay``).

Converts a seeded emulated drive (GNSS 1 Hz, IMU 100 Hz, odometry 10 Hz, ground truth;
optionally the camera at 10 Hz with its map database) into a bag, replays it at
``R = 0`` (as fast as the nodes keep up, lossless: :mod:`gnsscam_ros.live.flow`) through gnss_node,
imu_node, camera_node and fusion_node at ``--particles`` particles, records the outputs,
and reports:

* the replay speed as a multiple of real time (bag time / wall time from the first
  message to the last acknowledgement; node start-up is not included);
* GNSS epochs published, processed by the filter (an ``integrity_risk`` came back for
  each) and dropped (published - processed), and fusion_node's own ``dropped_epochs``
  counter;
* the CPU time of each process (replay + recorder here; each node process).

Each measurement is printed and, with ``--json``, written as JSON.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from ..core.config import FilterConfig
from ..bags.convert import convert_drive
from ..datasets.emulated.camera import with_camera
from ..datasets.emulated.drive import make_emulated_drive
from ..datasets.emulated.map_database import build_emulated_map_database
from ..datasets.emulated.scenario import scenario_of
from ..datasets.emulated.views import route_range_of
from ..io.atomic import write_json_atomic
from ..io.tables import format_table
from ..live.replay_through_nodes import replay_through_nodes
from ..live.launch import LAYOUTS


def bench_once(particles: int = 10_000, duration_s: float = 120.0, seed: int = 3,
               layout: str = 'processes', acquisition_particles: int | None = None,
               camera: bool = False, topics: list[str] | None = None,
               work_dir: Path | None = None, log=print) -> dict:
    """One replay of an emulated drive through the nodes; returns the figures.

    Args:
        particles: Filter particles per posterior N (the other filter parameters: the
            package defaults, M = ``FilterConfig().n_posteriors`` posteriors).
        duration_s: Length of the drive [s].
        seed: Drive (and filter) seed.
        layout: Where the nodes run (:data:`gnsscam_ros.live.launch.LAYOUTS`).
        acquisition_particles: ``acquisition_particles`` (None: the filter default, 10,000
            particles for the first 100 m when N is smaller).
        camera: Include the camera (renders the frames and builds the map database of the
            drive's route; slow the first time).
        topics: Topics to replay (None: all).
        work_dir: Folder for the bags (default: a temporary folder, removed afterwards).
        log: Progress printer.

    Returns:
        The figures (see the module docstring) and the replay summary.
    """
    drive = make_emulated_drive(seed, faults=6, bias_m=100.0, duration_s=duration_s)
    params: dict = {'fusion_node': {'n_particles': int(particles), 'seed': int(seed),
                                    'use_map_origin': True,
                                    'map_origin_llh': [float(v) for v in drive.origin_llh]}}
    if acquisition_particles is not None:
        params['fusion_node']['acquisition_particles'] = int(acquisition_particles)
    folder = Path(work_dir) if work_dir is not None else Path(
        tempfile.mkdtemp(prefix='gnsscam_replay_bench_'))
    try:
        if camera:
            drive = with_camera(drive)
            scenario = scenario_of(drive)
            log('bench: map database of the route (cached after the first build) ...')
            db = build_emulated_map_database(scenario,
                                             route_range_m=route_range_of(scenario, drive))
            db_path = folder / 'map.npz'
            db.save(db_path)
            params['camera_node'] = {'database_path': str(db_path)}
        bag = folder / f'emulated_s{seed}_{duration_s:g}s'
        log(f'bench: converting {duration_s:g} s of the emulated drive -> {bag}')
        convert_drive(drive, bag)
        log(f'bench: replaying through the nodes ({layout}), N = {particles} ...')
        started = time.monotonic()
        summary, record = replay_through_nodes(
            bag, folder / 'result', rate=0.0, parameters=params, layout=layout, topics=topics,
            log_dir=folder / 'logs')
        total_s = time.monotonic() - started
    finally:
        if work_dir is None:
            shutil.rmtree(folder, ignore_errors=True)
    fusion = summary.node_diagnostics.get('fusion_node: status', {})
    return {'particles': particles, 'posteriors': FilterConfig().n_posteriors,
            'duration_s': duration_s,
            'layout': layout, 'camera': camera, 'topics': topics,
            'acquisition_particles': acquisition_particles,
            'speed_x_real_time': summary.speed, 'replay_wall_s': summary.wall_s,
            'total_wall_s_with_startup': total_s,
            'gnss_epochs': summary.gnss_epochs,
            'gnss_epochs_processed': summary.gnss_epochs_processed,
            'dropped_gnss_epochs': summary.dropped_gnss_epochs,
            'fusion_dropped_epochs': _int(fusion.get('dropped_epochs', 0)),
            'fusion_processing_p50_ms': _float(fusion.get('processing_p50_ms')),
            'camera_dropped_frames': _int(summary.node_diagnostics.get(
                'camera_node: status', {}).get('dropped_frames', 0)),
            'unacknowledged': summary.unacknowledged, 'cpu_s': summary.cpu_s,
            'recorded': record.counts if record is not None else None,
            'load_average': os.getloadavg(), 'cpus': os.cpu_count(),
            'replay': summary.as_dict()}


def _int(value) -> int:
    try:
        return int(float(value))
    except (TypeError, ValueError):
        return 0


def _float(value) -> float | None:
    try:
        return float(value)
    except (TypeError, ValueError):
        return None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m gnsscam_ros.bench.replay',
                                     description=__doc__.split('\n')[0])
    parser.add_argument('--particles', type=int, nargs='+', default=[10_000],
                        help='particles per posterior (default %(default)s)')
    parser.add_argument('--duration', type=float, default=120.0,
                        help='drive length [s] (default %(default)s)')
    parser.add_argument('--seed', type=int, default=3)
    parser.add_argument('--layout', choices=LAYOUTS, nargs='+', default=['processes'])
    parser.add_argument('--acquisition-particles', type=int, nargs='+', default=[None],
                        help='acquisition_particles values (default: the filter '
                        'default)')
    parser.add_argument('--camera', action='store_true', help='include the camera')
    parser.add_argument('--topics', nargs='+', help='replay only these topics')
    parser.add_argument('--json', type=Path, help='write the results as JSON')
    args = parser.parse_args(argv)
    if args.json is not None and args.json.exists():
        print(f'replay_bench: {args.json} exists; not overwriting', file=sys.stderr)
        return 2
    results = []
    for layout in args.layout:
        for n in args.particles:
            for acquisition in args.acquisition_particles:
                r = bench_once(n, args.duration, args.seed, layout, acquisition, args.camera,
                               args.topics, log=lambda m: print(m, file=sys.stderr))
                results.append(r)
                print(json.dumps({k: v for k, v in r.items() if k != 'replay'}),
                      file=sys.stderr)
    rows = [[r['layout'], r['particles'],
             'default' if r['acquisition_particles'] is None else r['acquisition_particles'],
             r['duration_s'], r['speed_x_real_time'], r['gnss_epochs'],
             r['dropped_gnss_epochs'], r['fusion_dropped_epochs'],
             r['fusion_processing_p50_ms'],
             ' '.join(f'{k} {v:.1f}' for k, v in r['cpu_s'].items())] for r in results]
    print(format_table(['layout', 'N', 'acq. particles', 'bag [s]', 'x real time',
                        'GNSS epochs', 'dropped', 'fusion dropped', 'epoch p50 [ms]',
                        'CPU [s]'], rows))
    if args.json is not None:
        write_json_atomic(args.json, results)
    return 0


if __name__ == '__main__':
    sys.exit(main())
