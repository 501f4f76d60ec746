"""Epoch-time tails: the garbage collector's full collections over a long run of epochs.

Runs ``--epochs`` GNSS epochs of the bench's emulated drive (``gnsscam_bench``'s engine
loop; the default configuration at ``--particles`` per posterior) in two child processes,
each with the package's node modules imported and its kernels warmed up as a node process
has them: one as that leaves it, one after :func:`gnsscam_ros.nodes.memory.
freeze_start_up_objects` (what the node processes do once their nodes are built). Prints
per process the objects the collector tracks, the median, 99.9th percentile and largest
epoch time, the full (generation 2) collections the collector started itself (how many,
and the longest) and what one full collection costs at the end (forced). A full
collection walks every tracked object, and in a started node there are some 150,000; the
collector starts one when the objects that survived since the last exceed a quarter of
the long-lived ones, so whether a run meets one depends on what the process did before.
"""
from __future__ import annotations

import argparse
import gc
import json
import subprocess
import sys
import time

import numpy as np

from ..core.filter import FilterConfig
from ..core.frames import LocalFrame
from ..core.warmup import warm_up_kernels
from ..datasets.emulated.drive import make_emulated_drive
from ..nodes.memory import freeze_start_up_objects
from .filter import _timed_engine

try:                                        # what a node process has imported
    import gnsscam_ros.nodes.pipeline  # noqa: F401
except ImportError:                         # no rclpy here: the package's core only
    pass

MODES = ('as started', 'frozen')


def _child(mode: str, epochs: int, particles: int) -> dict:
    """One process's run (``mode`` of :data:`MODES`), as a dict."""
    warm_up_kernels()
    drive = make_emulated_drive(0, faults=4, duration_s=60.0)
    frame = LocalFrame(*drive.origin_llh)
    config = FilterConfig(n_particles=particles, acquisition_particles=0)
    _, one_epoch = _timed_engine(config, [e for e in drive.gnss if e.n_sv == 12], frame, 0,
                                 0)
    for _ in range(20):
        one_epoch()
    if mode == 'frozen':
        freeze_start_up_objects()
    tracked = len(gc.get_objects())
    full_ms: list[float] = []
    started: list[float] = []

    def on_collection(phase: str, info: dict) -> None:
        if info['generation'] != 2:
            return
        if phase == 'start':
            started[:] = [time.perf_counter()]
        elif started:
            full_ms.append((time.perf_counter() - started[0]) * 1e3)

    gc.callbacks.append(on_collection)
    times = np.empty(epochs)
    for i in range(epochs):
        start = time.perf_counter()
        one_epoch()
        times[i] = (time.perf_counter() - start) * 1e3
    gc.callbacks.remove(on_collection)
    start = time.perf_counter()
    gc.collect()                            # what one full collection costs this process
    forced_ms = (time.perf_counter() - start) * 1e3
    return {'mode': mode, 'tracked_objects': tracked, 'epochs': epochs,
            'epoch_ms_median': float(np.median(times)),
            'epoch_ms_p999': float(np.percentile(times, 99.9)),
            'epoch_ms_max': float(times.max()), 'full_collections': len(full_ms),
            'full_collection_ms_max': max(full_ms, default=0.0),
            'forced_full_collection_ms': forced_ms}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m gnsscam_ros.bench.pauses',
                                     description=__doc__.split('\n')[0])
    parser.add_argument('--epochs', type=int, default=3000, help='epochs per process')
    parser.add_argument('--particles', type=int, default=120,
                        help='particles per posterior N (default 120: the fixed costs)')
    parser.add_argument('--child', choices=MODES, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.epochs < 1 or args.particles < 2:
        parser.error('--epochs must be at least 1 and --particles at least 2')
    if args.child:
        print(json.dumps(_child(args.child, args.epochs, args.particles)))
        return 0
    rows = []
    for mode in MODES:
        out = subprocess.run([sys.executable, '-m', 'gnsscam_ros.bench.pauses', '--child',
                              mode, '--epochs', str(args.epochs), '--particles',
                              str(args.particles)], capture_output=True, text=True)
        if out.returncode != 0:
            print(out.stderr, file=sys.stderr)
            return out.returncode
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    print(f'{args.epochs} epochs per process, N = {args.particles}')
    print(f'{"process":>11} {"tracked":>8} {"median [ms]":>11} {"p99.9 [ms]":>10} '
          f'{"max [ms]":>9} {"full collections":>16} {"longest [ms]":>12} '
          f'{"one forced [ms]":>15}')
    for r in rows:
        print(f'{r["mode"]:>11} {r["tracked_objects"]:>8} {r["epoch_ms_median"]:>11.2f} '
              f'{r["epoch_ms_p999"]:>10.2f} {r["epoch_ms_max"]:>9.2f} '
              f'{r["full_collections"]:>16} {r["full_collection_ms_max"]:>12.2f} '
              f'{r["forced_full_collection_ms"]:>15.3f}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
