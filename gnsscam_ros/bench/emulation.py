"""Speed of the emulated dataset: ``python -m gnsscam_ros.bench.emulation``.

Prints the wall time of

* generating a whole emulated drive (truth, IMU, odometry, GNSS with faults), after a
  warm-up drive of another seed (imports, caches), median of ``--repeats`` runs;
* setting up its camera stream (poses, faults, exposure; no rendering);
* rendering its first ``--frames`` camera frames, cold (a fresh stream: the facade
  textures are generated on the way) and warm (the same frames again, textures cached).

For reference, the renderer was measured at ~5 ms per frame cold and ~4 ms warm, and a
whole drive takes well under 2 s (the bounds the tests used to assert).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time

from ..datasets.emulated.camera import make_camera_stream
from ..datasets.emulated.drive import make_emulated_drive
from ..datasets.emulated.scenario import make_scenario
from ..io.tables import format_table


def _seconds(fn, *args, **kwargs) -> tuple[float, object]:
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    return time.perf_counter() - t0, out


def bench(seed: int = 9, repeats: int = 3, frames: int = 100) -> dict:
    """Time drive generation, camera-stream set-up and frame rendering.

    Args:
        seed: Drive seed (the warm-up drive uses ``seed - 1``).
        repeats: Drives generated for the median.
        frames: Camera frames rendered, from the first one.

    Returns:
        ``{'drive_s', 'drive_s_min', 'epochs', 'stream_s', 'frames', 'render_cold_ms',
        'render_warm_ms'}`` (times per drive [s] and per frame [ms]).
    """
    make_emulated_drive(seed - 1)                  # warm-up: imports, caches
    times = []
    for _ in range(max(1, repeats)):
        dt, drive = _seconds(make_emulated_drive, seed, faults=4)
        times.append(dt)
    scenario = make_scenario(seed)
    stream_s, stream = _seconds(make_camera_stream, scenario)
    n = min(max(1, frames), len(stream))
    cold_s, _ = _seconds(lambda: [stream.clean_image(i) for i in range(n)])
    warm_s, _ = _seconds(lambda: [stream.clean_image(i) for i in range(n)])
    return {'drive_s': statistics.median(times), 'drive_s_min': min(times),
            'epochs': len(drive.gnss), 'stream_s': stream_s, 'frames': n,
            'render_cold_ms': 1e3 * cold_s / n, 'render_warm_ms': 1e3 * warm_s / n}


def main(argv: list[str] | None = None) -> int:
    """Print the figures of :func:`bench`."""
    parser = argparse.ArgumentParser(prog='python -m gnsscam_ros.bench.emulation',
                                     description=__doc__.split('\n')[0])
    parser.add_argument('--seed', type=int, default=9, help='drive seed (default 9)')
    parser.add_argument('--repeats', type=int, default=3,
                        help='drives generated for the median (default 3)')
    parser.add_argument('--frames', type=int, default=100,
                        help='camera frames rendered (default 100)')
    args = parser.parse_args(argv)
    r = bench(args.seed, args.repeats, args.frames)
    print(format_table(['step', 'time', 'unit'], [
        [f'whole drive, seed {args.seed}, 4 faults ({r["epochs"]} epochs), median',
         r['drive_s'], 's'],
        ['whole drive, fastest', r['drive_s_min'], 's'],
        ['camera stream set-up (no rendering)', r['stream_s'], 's'],
        [f'render, first {r["frames"]} frames, cold', r['render_cold_ms'], 'ms/frame'],
        [f'render, same {r["frames"]} frames, warm', r['render_warm_ms'], 'ms/frame'],
    ]))
    return 0


if __name__ == '__main__':
    sys.exit(main())
