"""``gnsscam_eval robustness FOLDER``: the robustness matrix of one drive (the cells and
their figures: :mod:`.robustness`).

Examples::

    gnsscam_eval robustness ../shared/data/smartloc --json robustness.json \\
        --figure robustness.png
    gnsscam_eval robustness ../shared/data/smartloc --cells baseline gnss_1hz --seeds 3 \\
        --duration-s 60 --scheduler tcp://host:8786
    gnsscam_eval robustness --list-cells

Exit codes as every ``gnsscam_eval`` command: 0 done (whether or not the cells meet
their targets: the table and the JSON say), 1 some runs failed or a cell could not be
made (e.g. a start after the drive's end; the others are reported),
2 bad arguments, 3 unreadable input (folder, files) or unreachable cluster, 4 an output
that exists (without ``--force``) or cannot be written, 130 interrupted.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..datasets.errors import DatasetError
from ..datasets.smartloc import load_smartloc_args
from ..io.atomic import OutputExistsError, check_writable, write_json_atomic
from ..io.provenance import provenance as tool_provenance
from ..io.tables import format_table
from .campaign import campaign_config
from .campaign_cluster import ClusterError
from .filter_options import add_n_particles
from .interrupts import EXIT_INTERRUPTED, is_interrupt
from .robustness import (DEFAULT_CELLS, DEFAULT_FAULT_SEED, DEFAULT_SEEDS, TARGETS,
                         RobustnessError, matrix_rows, run_robustness, select_cells)

#: The exit codes of ``gnsscam_eval`` (``cli.EXIT_*``; a test keeps them equal).
EXIT_OK, EXIT_RUNS_FAILED, EXIT_USAGE, EXIT_INPUT, EXIT_OUTPUT = 0, 1, 2, 3, 4


def add_robustness_parser(sub) -> argparse.ArgumentParser:
    """Register ``robustness`` on ``gnsscam_eval``'s subcommands."""
    rob = sub.add_parser(
        'robustness', help='one drive under a matrix of data variations (stated variances '
        'scaled or constant, GNSS rate, systems, late starts, injected faults), several '
        'filter seeds each, on Dask')
    rob.add_argument('folder', type=Path, nargs='?',
                     help='folder with *_Input.txt and *_GT.txt (libRSF text format; or use '
                          '--input/--truth)')
    rob.add_argument('--input', type=Path, help='input file (pseudorange3/odom3 lines)')
    rob.add_argument('--truth', type=Path, help='ground-truth file (point3 lines)')
    grid = rob.add_argument_group('matrix')
    grid.add_argument('--cells', nargs='+', metavar='CELL',
                      help='run these cells only (default: the whole default matrix; '
                           'the extra cells run only when named; see --list-cells)')
    grid.add_argument('--list-cells', action='store_true',
                      help='print the matrix and exit')
    grid.add_argument('--seeds', type=int, default=DEFAULT_SEEDS,
                      help='filter seeds per cell, at least 2 (default %(default)s)')
    grid.add_argument('--first-seed', type=int, default=0,
                      help='seeds are FIRST..FIRST+SEEDS-1 (default %(default)s)')
    grid.add_argument('--fault-seed', type=int, default=DEFAULT_FAULT_SEED,
                      help='seed of the injected faults (default %(default)s)')
    grid.add_argument('--duration-s', type=float, default=None,
                      help="cut every cell's drive to this many seconds after its start "
                           '(quick runs; default: whole drive)')
    add_n_particles(grid, None, "the same for every cell; default: the filter's")
    where = rob.add_argument_group('cluster (Dask)')
    where.add_argument('--scheduler', metavar='ADDRESS',
                       help='run on an existing Dask cluster, e.g. tcp://host:8786 (default: '
                            'an embedded LocalCluster on this machine)')
    where.add_argument('--workers', type=int, default=None,
                       help='worker processes of the embedded cluster (default: cores)')
    where.add_argument('--sequential', action='store_true',
                       help='run every seed of every cell in this process, without Dask')
    out = rob.add_argument_group('outputs')
    out.add_argument('--json', type=Path, help='write the matrix figures as JSON')
    out.add_argument('--figure', type=Path, metavar='PNG',
                     help='write the figure: MI rate with its interval, RMSE / WLS and '
                          'median PL / median error, per cell')
    out.add_argument('--force', action='store_true', help='replace existing outputs')
    out.add_argument('--quiet', action='store_true', help='no progress output')
    return rob


def provenance(argv) -> dict:
    """When, where and how a result was made: date (UTC), machine, command line."""
    return tool_provenance('gnsscam_eval', argv)


def _fmt_rate(mi: dict) -> str:
    if mi['mean'] is None:
        return '-'
    if mi['ci95'] is None:
        return f"{mi['mean']:.3f}"
    return f"{mi['mean']:.3f} [{mi['ci95'][0]:.3f}, {mi['ci95'][1]:.3f}]"


def robustness_table(result: dict) -> str:
    """The printed table: one row per cell, its figures and the targets' verdict."""
    headers = ['cell', 'epochs', 'MI rate [95 % CI]', 'RMSE 2D [m]', 'WLS 2D [m]',
               'RMSE/WLS', 'PL p50 [m]', 'PL p95 [m]', 'err p50 [m]', 'PL/err', 'sized',
               'spread/err', 'recov', 'pass']
    rows = []
    for c in result['cells']:
        if 'mi_rate' not in c:
            rows.append([c['name'], c['data'].get('gnss_epochs', 0)] + [None] * 11
                        + [f"no: {c.get('error', 'not run')}"])
            continue
        failed = [k for k, t in c['targets'].items() if not t['pass']]
        rows.append([
            c['name'] + (f" (= {c['same_data_as']})" if c['same_data_as'] else ''),
            c['data']['gnss_epochs'], _fmt_rate(c['mi_rate']),
            c['rmse_2d_m']['mean'] if c['rmse_2d_m'] else None, c['wls_rmse_2d_m'],
            c['rmse_ratio_to_wls'], c['protection_level']['median_m'],
            c['protection_level']['p95_m'], c['median_error_m'], c['pl_to_error_ratio'],
            (c.get('level_sizing') or {}).get('pl_to_error_sized'),
            c['cloud_calibration']['spread_to_error'],
            c['recoveries']['total'] if c['recoveries']['reported'] else '-',
            'yes' if c['pass'] else 'no: ' + ','.join(failed)])
    legend = ('targets: ' + '; '.join(f'{k} = {w} <= {lim:g}'
                                      for k, (w, lim) in TARGETS.items())
              + '. sized: the median PL / error of a level of the same shape scaled to miss '
              "exactly the share of the epochs the bound allows (q_max at a KL of 0; '-': "
              'not measured in this file), not a target. spread/err: the reported '
              "covariance's spread over the errors' (sqrt of the chi-square median over the "
              'median NEES; 1 = calibrated), not a target')
    seeds = result['seeds']
    head = (f"{result['dataset']['name']}: {len(result['cells'])} cells x {len(seeds)} "
            f'filter seeds ({seeds[0]}-{seeds[-1]}), one configuration; '
            f"{result['cells_passed']} of {len(result['cells'])} cells meet every target")
    return '\n'.join([head, format_table(headers, rows), legend])


def _check_output(path: Path | None, force: bool) -> str | None:
    """Why ``path`` cannot be written (None when it can), said before any work."""
    if path is None:
        return None
    if path.exists() and not force:
        return f'{path} exists; pass --force to replace it'
    try:
        check_writable(path)
    except OSError as err:
        return f'cannot write {path}: {err.strerror or err}'
    return None


def _error(message: str, code: int) -> int:
    print(f'gnsscam_eval: {message}', file=sys.stderr)
    return code


def run_robustness_command(args: argparse.Namespace, argv) -> int:
    """``gnsscam_eval robustness``: run the matrix, print the table, write JSON and figure.

    Args:
        args: The parsed command line.
        argv: The command line's arguments (recorded in the JSON).

    Returns:
        The exit code (module docstring).
    """
    if args.list_cells:
        print(format_table(['cell', 'kind', 'value', 'the data, changed only in',
                            'default'], matrix_rows()))
        return EXIT_OK
    try:
        cells = select_cells(args.cells)
        if args.seeds < 2:
            raise RobustnessError(f'--seeds must be at least 2, got {args.seeds}')
        for flag, value in (('--first-seed', args.first_seed),
                            ('--fault-seed', args.fault_seed)):
            if value < 0:            # numpy's generators take seeds >= 0 only
                raise RobustnessError(f'{flag} must be >= 0, got {value}')
        if args.sequential and args.scheduler:
            raise RobustnessError('--sequential and --scheduler exclude each other')
        if args.workers is not None and args.workers < 1:
            raise RobustnessError(f'--workers must be at least 1, got {args.workers}')
        if args.duration_s is not None and not args.duration_s > 0:
            raise RobustnessError(f'--duration-s must be positive, got {args.duration_s}')
        overrides = {} if args.n_particles is None else {'n_particles': args.n_particles}
        config = campaign_config(**overrides)
    except ValueError as err:                # RobustnessError, a FilterConfig refusal
        return _error(str(err), EXIT_USAGE)
    for path in (args.json, args.figure):
        problem = _check_output(path, args.force)
        if problem:
            return _error(problem, EXIT_OUTPUT)
    info = provenance(argv)
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    try:
        drive = load_smartloc_args(args.folder, args.input, args.truth)
        result = run_robustness(drive, cells, seeds, config, duration_s=args.duration_s,
                                fault_seed=args.fault_seed, scheduler=args.scheduler,
                                workers=args.workers, sequential=args.sequential,
                                progress=not args.quiet)
    except (DatasetError, ClusterError) as err:
        return _error(str(err), EXIT_INPUT)
    except (KeyboardInterrupt, SystemError) as err:
        if not is_interrupt(err):
            raise
        return _error('interrupted; nothing written', EXIT_INTERRUPTED)
    result = {'command': 'robustness', **info,
              'dataset': {'name': drive.name, 'gnss_epochs': len(drive.gnss),
                          **{k: v for k, v in drive.info.items()
                             if isinstance(v, (str, int, float, bool)) or v is None}},
              **result, 'matrix': [c.name for c in DEFAULT_CELLS]}
    print(robustness_table(result))
    print(f"\n{result['runs_computed']} runs in {result['seconds']:.0f} s "
          f"({result['cluster']['kind']}, {result['cluster']['workers']} workers), "
          + (f"{result['run_seconds_mean']:.1f} s per run"
             if result['run_seconds_mean'] else 'no run finished'))
    code = _write_outputs(args, result)
    if code != EXIT_OK:
        return code
    if result['failed']:
        return _error(f"{len(result['failed'])} runs or cells failed (listed in the "
                      "JSON's 'failed'); the cells are summarised without them",
                      EXIT_RUNS_FAILED)
    return EXIT_OK


def _write_outputs(args: argparse.Namespace, result: dict) -> int:
    """``--figure`` then ``--json`` (which records the figure's path)."""
    if args.figure is not None:
        # matplotlib takes ~0.7 s to import: only when a figure is asked for.
        from .robustness_plot import robustness_figure
        try:
            robustness_figure(args.figure, result)
        except OSError as err:
            return _error(f'cannot write {args.figure}: {err}', EXIT_OUTPUT)
        result['figure'] = str(args.figure)
        print(f'wrote {args.figure}')
    if args.json is not None:
        try:
            write_json_atomic(args.json, result, force=args.force)
        except (OSError, OutputExistsError, ValueError) as err:
            return _error(f'cannot write {args.json}: {err}', EXIT_OUTPUT)
        print(f'wrote {args.json}')
    return EXIT_OK
