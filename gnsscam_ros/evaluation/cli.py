"""``gnsscam_eval``: evaluate the filter on the smartLoc data or the emulated drive.

Examples::

    gnsscam_eval smartloc ../shared/data/smartloc --json out.json
    gnsscam_eval emulated --faults 6 --bias-m 100 --seed 3 --json out.json
    gnsscam_eval smartloc ../shared/data/smartloc --epochs-csv epochs.csv --plots plots/
    gnsscam_eval rinex --obs slac1180.21o --nav brdc1180.21n --static \
        --station-ecef -2703115.921 -4291767.208 3854247.906 --json slac.json

``--epochs-csv FILE`` writes one row per GNSS epoch (updated or not; columns
``runner.EpochTable.CSV_COLUMNS``: ``stamp_ns`` the input's time, the estimate in WGS84
``lat_deg``/``lon_deg``/``height_m``, ``protection_level_m`` (empty when none),
``risk_bound``, ``integrity`` OK/ERROR/STALE, ``horizontal_error_m``, ...). ``--plots DIR``
writes the Stanford diagram and the error/protection-level timeline of the run.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..bags.errors import BagError
from ..core.filter import FilterConfig
from ..core.interrupts import interrupts_redelivered
from ..datasets.emulated.drive import make_emulated_drive
from ..datasets.errors import DatasetError
from ..datasets.faults import FaultEpisodes, inject_pseudorange_faults
from ..datasets.rinex_args import (add_rinex_arguments, load_rinex_args,
                                   preprocessing_summary, station_figures)
from ..datasets.smartloc import load_smartloc_args
from ..io.atomic import (OutputExistsError, check_writable, write_csv_atomic,
                         write_json_atomic)
from ..io.provenance import provenance
from ..io.tables import format_table
from .bag_eval import evaluate_result_bag_epochs
from .campaign import GNSS_CASES, METHODS, campaign_config
from .campaign_cluster import ClusterError
from .campaign_grid import gnss_cases, parse_seeds
from .campaign_run import run_campaign
from .campaign_store import CampaignStoreError
from .campaign_summary import campaign_tables
from .evaluate import evaluate_drive_record
from .filter_options import (DEFAULT_ALERT_LIMITS_M, add_filter_arguments, add_n_particles,
                             config_from_args)
from .interrupts import EXIT_INTERRUPTED, is_interrupt
from .report import (INTEGRITY_HEADERS, integrity_rows, protection_level_headers,
                     protection_level_rows, stanford_line)
from .robustness_cli import add_robustness_parser, run_robustness_command

EXIT_OK, EXIT_USAGE, EXIT_INPUT, EXIT_OUTPUT = 0, 2, 3, 4
#: Some campaign cases failed (the others are written; a rerun retries them).
EXIT_CASES_FAILED = 1
#: Filter seed of gnsscam_eval and of the demo (the same runs give the same figures).
DEFAULT_SEED = 1


def print_result(label: str, result: dict, out=None) -> None:
    """The readable summary of one evaluation."""
    out = sys.stdout if out is None else out
    base = result['baseline_wls']
    print(format_table(
        ['run', 'epochs', 'RMSE 2D [m]', 'RMSE 3D [m]', 'p95 2D [m]', 'WLS 2D [m]',
         'WLS 3D [m]', 'ratio 2D'],
        [[label, result['epochs'], result['rmse_2d_m'], result['rmse_3d_m'],
          result['p95_2d_m'], base['rmse_2d_m'], base['rmse_3d_m'],
          result['rmse_2d_ratio_to_wls']]]), file=out)
    print(file=out)
    rows = []
    for method, by_limit in result['integrity_by_inverse_bernoulli'].items():
        rows += integrity_rows(f'{label} ({method})', by_limit)
    print(format_table(INTEGRITY_HEADERS, rows), file=out)
    pl = result.get('protection_level')
    if pl is not None:
        print(file=out)
        print("Protection level (MI: error > PL; avail: PL <= AL; err>AL|PL<=AL and "
              "err>AL|OK: epochs with the error above the alert limit among those "
              "available / flagged OK):", file=out)
        print(format_table(protection_level_headers(pl), protection_level_rows(label, pl)),
              file=out)
        print(stanford_line(pl), file=out)
    calibration = result.get('cloud_calibration')
    if calibration is not None and calibration['median_nees'] is not None:
        print(f"Cloud calibration: median NEES {calibration['median_nees']:.3g} over "
              f"{calibration['epochs']} epochs ({calibration['calibrated_median_nees']:.3g} "
              f"when the reported covariance matches the errors, {calibration['dims']}D): "
              f"reported spread / error {calibration['spread_to_error']:.2f}", file=out)
    sizing = result.get('level_sizing')
    if sizing is not None and sizing['scale'] is not None:
        print(f"Level sizing: median PL / median error {sizing['pl_to_error']:.2f}; a level "
              f"of the same shape missing {100 * sizing['miss_share']:.2g} % of the "
              f"{sizing['epochs']} epochs (what the bound allows) would be "
              f"x{sizing['scale']:.2f} of it: median PL / error "
              f"{sizing['pl_to_error_sized']:.2f}", file=out)


def add_campaign_arguments(camp: argparse.ArgumentParser) -> None:
    """Options of ``gnsscam_eval campaign``: the grid, the cluster, the outputs."""
    grid = camp.add_argument_group('grid')
    grid.add_argument('--seeds', nargs='+', default=['1-3'], metavar='SEEDS',
                      help='drive seeds: N, ranges A-B and comma lists, e.g. 1-200 or '
                           '1-10,20 (default %(default)s)')
    grid.add_argument('--faults', type=int, nargs='+',
                      default=sorted({f for f, _ in GNSS_CASES}),
                      help='faulty satellites of 12; 0 is the NLOS-only case '
                           '(default %(default)s)')
    grid.add_argument('--bias-m', type=float, nargs='+',
                      default=sorted({b for f, b in GNSS_CASES if f}),
                      help='fault biases [m] of the cases with faults (default %(default)s)')
    grid.add_argument('--methods', nargs='+', default=list(METHODS), choices=list(METHODS))
    add_n_particles(grid, FilterConfig().n_particles, 'default %(default)s')
    grid.add_argument('--duration-s', type=float, default=None,
                      help='cut every drive short (quick looks; default: whole drives)')
    where = camp.add_argument_group('cluster (Dask)')
    where.add_argument('--scheduler', metavar='ADDRESS',
                       help='run on an existing Dask cluster, e.g. tcp://host:8786 (default: '
                            'an embedded LocalCluster on this machine)')
    where.add_argument('--workers', type=int, default=None,
                       help='worker processes of the embedded cluster (default: cores)')
    where.add_argument('--sequential', action='store_true',
                       help='run every case in this process, without Dask')
    where.add_argument('--cache', type=Path, default=None,
                       help='where workers cache map databases and camera matches, a path '
                            "on every worker (default: .cache/gnsscam here; with "
                            "--scheduler each worker's $GNSSCAM_CACHE_DIR or "
                            '~/.cache/gnsscam_ros)')
    out = camp.add_argument_group('outputs')
    out.add_argument('--out', type=Path, default=Path('out/campaign'),
                     help='campaign folder: each case is written there as it finishes, '
                          'the same command resumes an interrupted campaign, the summary '
                          '(campaign.json, runs.csv, intervals.csv) is written at the end '
                          '(default %(default)s)')
    out.add_argument('--restart', action='store_true',
                     help='discard the finished cases in --out first')
    out.add_argument('--plots', type=Path, help='folder for the PNG figures')
    out.add_argument('--epochs-csv', type=Path, metavar='DIR',
                     help='write one per-epoch CSV per run (seed, case, method) into DIR')


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='gnsscam_eval', description='Evaluate the GNSS(-camera) particle filter '
        'against ground truth, next to a robust snapshot WLS baseline.')
    sub = parser.add_subparsers(dest='command', required=True)
    smart = sub.add_parser('smartloc', help='a smartLoc run in the libRSF text format')
    smart.add_argument('folder', type=Path, nargs='?',
                       help='folder with *_Input.txt and *_GT.txt (or use --input/--truth)')
    smart.add_argument('--input', type=Path, help='input file (pseudorange3/odom3 lines)')
    smart.add_argument('--truth', type=Path, help='ground-truth file (point3 lines)')
    smart.add_argument('--inject-faults', type=int, default=0, metavar='EPISODES',
                       help='add this many pseudorange fault episodes (2-5 satellites, '
                            '20-200 m, 10-40 s each; drawn with --fault-seed) to the real '
                            'data (default 0)')
    smart.add_argument('--fault-seed', type=int, default=1,
                       help='seed of the injected faults (default %(default)s)')
    emu = sub.add_parser('emulated', help='the seeded emulated urban drive')
    emu.add_argument('--faults', type=int, default=0, help='faulty satellites of 12')
    emu.add_argument('--bias-m', type=float, default=100.0, help='fault bias [m]')
    emu.add_argument('--drive-seed', type=int, default=None,
                     help='drive seed (default: --seed)')
    emu.add_argument('--duration-s', type=float, default=None, help='cut the drive short')
    emu.add_argument('--no-nlos', action='store_true', help='no NLOS errors')
    rinex = sub.add_parser('rinex', help='RINEX observations + broadcast navigation of a '
                           'station with published coordinates')
    add_rinex_arguments(rinex, station_required=True)
    for p in (smart, emu, rinex):
        add_filter_arguments(p, DEFAULT_SEED)
    camp = sub.add_parser('campaign', help="the paper's campaign on the emulated drive "
                          '(Tables 2-4, Figures 4-11) with confidence intervals, on Dask')
    add_campaign_arguments(camp)
    bag = sub.add_parser('bag', help='metrics of a recorded result bag (pose/fix, '
                         'integrity_risk) against ground truth')
    bag.add_argument('result_bag', type=Path, help='bag recorded from the nodes')
    bag.add_argument('--truth', type=Path, help='the dataset bag (gnsscam_convert), when the '
                     'result bag has no ground_truth/pose')
    bag.add_argument('--namespace', default='/', help='namespace of the recorded topics')
    bag.add_argument('--origin', type=float, nargs=3, metavar=('LAT', 'LON', 'ALT'),
                     help='map frame origin, when no bag has map/origin')
    add_robustness_parser(sub)
    for p in (smart, emu, bag, rinex):
        p.add_argument('--epochs-csv', type=Path, metavar='FILE',
                       help='write one row per GNSS epoch (estimate in WGS84, protection '
                       'level, risk bound, integrity OK/ERROR/STALE, error)')
        p.add_argument('--plots', type=Path, metavar='DIR',
                       help='write the Stanford diagram and the error/PL timeline here')
    for p in (smart, emu, camp, bag, rinex):
        p.add_argument('--json', type=Path, help='write the metrics as JSON')
        p.add_argument('--force', action='store_true', help='replace an existing --json')
        p.add_argument('--quiet', action='store_true', help='no progress output')
    return parser


def write_result(args: argparse.Namespace, result: dict, epochs=None, label: str = 'run',
                 alert_limit_m: float = DEFAULT_ALERT_LIMITS_M[0]) -> int:
    """Write ``--epochs-csv``, ``--plots`` and ``--json`` when asked; the exit code.

    Args:
        args: The command line.
        result: The evaluation JSON (``plots`` and ``epochs_csv`` are added to it).
        epochs: The run's ``runner.EpochTable``.
        label: Run name (figure titles and file names).
        alert_limit_m: Alert limit of the figures [m].
    """
    if getattr(args, 'epochs_csv', None) is not None and epochs is not None:
        try:
            write_csv_atomic(args.epochs_csv, list(epochs.CSV_COLUMNS), epochs.csv_rows(),
                             force=args.force)
        except (OSError, OutputExistsError) as err:
            print(f'gnsscam_eval: cannot write {args.epochs_csv}: {err}', file=sys.stderr)
            return EXIT_OUTPUT
        result['epochs_csv'] = {'path': str(args.epochs_csv), 'rows': len(epochs)}
        print(f'\nwrote {args.epochs_csv} ({len(epochs)} GNSS epochs)')
    if getattr(args, 'plots', None) is not None and epochs is not None:
        # matplotlib takes ~0.7 s to import: only when figures are asked for.
        from .plots import dataset_title, integrity_plots
        name = ''.join(c if c.isalnum() or c in '-_.' else '_' for c in label)
        try:
            paths = integrity_plots(args.plots, name, dataset_title(label), epochs.stamp_ns,
                                    epochs.horizontal_error_m, epochs.protection_level_m,
                                    epochs.integrity, alert_limit_m)
        except OSError as err:
            print(f'gnsscam_eval: cannot write plots into {args.plots}: {err}',
                  file=sys.stderr)
            return EXIT_OUTPUT
        result['plots'] = [str(p) for p in paths]
        print('wrote ' + ', '.join(str(p) for p in paths))
    if args.json is not None:
        result = {'command': args.command, **getattr(args, 'provenance', {}), **result}
        try:
            write_json_atomic(args.json, result, force=args.force)
        except (OSError, OutputExistsError, ValueError) as err:
            # ValueError: a NaN the JSON cannot hold (inputs are checked at load, so this
            # is a metric without a value); nothing is written either way.
            print(f'gnsscam_eval: cannot write {args.json}: {err}', file=sys.stderr)
            return EXIT_OUTPUT
        print(f'\nwrote {args.json}')
    return EXIT_OK


def run_bag_command(args: argparse.Namespace) -> int:
    """``gnsscam_eval bag``: the offline metrics computed from a recorded result bag."""
    try:
        result, epochs = evaluate_result_bag_epochs(
            args.result_bag, args.truth, namespace=args.namespace,
            origin_llh=tuple(args.origin) if args.origin else None)
    except (BagError, ValueError) as err:
        print(f'gnsscam_eval: {err}', file=sys.stderr)
        return EXIT_INPUT
    label = Path(args.result_bag).name
    print_result(label, result)
    limit = result.get('protection_level', {}).get('alert_limit_m', DEFAULT_ALERT_LIMITS_M[0])
    return write_result(args, result, epochs, label, limit)


def run_campaign_command(args: argparse.Namespace) -> int:
    """``gnsscam_eval campaign``: run (or resume) the grid, print the tables, write the
    summary, the JSON and the plots."""
    try:
        if args.sequential and args.scheduler:
            raise ValueError('--sequential and --scheduler exclude each other')
        if args.workers is not None and args.workers < 1:
            raise ValueError(f'--workers must be at least 1, got {args.workers}')
        seeds = parse_seeds(args.seeds)
        cases = gnss_cases(args.faults, args.bias_m)
        base = campaign_config(n_particles=args.n_particles)
    except ValueError as err:
        print(f'gnsscam_eval: {err}', file=sys.stderr)
        return EXIT_USAGE
    if args.epochs_csv is not None and args.epochs_csv.exists() and any(
            args.epochs_csv.iterdir()) and not (args.force or _resuming(args.out)):
        print(f'gnsscam_eval: {args.epochs_csv} is not empty; pass --force to write into it',
              file=sys.stderr)
        return EXIT_OUTPUT
    cache = args.cache
    if cache is None and args.scheduler is None:
        cache = Path('.cache/gnsscam').resolve()   # this machine's workers share it
    try:
        result = run_campaign(seeds=seeds, base=base, methods=tuple(args.methods),
                              cases=cases, out_dir=args.out, restart=args.restart,
                              scheduler=args.scheduler, workers=args.workers,
                              sequential=args.sequential, cache_dir=cache,
                              plots_dir=args.plots, epochs_dir=args.epochs_csv,
                              progress=not args.quiet, duration_s=args.duration_s)
    except CampaignStoreError as err:
        print(f'gnsscam_eval: {err}', file=sys.stderr)
        return EXIT_OUTPUT
    except ClusterError as err:
        print(f'gnsscam_eval: {err}', file=sys.stderr)
        return EXIT_INPUT
    except (KeyboardInterrupt, SystemError) as err:
        if not is_interrupt(err):
            raise
        print(f'\ngnsscam_eval: interrupted; the finished cases are in {args.out}/cases: '
              'the same command resumes the campaign', file=sys.stderr)
        return EXIT_INTERRUPTED
    print(campaign_tables(result['cases'], result['intervals']))
    alpha = result['camera_mean_alpha']
    if alpha:
        print('\nmean camera mixture weight by frame fault: '
              + ', '.join(f'{k} {v:.4f}' for k, v in sorted(alpha.items())))
    cluster = result['cluster']
    where = {'sequential': 'in this process (sequential)',
             'embedded': f"on an embedded cluster ({cluster['workers']} workers)",
             'scheduler': f"on {cluster['scheduler']} ({cluster['workers']} workers)",
             'none': '(every case was finished before)'}
    rate = result['epochs_per_second']
    print(f"\ncampaign: {len(result['cases'])} runs, {result['epochs']} epochs "
          f"({result['computed']} runs computed, {result['resumed']} resumed) in "
          f"{result['seconds']:.0f} s {where[cluster['kind']]}"
          + (f', {rate:.1f} epochs/s' if rate else ''))
    print(f"wrote {args.out}/campaign.json, runs.csv, intervals.csv")
    if args.json is not None:
        result = {'command': 'campaign', **getattr(args, 'provenance', {}), **result}
        try:
            write_json_atomic(args.json, result, force=args.force)
        except (OSError, OutputExistsError, ValueError) as err:
            print(f'gnsscam_eval: cannot write {args.json}: {err}', file=sys.stderr)
            return EXIT_OUTPUT
        print(f'wrote {args.json}')
    if result['failed']:
        print(f"gnsscam_eval: {len(result['failed'])} cases failed (listed in "
              f"{args.out}/campaign.json); the same command runs them again",
              file=sys.stderr)
        return EXIT_CASES_FAILED
    return EXIT_OK


def _resuming(out: Path) -> bool:
    """A campaign folder with finished cases (its epoch CSVs are its own)."""
    cases = Path(out) / 'cases'
    return cases.is_dir() and any(cases.glob('*.json'))


def load_drive(args: argparse.Namespace):
    """The drive named on the command line."""
    if args.command == 'rinex':
        return load_rinex_args(args, quiet=args.quiet)
    if args.command == 'smartloc':
        drive = load_smartloc_args(args.folder, args.input, args.truth)
        if args.inject_faults:
            drive = inject_pseudorange_faults(drive, args.fault_seed,
                                              FaultEpisodes(episodes=args.inject_faults))
        return drive
    seed = args.seed if args.drive_seed is None else args.drive_seed
    return make_emulated_drive(seed, faults=args.faults, bias_m=args.bias_m,
                               nlos=not args.no_nlos, duration_s=args.duration_s)


def main(argv: list[str] | None = None) -> int:
    """``gnsscam_eval``; its exit status (``EXIT_*``; 130 after Ctrl-C, wherever it
    landed: nothing is written before a run has finished)."""
    try:
        with interrupts_redelivered():      # a Ctrl-C while numba compiles is not lost
            return _command(argv)
    except (KeyboardInterrupt, SystemError) as err:
        if not is_interrupt(err):
            raise
        print('\ngnsscam_eval: interrupted; nothing written', file=sys.stderr)
        return EXIT_INTERRUPTED


def _command(argv: list[str] | None) -> int:
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else argv
    args = parser.parse_args(argv)
    if args.command == 'robustness':
        return run_robustness_command(args, argv)
    # When, where and how: every result JSON carries it (docs/results.md shows it).
    args.provenance = provenance('gnsscam_eval', argv)
    for path in (args.json, None if args.command == 'campaign' else args.epochs_csv):
        if path is not None and path.exists() and not args.force:
            print(f'gnsscam_eval: {path} exists; pass --force to replace it',
                  file=sys.stderr)
            return EXIT_OUTPUT
        if path is not None:
            try:
                # A read-only or missing folder is said now, not after the whole run.
                check_writable(path)
            except OSError as err:
                print(f'gnsscam_eval: cannot write {path}: {err.strerror or err}',
                      file=sys.stderr)
                return EXIT_OUTPUT
    if args.command == 'campaign':
        return run_campaign_command(args)
    if args.command == 'bag':
        return run_bag_command(args)
    try:
        config = config_from_args(args)
    except ValueError as err:
        parser.error(str(err))
    try:
        drive = load_drive(args)
        result, record = evaluate_drive_record(drive, config, seed=args.seed,
                                               progress=not args.quiet)
    except (DatasetError, ValueError) as err:
        print(f'gnsscam_eval: {err}', file=sys.stderr)
        return EXIT_INPUT
    if args.command == 'rinex':
        result['preprocessing'] = preprocessing_summary(drive)
        result['station'] = station_figures(result, record.epochs)
        print('station: ' + ', '.join(f'{k} {v:.3f}' for k, v in result['station'].items()
                                      if v is not None))
    print_result(drive.name, result)
    return write_result(args, result, record.epochs, drive.name, config.alert_limit_m)


if __name__ == '__main__':
    sys.exit(main())
