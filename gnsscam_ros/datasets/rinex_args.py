"""The ``rinex`` subcommand's options, shared by ``gnsscam_convert`` and ``gnsscam_eval``.

Exit codes are those of the command (bad input: 3, with one line naming the file).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ..core.types import Drive
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


def load_rinex_args(args: argparse.Namespace, quiet: bool = False) -> Drive:
    """The drive of the ``rinex`` options; prints the satellites skipped by reason to
    stderr (the same counts are in ``drive.info``)."""
    station = None if args.station_ecef is None else np.array(args.station_ecef)
    drive = load_rinex(args.obs, args.nav, static=args.static, station_ecef_m=station,
                       duration_s=args.duration_s)
    if not quiet:
        print(f"rinex: {drive.info['epochs']} epochs ({drive.info['epochs_unusable']} with "
              f"fewer than 4 satellites), satellites skipped: "
              f"{preprocessing_summary(drive)['skipped_satellites'] or 'none'}",
              file=sys.stderr)
    return drive


def preprocessing_summary(drive: Drive) -> dict:
    """What the preprocessing left out, for the evaluation JSON."""
    keys = ('observations', 'navigation', 'static', 'epochs', 'epochs_unusable',
            'skipped_satellites')
    return {k: drive.info.get(k) for k in keys}
