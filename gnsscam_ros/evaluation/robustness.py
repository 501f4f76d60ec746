"""Robustness of the filter to how a drive is presented: one drive, a matrix of data
variations ("cells"), several filter seeds each, one configuration for all
(``gnsscam_eval robustness``).

The default matrix (:data:`DEFAULT_CELLS`; ``gnsscam_eval robustness --list-cells``):

============== ==========================================================================
cell           the data, changed only in (:mod:`gnsscam_ros.datasets.variants`)
============== ==========================================================================
baseline       nothing
var_x0.25 ...  every stated pseudorange variance times 0.25, 0.5, 2, 4
var_25m2/4m2   every stated variance set to 25 m^2 / 4 m^2 (a receiver that reports one
               sigma for every satellite)
gnss_1hz ...   GNSS epochs decimated to 1, 2, 5 Hz (odometry at its own rate); on a 5 Hz
               file the 5 Hz cell is the file as it is
gps_only       GPS satellites only; epochs with fewer than 5 of them dropped
glonass_only   GLONASS satellites only; epochs with fewer than 5 of them dropped (4
               unknowns plus one redundant range; the count of epochs kept is reported)
start_0s ...   the drive joined 0, 60, 120 s after its first epoch (GNSS and odometry
               before dropped; the truth, used for scoring only, kept)
fault_step     injected faults (:mod:`gnsscam_ros.datasets.faults`): one episode per
               :data:`FAULT_SPACING_S` of drive (at least one) at seeded uniform times,
               1-2 satellites in view, a bias of 30-100 m (random sign) for 20-60 s each
fault_ramp     the same episodes (same seed: same satellites and times) as ramps growing
               linearly from 0 to the bias over the episode
============== ==========================================================================

Extra cells (:data:`EXTRA_CELLS`, run only when named with ``--cells``; the issue's
matrix is the default one):

============== ==========================================================================
cn0_-8db ...   every C/N0 8 dB-Hz lower or higher: the same signals as another receiver
               (antenna, front end, C/N0 estimator) reports them
cn0_unknown    no C/N0 at all (a receiver or format that does not report it)
troposphere    the tropospheric delay left in the pseudoranges (a preprocessing that did
               not remove it; a standard atmosphere at the drive's start,
               :func:`gnsscam_ros.datasets.variants.leave_troposphere`)
============== ==========================================================================

A cell's drive is made in this order: the start cut, then ``duration_s`` (quick runs: the
first seconds after the start), then the cell's variation (faults are drawn over what
is left, with the fault seed, the same for every filter seed: the filter seeds measure
the filter on one set of data). Cells whose data come out identical (start 0 s and the
baseline; 5 Hz on a 5 Hz file) are run once and share their runs (``same_data_as``).

Every run is ``gnsscam_eval smartloc``'s (:func:`.evaluate.evaluate_drive_record`: the
filter in the tree, its default configuration, and the robust snapshot WLS on the same
data). Per cell (definitions in :mod:`.metrics`; errors measured like the PL,
horizontal by default):

* ``mi_rate``: MI epochs (error > PL) / updated epochs pooled over the seeds (``mean``),
  with the between-seed 95 % interval (:func:`.intervals.between_seed_interval`;
  ``upper`` its upper bound);
* ``rmse_2d_m``: mean over seeds with Student's t interval; ``rmse_ratio_to_wls`` its
  ratio to the WLS 2D RMSE of the cell;
* ``protection_level``: median and p95 over every seed's epochs (inf counts as inf);
  ``median_error_m``; ``pl_to_error_ratio`` = median PL / median error;
* ``cloud_calibration``: the NEES of every seed's epochs pooled (:func:`.metrics.
  cloud_calibration`): ``spread_to_error`` says how much of ``pl_to_error_ratio`` is the
  reported spread being wider than the errors (1: calibrated) rather than the bound's
  margin over it;
* ``recoveries``: the runs' ``recoveries`` (the evaluation JSON's key: epochs at which
  the filter recovered, ``runner.RunRecord.recoveries``), summed; 0 with ``reported:
  false`` when the evaluation does not report it;
* ``targets``: mean MI <= 0.10, its upper bound <= 0.15, RMSE <= 0.5 x WLS, median PL
  <= 3 x median error (:data:`TARGETS`); ``pass`` when all hold.
"""
from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from ..core.filter import FilterConfig
from ..core.frames import LocalFrame
from ..core.types import GLONASS, GPS, Drive
from ..datasets.cut import cut_drive
from ..datasets.errors import DatasetError
from ..datasets.faults import RAMP, STEP, FaultEpisodes, inject_pseudorange_faults
from ..datasets.variants import (decimate_gnss, drive_digest, drop_cn0, gnss_rate_hz,
                                 leave_troposphere, scale_variances, select_systems,
                                 set_variances, shift_cn0, start_after)
from .campaign_cluster import CaseRunner
from .evaluate import evaluate_drive_record
from .intervals import between_seed_interval, mean_interval
from .metrics import cloud_calibration, level_sizing, percentile_with_inf
from .runner import bound_miss_share, run_nees

#: Satellites a single-system cell needs in an epoch (4 unknowns and one redundant range).
SINGLE_SYSTEM_MIN_SATELLITES = 5
#: Drive seconds per injected fault episode (at least one episode per cell).
FAULT_SPACING_S = 90.0
#: How the injected faults are drawn (the number of episodes follows the drive's length).
FAULT_SATELLITES = (1, 2)
FAULT_BIAS_M = (30.0, 100.0)
FAULT_DURATION_S = (20.0, 60.0)
#: Filter seeds per cell by default.
DEFAULT_SEEDS = 10
#: Seed of the injected faults by default.
DEFAULT_FAULT_SEED = 1

#: The targets every cell is held to (issue: robustness matrix): name -> (what, limit).
TARGETS = {
    'mi_mean': ('mean MI rate', 0.10),
    'mi_upper': ('between-seed 95 % upper bound of the MI rate', 0.15),
    'rmse_ratio_to_wls': ('2D RMSE / robust WLS 2D RMSE', 0.5),
    'pl_to_error_ratio': ('median PL / median error', 3.0),
}


@dataclass(frozen=True)
class Cell:
    """One variation of the data.

    Attributes:
        name: Cell name (``--cells``).
        kind: ``'none'``, ``'scale_variances'``, ``'set_variances'``, ``'decimate'``,
            ``'systems'``, ``'start'``, ``'faults'``, ``'shift_cn0'`` or ``'drop_cn0'``.
        value: Its parameter: factor, variance [m^2], rate [Hz], systems, start [s], the
            fault profile (``'step'``, ``'ramp'``) or the C/N0 offset [dB-Hz].
        description: One line for tables and the JSON.
    """

    name: str
    kind: str
    value: object
    description: str


DEFAULT_CELLS: tuple[Cell, ...] = (
    Cell('baseline', 'none', None, 'the file as it is'),
    *(Cell(f'var_x{f:g}', 'scale_variances', f, f'stated variances x {f:g}')
      for f in (0.25, 0.5, 2.0, 4.0)),
    *(Cell(f'var_{v:g}m2', 'set_variances', v, f'every stated variance {v:g} m^2')
      for v in (25.0, 4.0)),
    *(Cell(f'gnss_{r:g}hz', 'decimate', r, f'GNSS decimated to {r:g} Hz, odometry kept')
      for r in (1.0, 2.0, 5.0)),
    Cell('gps_only', 'systems', (GPS,),
         f'GPS only, epochs with >= {SINGLE_SYSTEM_MIN_SATELLITES} satellites'),
    Cell('glonass_only', 'systems', (GLONASS,),
         f'GLONASS only, epochs with >= {SINGLE_SYSTEM_MIN_SATELLITES} satellites'),
    *(Cell(f'start_{s:g}s', 'start', s, f'joined {s:g} s into the drive')
      for s in (0.0, 60.0, 120.0)),
    Cell('fault_step', 'faults', STEP,
         f'{FAULT_BIAS_M[0]:g}-{FAULT_BIAS_M[1]:g} m step bias on 1-2 satellites for '
         f'{FAULT_DURATION_S[0]:g}-{FAULT_DURATION_S[1]:g} s, one per '
         f'{FAULT_SPACING_S:g} s'),
    Cell('fault_ramp', 'faults', RAMP,
         f'the same episodes as ramps from 0 to {FAULT_BIAS_M[0]:g}-{FAULT_BIAS_M[1]:g} m'),
)
#: Cells outside the default matrix, run when named (``--cells``).
EXTRA_CELLS: tuple[Cell, ...] = (
    *(Cell(f'cn0_{d:+g}db', 'shift_cn0', d, f'every C/N0 {d:+g} dB-Hz (another receiver)')
      for d in (-8.0, 8.0)),
    Cell('cn0_unknown', 'drop_cn0', None, 'no C/N0 reported'),
    Cell('troposphere', 'troposphere', None, 'tropospheric delay left in the pseudoranges'),
)
CELLS_BY_NAME = {c.name: c for c in (*DEFAULT_CELLS, *EXTRA_CELLS)}


class RobustnessError(ValueError):
    """A cell or seed specification that cannot be run."""


def select_cells(names=None) -> list[Cell]:
    """The cells named (in the matrix's order, the extra cells after it), or the default
    matrix for None.

    Raises:
        RobustnessError: An unknown name.
    """
    if not names:
        return list(DEFAULT_CELLS)
    unknown = [n for n in names if n not in CELLS_BY_NAME]
    if unknown:
        raise RobustnessError(f'unknown cell {unknown[0]!r}; cells: '
                              + ', '.join(CELLS_BY_NAME))
    wanted = set(names)
    return [c for c in (*DEFAULT_CELLS, *EXTRA_CELLS) if c.name in wanted]


def fault_episodes(drive: Drive, profile: str) -> FaultEpisodes:
    """The fault draw of a fault cell: one episode per :data:`FAULT_SPACING_S` of the
    drive's GNSS span (rounded, at least one)."""
    span_s = ((drive.gnss[-1].stamp_ns - drive.gnss[0].stamp_ns) * 1e-9
              if drive.gnss else 0.0)
    return FaultEpisodes(episodes=max(1, int(round(span_s / FAULT_SPACING_S))),
                         satellites=FAULT_SATELLITES, bias_m=FAULT_BIAS_M,
                         duration_s=FAULT_DURATION_S, profile=profile)


def cell_drive(drive: Drive, cell: Cell, duration_s: float | None = None,
               fault_seed: int = DEFAULT_FAULT_SEED) -> Drive:
    """The data of one cell (module docstring: start cut, ``duration_s``, variation).

    Raises:
        DatasetError: The variation leaves no GNSS epoch.
    """
    if cell.kind == 'start':
        drive = start_after(drive, cell.value)
    drive = cut_drive(drive, duration_s)
    if cell.kind == 'scale_variances':
        return scale_variances(drive, cell.value)
    if cell.kind == 'set_variances':
        return set_variances(drive, cell.value)
    if cell.kind == 'decimate':
        return decimate_gnss(drive, cell.value)
    if cell.kind == 'systems':
        return select_systems(drive, cell.value, SINGLE_SYSTEM_MIN_SATELLITES)
    if cell.kind == 'faults':
        return inject_pseudorange_faults(drive, fault_seed, fault_episodes(drive, cell.value))
    if cell.kind == 'shift_cn0':
        return shift_cn0(drive, cell.value)
    if cell.kind == 'drop_cn0':
        return drop_cn0(drive)
    if cell.kind == 'troposphere':
        lat_deg, _, height_m = _receiver_llh(drive)
        return leave_troposphere(drive, lat_deg, height_m)
    if cell.kind in ('none', 'start'):
        return drive
    raise ValueError(f'unknown cell kind {cell.kind!r}')


def _receiver_llh(drive: Drive) -> tuple[float, float, float]:
    """Where the receiver is, roughly (the atmosphere's place: metres do not matter): the
    drive's map origin, else its first ground-truth position (the data's preparation,
    not the filter, reads it).

    Raises:
        DatasetError: The drive has neither.
    """
    if drive.origin_llh is None and (drive.truth is None or not len(drive.truth)):
        raise DatasetError(f'{drive.name}: no map origin and no ground truth: where the '
                           'receiver is (for its atmosphere) is unknown')
    first = None if drive.origin_llh is not None else drive.truth.ecef_m[0]
    return LocalFrame.at_origin_or(drive.origin_llh, first).origin_llh


def run_seed(drive: Drive, seed: int, config: FilterConfig) -> dict:
    """One filter run of a cell: ``gnsscam_eval smartloc``'s evaluation of ``drive``.

    Returns:
        The run's figures (``mi_epochs``, ``epochs``, ``rmse_2d_m``, ``wls_rmse_2d_m``,
        ``recoveries`` (None when not reported), ``statuses``, ``filter_seconds``) and its
        per-epoch ``error_m``, ``protection_level_m`` and ``nees`` (measured like the PL;
        ``nees_dims`` its dimensions).
    """
    result, record = evaluate_drive_record(drive, config, seed=seed)
    diff = record.estimate_enu_m - record.truth_enu_m
    error = (np.hypot(diff[:, 0], diff[:, 1]) if config.horizontal_risk
             else np.linalg.norm(diff, axis=1))
    recoveries = result.get('recoveries')
    pl = result['protection_level']
    return {'seed': int(seed), 'mi_epochs': int(pl['mi_epochs']), 'epochs': int(pl['epochs']),
            'rmse_2d_m': result['rmse_2d_m'],
            'wls_rmse_2d_m': result['baseline_wls']['rmse_2d_m'],
            'wls_epochs': result['baseline_wls']['epochs'],
            'recoveries': None if recoveries is None else int(recoveries),
            'statuses': dict(result['statuses']), 'filter_seconds': result['filter_seconds'],
            'error_m': error, 'protection_level_m': np.asarray(record.protection_level_m),
            'nees': run_nees(record, config), 'nees_dims': 2 if config.horizontal_risk else 3}


def _ratio(numerator, denominator):
    if numerator is None or denominator is None or not denominator:
        return None
    return float(numerator) / float(denominator)


def _target(value, limit) -> dict:
    ok = value is not None and math.isfinite(value) and value <= limit
    return {'value': value, 'limit': limit, 'pass': bool(ok)}


def summarize_cell(runs: list[dict], miss_share: float | None = None) -> dict:
    """The figures of one cell from its runs (:func:`run_seed`), targets included; with
    ``miss_share`` (:func:`.runner.bound_miss_share`) also the level's size against its
    shape over the pooled epochs (``level_sizing``, not a target)."""
    runs = sorted(runs, key=lambda r: r['seed'])
    mi_counts = [r['mi_epochs'] for r in runs]
    mi_totals = [r['epochs'] for r in runs]
    total = sum(mi_totals)
    between = between_seed_interval(mi_counts, mi_totals)
    mi = {'mean': sum(mi_counts) / total if total else None,
          'ci95': between['ci95'] if between else None,
          'upper': between['ci95'][1] if between else None,
          'count': int(sum(mi_counts)), 'n': int(total),
          'drive_rate_mean': between['drive_rate_mean'] if between else None,
          'design_effect': between['design_effect'] if between else None}
    rmse = mean_interval([r['rmse_2d_m'] for r in runs if r['epochs']])
    wls = runs[0]['wls_rmse_2d_m'] if runs else None
    error = np.concatenate([r['error_m'] for r in runs]) if runs else np.zeros(0)
    pl = np.concatenate([r['protection_level_m'] for r in runs]) if runs else np.zeros(0)
    pl_median = percentile_with_inf(pl, 50)
    err_median = float(np.median(error)) if error.size else None
    reported = [r['recoveries'] for r in runs if r['recoveries'] is not None]
    out = {
        'seeds': [r['seed'] for r in runs], 'mi_rate': mi, 'rmse_2d_m': rmse,
        'wls_rmse_2d_m': wls,
        'rmse_ratio_to_wls': _ratio(rmse['mean'] if rmse else None, wls),
        'protection_level': {'median_m': pl_median, 'p95_m': percentile_with_inf(pl, 95)},
        'median_error_m': err_median,
        'pl_to_error_ratio': (None if pl_median is None or not err_median
                              else pl_median / err_median),
        'cloud_calibration': cloud_calibration(
            np.concatenate([r['nees'] for r in runs] or [np.zeros(0)]),
            runs[0]['nees_dims'] if runs else 2),
        'recoveries': {'total': int(sum(reported)), 'reported': bool(reported),
                       'per_run': [r['recoveries'] or 0 for r in runs]},
        'runs': [{k: v for k, v in r.items()
                  if k not in ('error_m', 'protection_level_m', 'nees', 'nees_dims')}
                 for r in runs],
    }
    if miss_share is not None:
        out['level_sizing'] = level_sizing(error, pl, miss_share)
    out['targets'] = {
        'mi_mean': _target(mi['mean'], TARGETS['mi_mean'][1]),
        'mi_upper': _target(mi['upper'], TARGETS['mi_upper'][1]),
        'rmse_ratio_to_wls': _target(out['rmse_ratio_to_wls'],
                                     TARGETS['rmse_ratio_to_wls'][1]),
        'pl_to_error_ratio': _target(out['pl_to_error_ratio'],
                                     TARGETS['pl_to_error_ratio'][1])}
    out['pass'] = all(t['pass'] for t in out['targets'].values())
    return out


def _data_info(base: Drive, drive: Drive) -> dict:
    """What a cell's data are: epochs, rate, satellites, the variations' records."""
    sats = [e.n_sv for e in drive.gnss]
    return {'name': drive.name, 'gnss_epochs': len(drive.gnss),
            'gnss_epochs_of_file': len(base.gnss), 'gnss_rate_hz': gnss_rate_hz(drive),
            'span_s': (drive.gnss[-1].stamp_ns - drive.gnss[0].stamp_ns) * 1e-9,
            'satellites_mean': float(np.mean(sats)) if sats else 0.0,
            'odometry_samples': 0 if drive.odometry is None else len(drive.odometry),
            'variants': drive.info.get('variants', []),
            'injected_faults': drive.info.get('injected_faults'),
            'faulty_measurements': drive.info.get('faulty_measurements')}


def run_robustness(drive: Drive, cells: list[Cell], seeds: list[int],
                   config: FilterConfig, duration_s: float | None = None,
                   fault_seed: int = DEFAULT_FAULT_SEED, scheduler: str | None = None,
                   workers: int | None = None, sequential: bool = False,
                   progress: bool = True) -> dict:
    """Run every cell's data under every seed (on Dask unless ``sequential``).

    Args:
        drive: The drive as loaded (with ground truth).
        cells: The cells (:func:`select_cells`).
        seeds: Filter seeds (two or more: the between-seed interval needs them).
        config: The one configuration of every run.
        duration_s: Cut each cell's drive to this many seconds after its start.
        fault_seed: Seed of the injected faults.
        scheduler, workers, sequential: Where to run (:class:`.campaign_cluster.CaseRunner`).
        progress: A progress bar on stderr.

    Returns:
        ``{'cells': [...], 'failed': [...], 'cluster', 'seconds', 'runs_computed', ...}``;
        ``failed`` lists the runs that failed (``cell``, ``seed``, ``error``) and the cells
        that could not be made (``seed`` None).

    Raises:
        RobustnessError: Fewer than two seeds, or no cell.
        DatasetError: The drive has no truth (a cell whose variation leaves no epoch is
            reported in ``failed`` and its entry's ``error``; the others run).
        campaign_cluster.ClusterError: The cluster cannot be started or reached.
    """
    seeds = list(dict.fromkeys(int(s) for s in seeds))
    if len(seeds) < 2:
        raise RobustnessError('need at least 2 filter seeds (the between-seed interval)')
    if not cells:
        raise RobustnessError('no cell to run')
    if drive.truth is None:
        raise DatasetError(f'{drive.name}: no ground truth, nothing to evaluate against')
    start = time.monotonic()
    drives, data, same_as, failed = _cell_drives(drive, cells, duration_s, fault_seed)
    tasks = [(f'{name}-s{seed}', name, (seed, config)) for name in drives for seed in seeds]
    runs: dict[str, list[dict]] = {name: [] for name in drives}
    bar = tqdm(total=len(tasks), unit='run', disable=not progress, file=sys.stderr,
               dynamic_ncols=True, desc='robustness')
    try:
        # Nothing to run (no cell has data): no cluster to start.
        with CaseRunner(scheduler if tasks else None, workers,
                        sequential or not tasks) as runner:
            ready = time.monotonic()
            bar.set_postfix_str(f"{runner.info['kind']}, {runner.info['workers']} workers")
            label_of = {label: (name, args[0]) for label, name, args in tasks}
            for label, out, error in runner.run_tasks(run_seed, tasks, drives):
                name, seed = label_of[label]
                bar.update(1)
                if error is not None:
                    failed.append({'cell': name, 'seed': seed, 'error': error})
                    bar.write(f'[robustness] {label} failed: {error}')
                    continue
                run = out['result']
                run.update(worker=out['worker'], wall_seconds=out['wall_seconds'])
                runs[name].append(run)
            cluster = dict(runner.info)
    finally:
        bar.close()
    running = time.monotonic() - ready
    cluster['startup_seconds'] = ready - start
    miss_share = bound_miss_share(config)
    summaries = [_cell_entry(cell, data, same_as, runs, miss_share) for cell in cells]
    wall = [r['wall_seconds'] for rs in runs.values() for r in rs]
    return {'cells': summaries, 'failed': failed, 'seeds': seeds,
            'fault_seed': int(fault_seed), 'duration_s': duration_s,
            'config': config.as_flat(), 'targets': {k: {'what': w, 'limit': lim}
                                                    for k, (w, lim) in TARGETS.items()},
            'cluster': cluster, 'runs_computed': len(wall),
            'run_seconds_mean': float(np.mean(wall)) if wall else None,
            'seconds': time.monotonic() - start, 'running_seconds': running,
            'cells_passed': sum(bool(c.get('pass')) for c in summaries),
            'all_pass': all(c.get('pass') for c in summaries)}


def _cell_drives(drive: Drive, cells: list[Cell], duration_s, fault_seed):
    """Every cell's data: ``(drives to run {name: drive}, data info {name: ...},
    same_as {name: earlier cell with the same data}, failed [cells without data])``."""
    drives, first_of, data, same_as, failed = {}, {}, {}, {}, []
    for cell in cells:
        try:
            made = cell_drive(drive, cell, duration_s, fault_seed)
        except DatasetError as err:      # e.g. a start after the end: this cell only
            data[cell.name] = {'error': str(err)}
            failed.append({'cell': cell.name, 'seed': None, 'error': str(err)})
            continue
        digest = drive_digest(made)
        data[cell.name] = {**_data_info(drive, made), 'digest': digest}
        if digest in first_of:
            same_as[cell.name] = first_of[digest]
        else:
            first_of[digest] = cell.name
            drives[cell.name] = made
    return drives, data, same_as, failed


def _cell_entry(cell: Cell, data: dict, same_as: dict, runs: dict,
                miss_share: float | None = None) -> dict:
    """A cell's entry of the JSON: what it is, its data, and its figures (or why none)."""
    entry = {'name': cell.name, 'description': cell.description,
             'variation': {'kind': cell.kind, 'value': _plain(cell.value)},
             'same_data_as': same_as.get(cell.name), 'data': data[cell.name]}
    mine = runs.get(same_as.get(cell.name, cell.name), [])
    if 'error' in data[cell.name]:
        entry.update(seeds=[], error=data[cell.name]['error'])
    elif mine:
        entry.update(summarize_cell(mine, miss_share))
    else:
        entry.update(seeds=[], error='every run failed')
    entry.setdefault('pass', False)
    return entry


def _plain(value):
    """A cell parameter as JSON (tuples as lists)."""
    return list(value) if isinstance(value, tuple) else value


def matrix_rows() -> list[list]:
    """``[name, kind, value, description, default]`` of every cell: the default matrix,
    then the extra cells."""
    return [[c.name, c.kind, _plain(c.value), c.description, default]
            for cells, default in ((DEFAULT_CELLS, 'yes'), (EXTRA_CELLS, 'no'))
            for c in cells]
