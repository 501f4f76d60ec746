"""The ``rinex`` subcommand's options, shared by ``gnsscam_convert`` and ``gnsscam_eval``.

Exit codes are those of the command (bad input: 3, with one line naming the file).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ..core.types import Drive
from .android import load_android
from .errors import DatasetError
from .rinex import SYSTEM_OF_LETTER
from .rinex_drive import load_rinex


def add_rinex_arguments(parser: argparse.ArgumentParser, station_required: bool) -> None:
    """``--obs FILE --nav FILE [--nav FILE ...] [--static] [--station-ecef X Y Z]
    [--duration-s S]``."""
    parser.add_argument('--obs', type=Path, required=True,
                        help='RINEX 2/3 observation file (.o, .rnx, .gz, .crx, .crx.gz)')
    parser.add_argument('--nav', type=Path, action='append', required=True,
                        help='RINEX broadcast navigation file; repeat for each system')
    parser.add_argument('--static', action='store_true',
                        help='the receiver does not move: add zero-motion odometry with a '
                             'tight covariance (odom/twist)')
    parser.add_argument('--station-ecef', type=float, nargs=3, metavar=('X', 'Y', 'Z'),
                        required=station_required,
                        help='published marker position, ECEF [m] (ground truth)')
    parser.add_argument('--duration-s', type=float, default=None,
                        help='only the first seconds of the observation file [s]')
    parser.add_argument('--systems', default=None, metavar='LETTERS',
                        help='use only these systems, RINEX letters (e.g. G or GEC; '
                             'default: every system with navigation)')


def parse_systems(letters: str | None) -> tuple[int, ...] | None:
    """``'GEC'`` -> system codes; None stays None.

    Raises:
        ValueError: A letter that is not G, R, E or C.
    """
    if letters is None:
        return None
    codes = []
    for letter in letters.upper():
        if letter not in 'GREC':
            raise ValueError(f'--systems: {letter!r} is not one of G R E C')
        codes.append(SYSTEM_OF_LETTER[letter])
    return tuple(codes)


def load_rinex_args(args: argparse.Namespace, quiet: bool = False) -> Drive:
    """The drive of the ``rinex`` options; prints the satellites skipped by reason to
    stderr (the same counts are in ``drive.info``)."""
    station = None if args.station_ecef is None else np.array(args.station_ecef)
    try:
        systems = parse_systems(args.systems)
    except ValueError as err:
        raise DatasetError(str(err)) from err
    drive = load_rinex(args.obs, args.nav, static=args.static, station_ecef_m=station,
                       duration_s=args.duration_s, systems=systems)
    if not quiet:
        print(f"rinex: {drive.info['epochs']} epochs ({drive.info['epochs_unusable']} with "
              f"fewer than 4 satellites), satellites skipped: "
              f"{preprocessing_summary(drive)['skipped_satellites'] or 'none'}",
              file=sys.stderr)
    return drive


def preprocessing_summary(drive: Drive) -> dict:
    """What the preprocessing left out, for the evaluation JSON."""
    keys = ('observations', 'navigation', 'static', 'systems', 'epochs', 'epochs_unusable',
            'skipped_satellites')
    return {k: drive.info.get(k) for k in keys}


def station_figures(result: dict, epochs) -> dict:
    """The figures a static station is judged by, from an evaluation's result and epoch
    table: the snapshot WLS's horizontal and vertical RMS error [m] (vertical from its 3D
    and 2D RMS), the filter's median horizontal error [m] and median protection level
    over it."""
    base = result['baseline_wls']
    vertical = float(np.sqrt(max(base['rmse_3d_m'] ** 2 - base['rmse_2d_m'] ** 2, 0.0)))
    err = np.asarray(epochs.horizontal_error_m, dtype=float)
    pl = np.asarray(epochs.protection_level_m, dtype=float)
    err_med = float(np.nanmedian(err)) if np.isfinite(err).any() else None
    pl_med = float(np.nanmedian(pl[np.isfinite(pl)])) if np.isfinite(pl).any() else None
    return {'wls_horizontal_rms_m': base['rmse_2d_m'], 'wls_vertical_rms_m': vertical,
            'filter_horizontal_rms_m': result['rmse_2d_m'],
            'filter_median_horizontal_error_m': err_med, 'median_protection_level_m': pl_med,
            'pl_to_error_ratio': (pl_med / err_med if pl_med is not None and err_med
                                  else None),
            'mi_rate': result['protection_level']['mi_rate']}


def add_android_arguments(parser: argparse.ArgumentParser) -> None:
    """``--log FILE --nav FILE [--nav FILE ...] [--static] [--truth CSV] [--systems L]``."""
    parser.add_argument('--log', type=Path, required=True,
                        help='GnssLogger raw log (gnss_log.txt) or GSDC device_gnss.csv')
    parser.add_argument('--nav', type=Path, action='append', required=True,
                        help='RINEX broadcast navigation file of the same day; repeat for '
                             'each system')
    parser.add_argument('--static', action='store_true',
                        help='the phone does not move: zero-motion odometry')
    parser.add_argument('--truth', type=Path, help='GSDC ground_truth.csv')
    parser.add_argument('--systems', default=None, metavar='LETTERS',
                        help='use only these systems (G R E C)')


def load_android_args(args: argparse.Namespace, quiet: bool = False) -> Drive:
    """The drive of the ``android`` options (skips printed as for ``rinex``)."""
    try:
        systems = parse_systems(args.systems)
    except ValueError as err:
        raise DatasetError(str(err)) from err
    drive = load_android(args.log, args.nav, static=args.static, truth_path=args.truth,
                         systems=systems)
    if not quiet:
        print(f"android: {drive.info['epochs']} epochs, rows not used: "
              f"{drive.info['rows_not_used'] or 'none'}, satellites skipped: "
              f"{drive.info['skipped_satellites'] or 'none'}", file=sys.stderr)
    return drive
