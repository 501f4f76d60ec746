"""The main job (``./run demo``): datasets -> bags -> replay through the nodes -> results.

For the emulated urban drive (camera included) and, when the data folder is there, the
real smartLoc run (no camera), in one command and without a ROS install:

1. the dataset is generated (emulated: seeded, a ``--duration-s`` cut of the drive with
   its rendered camera) or loaded (smartLoc: a ``--smartloc-duration-s`` cut) and
   converted into a rosbag2 bag (``bags.convert_drive``);
2. emulated: the map database of the drive's route is built (or loaded from the cache:
   the first build renders a few thousand database views, about a minute or two on two
   cores; later runs load it in a second) and saved next to the bag for camera_node;
3. the bag is replayed at ``R = 0`` (as fast as the nodes keep up, lossless;
   ``live.replay``) into gnss_node, imu_node, camera_node and fusion_node, each in its own
   process, and their outputs are recorded into a result bag (``live.record``);
4. ``gnsscam_eval bag`` metrics are computed from the result bag
   (``evaluation.bag_eval``), next to the offline evaluation of the same drive with the
   same seed and configuration (:func:`offline_run`: the filter core run over the bag's
   data with the nodes' dead reckoning and camera handling, no ROS graph) and the snapshot
   WLS baseline; the largest difference between the nodes' and the offline estimates
   shows that the replay path changes nothing;
5. figures (trajectory; risk bound against the reference risk; for the nodes and the
   offline run each a Stanford diagram and the error with the protection level over
   time, the nodes' PL taken from the recorded ``integrity_risk``) go next to the JSON.

Everything lands in a new folder ``<out>/demo-<UTC time>/`` (a suffix is added if it
exists: nothing is ever overwritten). The time of every stage and the replay speed (x real
time) are printed. The bags (the dataset's and the recorded one: ~1.3 GB for the emulated
drive with its images) are intermediate: they are removed once their results are written,
unless ``--keep-bags``; the end says what the folder keeps and its size.

A run that does not finish (Ctrl-C, an error) leaves the file ``INCOMPLETE`` in its folder,
saying where it stopped; it is removed only when ``summary.json`` is written. Ctrl-C stops
the demo at once with exit status 130 (the replay does not go on as if its truncated run
were a result).
"""
from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from ..bags.convert import convert_drive
from ..bags.read import read_drive, read_results
from ..core.filter import FilterConfig
from ..core.frames import LocalFrame
from ..core.fusion import CameraMeasurement
from ..core.interrupts import interrupts_redelivered
from ..core.motion import DeadReckoningConfig
from ..core.types import Drive
from ..core.warmup import warm_up_kernels
from ..datasets.cut import cut_drive
from ..datasets.emulated.camera import with_camera
from ..datasets.emulated.drive import make_emulated_drive
from ..datasets.emulated.map_database import build_emulated_map_database
from ..datasets.emulated.scenario import scenario_of
from ..datasets.emulated.views import route_range_of
from ..datasets.errors import DatasetError
from ..datasets.smartloc import discover_files, load_smartloc
from ..io.atomic import atomic_output, write_json_atomic
from ..io.provenance import provenance
from ..io.tables import format_table
from ..live.replay import replay_through_nodes, use_dds_profile
from ..nodes.camera_node import DEFAULTS as CAMERA_DEFAULTS
from .bag_eval import evaluate_result_bag_epochs
from .cli import DEFAULT_SEED
from .filter_options import add_n_particles
from .interrupts import EXIT_INTERRUPTED, is_interrupt
from .plots import dataset_title, integrity_plots, risk_plot, trajectory_plot
from .report import protection_level_headers, protection_level_rows, stanford_line
from .runner import (RunRecord, accuracy, offline_camera_matches, run_epochs,
                     run_snapshot_baseline, summarize, truth_at)

#: Alert limit of the comparison [m]: the nodes publish the risk at one alert limit
#: (fusion_node ``alert_limit_m``; extra limits are not a node parameter).
ALERT_LIMIT_M = 8.0
EMULATED_SEED, EMULATED_FAULTS, EMULATED_BIAS_M = 3, 6, 100.0
#: What the reference risk of the figures is. The failure ratio (bound below the
#: reference) depends on it: the offline run has its M posteriors (with their bias
#: hypotheses), the nodes' row of the table only what the result bag holds (the particle
#: cloud of ``particles``, else the pose covariance), so the two ratios differ for
#: identical estimates.
OFFLINE_REFERENCE = "reference risk: offline run's M posteriors around the truth"
FAILURE_RATIO_NOTE = ('fail ratio: epochs whose risk bound is below the reference risk '
                      '(posterior mass beyond the AL around the truth). nodes: reference '
                      'from the result bag (particle cloud, else pose covariance); offline: '
                      'from the M posteriors, as in the risk figure. Two references, so two '
                      'ratios for the same estimates.')
#: Marker file of a run folder whose run has not finished.
INCOMPLETE = 'INCOMPLETE'


# ============================================================================ helpers


def offline_run(drive: Drive, config: FilterConfig, seed: int,
                camera_matches: list[CameraMeasurement] | None = None,
                dr_config: DeadReckoningConfig | None = None) -> tuple[RunRecord, LocalFrame]:
    """The offline evaluation run of a drive: the filter core over the drive's epochs
    through the same :class:`~gnsscam_ros.core.engine.EpochEngine` as fusion_node, with
    imu_node's dead reckoning (:func:`.runner.run_epochs`), no ROS graph.

    Args:
        drive: The data (with truth).
        config: Filter configuration (as fusion_node's parameters).
        seed: Filter seed (fusion_node ``seed``).
        camera_matches: Best match of every camera frame (:func:`offline_camera_matches`),
            None for GNSS only.
        dr_config: imu_node's dead-reckoning parameters (default: its defaults).

    Returns:
        The run record (as :func:`.runner.run_filter`) and the filter's map frame.
    """
    record, engine = run_epochs(drive, config, seed, camera_matches, dr_config=dr_config)
    return record, engine.frame


def node_series(result_bag: Path, frame: LocalFrame) -> dict:
    """Per-epoch estimates (from ``fix``, in ``frame``) and risk bounds of a result bag.

    Returns:
        ``{'stamp_ns': (E,), 'estimate_enu_m': (E, 3), 'risk_bound': (E,),
        'protection_level_m': (E,) (NaN when a verdict carries none)}`` for the epochs
        with an OK/ERROR verdict and a fix.
    """
    import pymap3d

    res = read_results(result_bag, particles=False)
    verdicts = {int(r.epoch_stamp_ns): r for r in res.integrity
                if r.level in (0, 2) and r.epoch_stamp_ns is not None
                and math.isfinite(r.risk_bound)}
    bound = {s: float(r.risk_bound) for s, r in verdicts.items()}
    ecef = np.column_stack(pymap3d.geodetic2ecef(res.fix_llh[:, 0], res.fix_llh[:, 1],
                                                 res.fix_llh[:, 2])) if len(
        res.fix_llh) else np.zeros((0, 3))
    enu = frame.ecef_to_enu(ecef) if len(ecef) else np.zeros((0, 3))
    keep = [i for i, s in enumerate(res.fix_stamp_ns) if int(s) in bound]
    stamps = res.fix_stamp_ns[keep]
    return {'stamp_ns': stamps, 'estimate_enu_m': enu[keep].reshape(-1, 3),
            'risk_bound': np.array([bound[int(s)] for s in stamps], dtype=float),
            'protection_level_m': np.array(
                [math.nan if verdicts[int(s)].protection_level_m is None
                 else float(verdicts[int(s)].protection_level_m) for s in stamps],
                dtype=float)}


def new_run_folder(root: Path) -> Path:
    """``root/demo-<UTC time>``, with a suffix when it exists (never reused)."""
    base = root / time.strftime('demo-%Y%m%d-%H%M%S', time.gmtime())
    path, k = base, 1
    while True:
        try:
            path.mkdir(parents=True, exist_ok=False)
            return path
        except FileExistsError:
            k += 1
            path = base.with_name(f'{base.name}-{k}')


class Stages:
    """Wall time of each stage, printed as it ends."""

    def __init__(self):
        self.start = time.monotonic()
        self.times: dict[str, float] = {}
        self.started: list[str] = []         # in order, the one running last

    def run(self, name: str, fn, *args, **kwargs):
        t0 = time.monotonic()
        self.started.append(name)
        print(f'[demo] {name} ...', file=sys.stderr, flush=True)
        out = fn(*args, **kwargs)
        self.times[name] = time.monotonic() - t0
        print(f'[demo] {name}: {self.times[name]:.1f} s', file=sys.stderr, flush=True)
        return out

    @property
    def total_s(self) -> float:
        return time.monotonic() - self.start


# ============================================================================ one dataset
def run_dataset(key: str, drive: Drive, folder: Path, config: FilterConfig, seed: int,
                stages: Stages, layout: str = 'processes', database=None,
                keep_bags: bool = False) -> dict:
    """Convert, replay through the nodes, record, evaluate and plot one drive.

    Args:
        key: Short name (``emulated``, ``smartloc``): prefix of the stage names.
        drive: The data (``drive.camera`` set for the camera path).
        folder: Output folder of this dataset (created).
        config: Filter configuration of both the nodes and the offline run.
        seed: Filter seed of both.
        stages: Stage timer.
        layout: Where the nodes run (``live.replay.LAYOUTS``).
        database: Map database for the camera (None: GNSS only).
        keep_bags: Keep the dataset bag, the result bag and the map database file (else
            removed once the results are written).

    Returns:
        The dataset's results (metrics of the nodes, the offline run and WLS; replay and
        record summaries; paths).
    """
    folder.mkdir(parents=True, exist_ok=True)
    bag, result_bag = folder / 'dataset_bag', folder / 'result_bag'
    conversion = stages.run(f'{key}: convert to {bag}', convert_drive, drive, bag)
    print(f'[demo] {key}: {conversion.messages} messages, {conversion.duration_s:.0f} s, '
          f'{conversion.bag_bytes / 1e6:.0f} MB', file=sys.stderr)
    data = read_drive(bag)              # what the nodes receive (float32 fields included)
    params = {'fusion_node': {**config.as_parameters(), 'seed': int(seed)}}
    if data.origin_llh is not None:
        params['fusion_node'].update(use_map_origin=True,
                                     map_origin_llh=[float(v) for v in data.origin_llh])
    topics = None
    if database is not None:
        db_path = folder / 'map_database.npz'
        stages.run(f'{key}: save the map database', database.save, db_path)
        params['camera_node'] = {'database_path': str(db_path)}
    elif data.camera is not None:
        topics = [t for t in ('dataset/info', 'map/origin', 'gnss/pseudoranges', 'imu/data',
                              'odom/twist', 'ground_truth/pose')]
    replay, record = stages.run(
        f'{key}: replay through the nodes ({layout}) -> {result_bag}', replay_through_nodes,
        bag, result_bag, rate=0.0, parameters=params, layout=layout, topics=topics,
        log_dir=folder / 'logs')
    print(f'[demo] {key}: {replay.text()}', file=sys.stderr)
    if replay.interrupted:
        # A truncated replay is not a result: stop here rather than evaluate it.
        raise KeyboardInterrupt
    nodes, node_epochs = stages.run(f'{key}: gnsscam_eval bag', evaluate_result_bag_epochs,
                                    result_bag, bag)
    matches = None
    if database is not None and data.camera is not None:
        matches = stages.run(f'{key}: offline camera matching', offline_camera_matches,
                             data.camera, database, CAMERA_DEFAULTS['top_k'])
    record_off, frame = stages.run(f'{key}: offline run (same drive, seed, config)',
                                   offline_run, data, config, seed, matches)
    offline = summarize(record_off, config)
    # Baseline in the offline run's frame (WLS needs no seed: it is the same for both).
    stamps_wls, fixes = run_snapshot_baseline(data, frame, config.measurement_var_m2)
    wls = accuracy(fixes, truth_at(data, frame, stamps_wls))
    series = node_series(result_bag, frame)
    title = dataset_title(drive.name)
    index = {int(s): i for i, s in enumerate(record_off.stamp_ns)}
    common = [(i, index[int(s)]) for i, s in enumerate(series['stamp_ns']) if int(s) in index]
    diff = (np.abs(series['estimate_enu_m'][[i for i, _ in common]]
                   - record_off.estimate_enu_m[[j for _, j in common]]).max()
            if common else math.nan)
    # Figures: truth and both estimates at the common epochs; the nodes' bound against
    # the reference risk (posterior mass beyond the alert limit around the truth).
    paths = []
    if common:
        j = np.array([j for _, j in common])
        i = np.array([i for i, _ in common])
        t_s = (record_off.stamp_ns[j] - record_off.stamp_ns[j[0]]) * 1e-9
        paths.append(trajectory_plot(
            folder / 'trajectory.png', f'{title}: replay through the nodes vs offline',
            record_off.truth_enu_m[j], {'nodes (replayed bag)': series['estimate_enu_m'][i],
                                        'offline': record_off.estimate_enu_m[j]},
            config.alert_limit_m))
        paths.append(risk_plot(
            folder / f'risk_al{ALERT_LIMIT_M:g}m.png',
            f'{title}: risk bound of the nodes vs the offline reference risk', t_s,
            series['risk_bound'][i], record_off.reference_risk[j, 0], ALERT_LIMIT_M,
            config.target_risk, reference_label=OFFLINE_REFERENCE))
    # Stanford diagram and error/PL timeline of both runs (nodes: the PL of the recorded
    # integrity_risk; every GNSS epoch, STALE ones without a PL).
    for label, table in (('nodes', node_epochs), ('offline', record_off.epochs)):
        paths += integrity_plots(folder, label, f'{title}: {label}', table.stamp_ns,
                                 table.horizontal_error_m, table.protection_level_m,
                                 table.integrity, config.alert_limit_m)
    result = {'dataset': drive.name, 'nodes': nodes, 'offline': offline, 'wls': wls,
              'max_estimate_difference_m': float(diff), 'common_epochs': len(common),
              'replay': replay.as_dict(),
              'record': record.as_dict() if record is not None else None,
              'camera_matches_offline': None if matches is None else len(matches),
              'bags': {'dataset': str(bag), 'result': str(result_bag)},
              'plots': [str(p) for p in paths], 'seed': seed,
              'config': config.as_flat()}
    result['bags']['kept'] = keep_bags
    write_json_atomic(folder / 'results.json', result)
    if not keep_bags:
        # The nodes' inputs and outputs; the map database is a copy of the cached one.
        for path in (bag, result_bag):
            shutil.rmtree(path, ignore_errors=True)
        (folder / 'map_database.npz').unlink(missing_ok=True)
    return result


def _rows(key: str, result: dict) -> list[list]:
    """Table rows: nodes, offline, WLS of one dataset."""
    limit = f'{ALERT_LIMIT_M:g}'
    rows = []
    for label, m in (('nodes (replayed bag)', result['nodes']),
                     ('offline (same seed)', result['offline'])):
        integ = m['integrity'][limit]
        pl = m['protection_level']
        flag = pl.get('flag_ok') or {}
        rows.append([key, label, m['epochs'], m['rmse_2d_m'], m['rmse_3d_m'],
                     integ['p_fa'], integ['p_mi'], integ['failure_ratio'],
                     integ['mean_risk_bound'], pl['mi_rate'], pl['median_m'],
                     pl['availability'][limit],
                     f"{flag.get('error_above_al_epochs')}/{flag.get('ok_epochs')}"])
    w = result['wls']
    rows.append([key, 'snapshot WLS', w['epochs'], w['rmse_2d_m'], w['rmse_3d_m']]
                + [None] * 8)
    return rows


# ============================================================================ main
def build_parser() -> argparse.ArgumentParser:
    """The demo's command line."""
    parser = argparse.ArgumentParser(prog='gnsscam demo', description=__doc__.split('\n')[0])
    parser.add_argument('--shared', type=Path, default=Path('../shared'),
                        help='folder holding data/smartloc (default %(default)s)')
    parser.add_argument('--out', type=Path, default=Path('out'),
                        help='results root; each run writes a new sub-folder')
    parser.add_argument('--seed', type=int, default=DEFAULT_SEED,
                        help='filter seed (default %(default)s, as gnsscam_eval)')
    add_n_particles(parser, FilterConfig().n_particles, 'default %(default)s')
    parser.add_argument('--duration-s', type=float, default=150.0,
                        help='emulated drive length [s] (default %(default)s; the whole '
                        'drive is ~424 s: --full)')
    parser.add_argument('--full', action='store_true', help='the whole emulated drive')
    parser.add_argument('--smartloc-duration-s', type=float, default=120.0,
                        help='smartLoc cut [s]; 0 = the whole run (~275 s) '
                        '(default %(default)s)')
    parser.add_argument('--no-camera', action='store_true', help='emulated drive: GNSS only')
    parser.add_argument('--no-smartloc', action='store_true', help='skip the smartLoc data')
    parser.add_argument('--layout', default='processes',
                        choices=('processes', 'threads', 'pipeline'),
                        help='where the nodes run (default %(default)s)')
    parser.add_argument('--keep-bags', action='store_true',
                        help='keep the dataset and result bags and the map database the '
                        'nodes read (about 1.4 GB with the camera images; by default removed '
                        'once evaluated)')
    parser.add_argument('--cache', type=Path,
                        default=Path(os.environ.get('GNSSCAM_CACHE_DIR', '.cache/gnsscam')),
                        help='map database cache (default %(default)s)')
    return parser


def main(argv: list[str] | None = None) -> int:
    """The demo; its exit status (0 done, 130 stopped by Ctrl-C)."""
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser().parse_args(argv)
    # ``./run demo ARGS`` runs this module with --shared and --out added: the line says so.
    args.provenance = provenance('python -m gnsscam_ros.evaluation.demo', argv)
    stages = Stages()
    out_dir = new_run_folder(args.out)
    marker = out_dir / INCOMPLETE
    with atomic_output(marker) as handle:
        handle.write(f'{INCOMPLETE}: this demo run has not finished; its results are not '
                     'complete (the file goes when summary.json is written).\n')
    print(f'[demo] writing into {out_dir}', file=sys.stderr)
    try:
        with interrupts_redelivered():      # a Ctrl-C while numba compiles is not lost
            run_demo(args, out_dir, stages)
    except (KeyboardInterrupt, SystemError) as err:
        # A Ctrl-C inside a compiled kernel is a SystemError (evaluation.interrupts).
        if not is_interrupt(err):
            raise
        stage = next(reversed(stages.started), 'the start')
        if not args.keep_bags:
            # An interrupted run keeps no bag, finished or partial (as a finished run
            # without --keep-bags): nothing of it is a result.
            for path in list(out_dir.rglob('dataset_bag')) + list(out_dir.rglob('result_bag')):
                shutil.rmtree(path, ignore_errors=True)
        with atomic_output(marker, force=True) as handle:
            handle.write(f'{INCOMPLETE}: interrupted (Ctrl-C) during "{stage}"; the results '
                         'here are not complete.\n')
        print(f'\n[demo] interrupted during "{stage}": {out_dir} is incomplete (see its '
              f'{INCOMPLETE} file)', file=sys.stderr)
        return EXIT_INTERRUPTED
    marker.unlink()
    return 0


def _map_database(args: argparse.Namespace, drive: Drive, stages: Stages):
    """The map database of the emulated route, from the cache or built (with progress)."""
    scenario = scenario_of(drive)
    built: dict[str, int] = {}

    def progress(stage: str, done: int, total: int) -> None:
        # Called only while building (a cache hit is silent); one line per tenth.
        tenth = 10 * done // max(total, 1)
        if tenth > built.get(stage, -1):
            print(f'[demo]   {stage}: {done}/{total}', file=sys.stderr, flush=True)
            built[stage] = tenth

    database = stages.run('emulated: map database of the route (from the cache, or '
                          f'rendered and built once into {args.cache})',
                          build_emulated_map_database, scenario, cache_dir=args.cache,
                          route_range_m=route_range_of(scenario, drive), progress=progress)
    print('[demo] emulated: map database ' + ('built and cached for later runs' if built
                                              else f'loaded from the cache {args.cache}')
          + f' ({len(database)} images)', file=sys.stderr)
    return database


def run_demo(args: argparse.Namespace, out_dir: Path, stages: Stages) -> None:
    """Both datasets into ``out_dir``, the summary printed and written."""
    config = FilterConfig(n_particles=args.n_particles, alert_limit_m=ALERT_LIMIT_M)
    use_dds_profile(out_dir)            # before the first ROS participant of this process
    results: dict[str, dict] = {}
    # Compiled once here, in view, rather than inside the nodes' start-up during the
    # replay (numba caches the machine code on disk for every later process).
    stages.run('compile the filter kernels (numba; the first run only, cached after)',
               warm_up_kernels)

    # ---- emulated urban drive, camera included
    duration = None if args.full else args.duration_s
    drive = stages.run('emulated: generate the drive', make_emulated_drive, EMULATED_SEED,
                       faults=EMULATED_FAULTS, bias_m=EMULATED_BIAS_M, duration_s=duration)
    database = None
    if not args.no_camera:
        drive = with_camera(drive)
        database = _map_database(args, drive, stages)
    results['emulated'] = run_dataset('emulated', drive, out_dir / 'emulated', config,
                                      args.seed, stages, args.layout, database,
                                      args.keep_bags)

    # ---- smartLoc (real data), no camera
    smartloc_dir = args.shared / 'data' / 'smartloc'
    if args.no_smartloc:
        pass
    elif smartloc_dir.is_dir():
        try:
            real = cut_drive(load_smartloc(*discover_files(smartloc_dir)),
                             args.smartloc_duration_s)
            results['smartloc'] = run_dataset('smartloc', real, out_dir / 'smartloc', config,
                                              args.seed, stages, args.layout,
                                              keep_bags=args.keep_bags)
        except DatasetError as err:
            print(f'[demo] skipping smartLoc: {err}', file=sys.stderr)
    else:
        print(f'[demo] {smartloc_dir} not found: emulated drive only', file=sys.stderr)

    # ---- summary
    rows = [row for key, r in results.items() for row in _rows(key, r)]
    print()
    print(f'Results at alert limit {ALERT_LIMIT_M:g} m, target risk {config.target_risk:g}, '
          f'N = {config.n_particles} x M = {config.n_posteriors}, seed {args.seed}:')
    print(format_table(['data', 'run', 'epochs', 'RMSE 2D [m]', 'RMSE 3D [m]', 'P_FA', 'P_MI',
                        'fail ratio', 'mean bound', 'MI rate', 'PL p50 [m]',
                        f'avail {ALERT_LIMIT_M:g} m', f'err>{ALERT_LIMIT_M:g}|OK'], rows))
    print('(MI: error > protection level; avail: PL <= alert limit; err>AL|OK: epochs the '
          'flag said OK with the error above the alert limit / epochs OK)')
    print(f'({FAILURE_RATIO_NOTE})')
    # Availability at every alert limit the evaluation reports: where the PLs sit decides
    # which limits a dataset supports (smartLoc's urban PLs exceed 8 m most of the time).
    first = next(iter(results.values()))['nodes']['protection_level']
    print('\nProtection level by alert limit (avail: share of epochs with PL <= AL):')
    print(format_table(protection_level_headers(first), [
        protection_level_rows(f'{key} {label}', r[label]['protection_level'])[0]
        for key, r in results.items() for label in ('nodes', 'offline')]))
    for key, r in results.items():
        for label in ('nodes', 'offline'):
            print(f'{key} {label}: {stanford_line(r[label]["protection_level"])}')
    print()
    for key, r in results.items():
        rep = r['replay']
        done = ('none acknowledged' if rep['gnss_epochs_processed'] is None else
                f'{rep["gnss_epochs_processed"]} processed, dropped {rep["dropped_gnss_epochs"]}')
        print(f'{key}: replay {rep["bag_span_s"]:.0f} s of data in {rep["wall_s"]:.1f} s = '
              f'{rep["speed_x_real_time"]:.1f}x real time; GNSS epochs {rep["gnss_epochs"]} '
              f'published, {done}; nodes vs offline estimates differ by at most '
              f'{r["max_estimate_difference_m"]:.2g} m over {r["common_epochs"]} epochs')
    summary = {'command': 'demo', **getattr(args, 'provenance', {}),
               'results': results, 'stages_s': stages.times, 'total_s': stages.total_s,
               'out_dir': str(out_dir)}
    path = write_json_atomic(out_dir / 'summary.json', summary)
    kept = sorted(f for f in out_dir.rglob('*') if f.is_file() and f.name != INCOMPLETE)
    size_mb = sum(f.stat().st_size for f in kept) / 1e6
    bags = ('dataset and result bags kept (--keep-bags)' if args.keep_bags
            else 'bags removed; --keep-bags keeps them')
    print(f'\nOutputs in {out_dir}: {len(kept)} files, {size_mb:.0f} MB ({bags}): '
          f'results.json, trajectory.png, risk_al{ALERT_LIMIT_M:g}m.png, '
          'stanford_nodes/offline.png and error_pl_nodes/offline.png per dataset, logs; '
          f'{path.name}.')
    print('Stage times: ' + ', '.join(f'{k.split(" (")[0].split(" ->")[0]} {v:.0f} s'
                                      for k, v in stages.times.items()))
    print(f'Total wall time: {stages.total_s:.0f} s')


if __name__ == '__main__':
    sys.exit(main())
