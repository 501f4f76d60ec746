"""``gnsscam_convert``: a dataset into a rosbag2 bag (MCAP by default).

Examples::

    gnsscam_convert emulated --seed 1 --out bags/emulated_s1
    gnsscam_convert emulated --seed 3 --faults 6 --duration-s 60 --out bags/short
    gnsscam_convert smartloc ../shared/data/smartloc --out bags/smartloc --storage sqlite3
    gnsscam_convert rinex --obs slac1180.21o --nav brdc1180.21n --static --out bags/slac
    gnsscam_convert android --log gnss_log.txt --nav BRDC00IGS_R_....rnx --out bags/phone

Progress goes to stderr, the summary (topics, counts, duration, size, MB/s) to stdout.
Exit codes: 0 done, 2 bad usage, 3 bad input (dataset or data a bag cannot hold),
4 output refused or failed (an existing path is never overwritten), 130 interrupted (the
partial bag is removed).

The bag is written into a hidden ``.NAME.partial-HOST-PID-*`` folder beside ``--out``.
One left by a killed run (SIGKILL, power cut) is found by the next run in that folder:
removed when its writer provably no longer runs, else reported with the command that
removes it (:mod:`..io.partials`).
"""
from __future__ import annotations

import argparse
import signal
import sys
import time
from pathlib import Path

from ..datasets.emulated.camera import with_camera
from ..datasets.emulated.drive import make_emulated_drive
from ..datasets.errors import DatasetError
from ..datasets.rinex_args import (add_android_arguments, add_rinex_arguments,
                                   load_android_args, load_rinex_args)
from ..datasets.smartloc import load_smartloc_args
from ..io.atomic import check_writable, write_json_atomic
from ..io.partials import sweep_and_report
from ..io.tables import format_table
from .convert import STORAGES, ConvertSummary, convert_drive
from .errors import BagContentError, BagError, BagExistsError

EXIT_OK, EXIT_USAGE, EXIT_INPUT, EXIT_OUTPUT, EXIT_INTERRUPTED = 0, 2, 3, 4, 130


class ProgressLine:
    """Progress on a stream: one rewritten line on a terminal, a line every 10 s else."""

    def __init__(self, stream=None, label: str = 'convert'):
        self.stream = sys.stderr if stream is None else stream
        self.label = label
        self.tty = bool(getattr(self.stream, 'isatty', lambda: False)())
        self.start = time.monotonic()
        self.last = -1e9
        self.period = 0.5 if self.tty else 10.0

    def __call__(self, done: int, total: int, payload_bytes: int) -> None:
        now = time.monotonic()
        if now - self.last < self.period and done < total:
            return
        self.last = now
        elapsed = now - self.start
        rate = payload_bytes / 1e6 / elapsed if elapsed > 0 else 0.0
        text = (f'{self.label}: {done}/{total} messages ({100.0 * done / max(total, 1):.0f} %)'
                f', {payload_bytes / 1e6:.1f} MB, {rate:.1f} MB/s, {elapsed:.0f} s')
        if self.tty:
            self.stream.write('\r' + text + ('\n' if done >= total else ''))
        else:
            self.stream.write(text + '\n')
        self.stream.flush()


def format_summary(summary: ConvertSummary) -> str:
    """The readable summary: one row per topic, then totals and speed."""
    rows = [[topic, rec.msgtype, rec.count, rec.payload_bytes / 1e6]
            for topic, rec in summary.topics.items()]
    table = format_table(['topic', 'type', 'messages', 'MB'], rows)
    return (f'{table}\n'
            f'bag {summary.path} ({summary.storage}): {summary.messages} messages over '
            f'{summary.duration_s:.1f} s, {summary.bag_bytes / 1e6:.1f} MB on disk\n'
            f'converted in {summary.seconds:.1f} s: {summary.mb_per_s:.1f} MB/s end to end, '
            f'{summary.write_mb_per_s:.1f} MB/s without waiting for frames to render '
            f'({summary.camera_wait_seconds:.1f} s)')


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='gnsscam_convert',
        description='Convert a dataset into a rosbag2 bag with the gnsscam_ros input topics '
        '(gnss/pseudoranges, camera/image_raw, imu/data, odom/twist) and ground truth '
        '(ground_truth/pose). Never overwrites; a failed or interrupted run leaves no bag.')
    sub = parser.add_subparsers(dest='dataset', required=True)
    emu = sub.add_parser('emulated', help='the seeded emulated urban drive (with camera)')
    emu.add_argument('--seed', type=int, default=1, help='drive seed (default %(default)s)')
    emu.add_argument('--duration-s', type=float, default=None,
                     help='keep only the first seconds of the drive [s]')
    emu.add_argument('--faults', type=int, default=0, help='faulty satellites of 12')
    emu.add_argument('--bias-m', type=float, default=100.0, help='fault bias [m]')
    emu.add_argument('--no-nlos', action='store_true', help='no NLOS errors')
    emu.add_argument('--no-camera', action='store_true', help='leave out camera/image_raw')
    emu.add_argument('--camera-fault-fraction', type=float, default=0.2,
                     help='fraction of blurred/occluded frames (default %(default)s)')
    smart = sub.add_parser('smartloc', help='a smartLoc run in the libRSF text format')
    smart.add_argument('folder', type=Path, nargs='?',
                       help='folder with *_Input.txt and *_GT.txt (or use --input/--truth)')
    smart.add_argument('--input', type=Path, help='input file (pseudorange3/odom3 lines)')
    smart.add_argument('--truth', type=Path, help='ground-truth file (point3 lines)')
    rinex = sub.add_parser('rinex', help='RINEX observations + broadcast navigation')
    add_rinex_arguments(rinex, station_required=False)
    android = sub.add_parser('android', help='Android GnssLogger raw log + RINEX navigation')
    add_android_arguments(android)
    for p in (emu, smart, rinex, android):
        p.add_argument('--out', type=Path, required=True,
                       help='bag folder to create (must not exist)')
        p.add_argument('--storage', choices=sorted(STORAGES), default='mcap',
                       help='storage plugin (default %(default)s, as ros2 bag on Jazzy)')
        p.add_argument('--namespace', default='/',
                       help='namespace to write the topics under (default /)')
        p.add_argument('--workers', type=int, default=None,
                       help='threads rendering camera frames ahead (default min(4, cores))')
        p.add_argument('--json', type=Path, help='also write the summary as JSON')
        p.add_argument('--quiet', action='store_true', help='no progress output')
    return parser


def load(args: argparse.Namespace):
    """The drive named on the command line (emulated: with its camera stream)."""
    if args.dataset == 'smartloc':
        return load_smartloc_args(args.folder, args.input, args.truth)
    if args.dataset == 'rinex':
        return load_rinex_args(args, quiet=args.quiet)
    if args.dataset == 'android':
        return load_android_args(args, quiet=args.quiet)
    try:
        drive = make_emulated_drive(args.seed, faults=args.faults, bias_m=args.bias_m,
                                    nlos=not args.no_nlos, duration_s=args.duration_s)
        if not args.no_camera:
            drive = with_camera(drive, fault_fraction=args.camera_fault_fraction)
    except ValueError as err:
        raise DatasetError(f'emulated drive: {err}') from err
    return drive


def _interrupt(signum, frame):
    # SIGTERM is handled like Ctrl-C so that the partial bag is removed either way.
    raise KeyboardInterrupt(f'signal {signum}')


def main(argv: list[str] | None = None) -> int:
    """``gnsscam_convert``; returns the exit code (see the module docstring)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.out.exists() or args.out.is_symlink():
        # Refuse before generating or loading anything.
        print(f'gnsscam_convert: {args.out} exists; not overwriting', file=sys.stderr)
        return EXIT_OUTPUT
    if args.json is not None and (args.json.exists() or args.json.is_symlink()):
        print(f'gnsscam_convert: {args.json} exists; not overwriting', file=sys.stderr)
        return EXIT_OUTPUT
    if args.json is not None:
        try:
            check_writable(args.json)       # said now, not after the whole run
        except OSError as err:
            print(f'gnsscam_convert: cannot write {args.json}: {err.strerror or err}',
                  file=sys.stderr)
            return EXIT_OUTPUT
    # The hidden partial bags of killed conversions or recordings beside the output:
    # removed when provably stale, else reported with the command that removes them.
    sweep_and_report(args.out, 'gnsscam_convert')
    previous = None
    try:
        try:
            previous = signal.signal(signal.SIGTERM, _interrupt)
        except ValueError:
            previous = None     # not the main thread (e.g. called from a test runner)
        drive = load(args)
        if not args.quiet:
            print(f'gnsscam_convert: {drive.name} -> {args.out}', file=sys.stderr)
        summary = convert_drive(drive, args.out, storage=args.storage,
                                progress=None if args.quiet else ProgressLine(),
                                namespace=args.namespace, workers=args.workers)
    except KeyboardInterrupt:
        # Cleanup is done; a signal still pending (OpenCV and writer threads may have
        # caught a copy) must not turn exit code 130 into death by SIGINT at shutdown.
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                signal.signal(sig, signal.SIG_IGN)
            except ValueError:
                break           # not the main thread
        previous = None
        print(f'\ngnsscam_convert: interrupted; no bag written at {args.out}',
              file=sys.stderr)
        return EXIT_INTERRUPTED
    except (DatasetError, BagContentError) as err:
        print(f'gnsscam_convert: {err}', file=sys.stderr)
        return EXIT_INPUT
    except (BagExistsError, BagError, OSError) as err:
        print(f'gnsscam_convert: {err}', file=sys.stderr)
        return EXIT_OUTPUT
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    print(format_summary(summary))
    if args.json is not None:
        try:
            write_json_atomic(args.json, summary.as_dict())
        except (OSError, ValueError) as err:
            # The bag is complete and stays; only the summary file is missing.
            print(f'gnsscam_convert: cannot write {args.json}: {err}', file=sys.stderr)
            return EXIT_OUTPUT
    return EXIT_OK


if __name__ == '__main__':
    sys.exit(main())
