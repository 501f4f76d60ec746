"""``gnsscam_bench``: time one GNSS epoch of the filter and the bare likelihood arithmetic.

Prints, for each particle count N per posterior (M posteriors, 12 satellites), the median
wall time of a full filter epoch through the epoch engine (propagate, clock, likelihood,
choice, risk bound and protection level, resampling), the same with 10 camera matches per
epoch, and the bare arithmetic on the same number of likelihood evaluations (ranges plus a
Gaussian log-sum-exp over satellites, plain numpy: the yardstick), timed in turn with the
epoch so that each ratio is the median of ratios taken in the same round; then the
package's default configuration, timed the same way; then the peak resident memory.
Kernels are compiled (or loaded from the cache) before anything is timed, and the time
that took is printed.
"""
from __future__ import annotations

import argparse
import resource
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..core.engine import EpochEngine
from ..core.filter import BIAS_MODELS, FilterConfig
from ..core.frames import LocalFrame
from ..core.fusion import CameraMeasurement
from ..core.gnss import prepare_epoch
from ..core.motion import DeadReckoningState
from ..core.warmup import warm_up_kernels
from ..datasets.emulated.drive import make_emulated_drive
from ..io.atomic import OutputExistsError, write_json_atomic
from ..io.provenance import provenance
from ..io.tables import format_table

DEFAULT_COUNTS = (120, 1000, 10000, 100000)
#: Posteriors M of the rows (the issue's yardstick: M = 10) and camera matches per epoch.
BENCH_POSTERIORS = 10
CAMERA_MATCHES = 10
#: Timed calls of one function per turn (after one untimed call), :func:`interleaved_times_ms`.
BLOCK_CALLS = 2


def median_ms(fn, repeats: int) -> float:
    """Median wall time of ``fn`` over ``repeats`` calls after a first one (warm-up:
    allocations, caches, kernel compilation or cache load) [ms]: one round of
    :func:`interleaved_times_ms` with one function."""
    return float(interleaved_times_ms({'fn': fn}, 1, block=repeats)['fn'][0])


def interleaved_times_ms(fns: dict, repeats: int, block: int = BLOCK_CALLS) -> dict:
    """Wall times [ms] of each function of ``fns`` over ``repeats`` rounds, the functions
    taking turns within each round: ``{name: (repeats,)}``, each entry the median of
    ``block`` calls after one untimed call (its caches warm again after the others ran).

    Timed in turn, the epoch and its yardstick see the same machine: a clock or cache
    state that drifts over the run (seen here: the bare arithmetic at N = 10,000 took
    26-42 ms in runs a minute apart) moves both, not one.
    """
    times = {name: np.empty(repeats) for name in fns}
    for i in range(repeats):
        for name, fn in fns.items():
            fn()
            calls = np.empty(block)
            for j in range(block):
                start = time.perf_counter()
                fn()
                calls[j] = time.perf_counter() - start
            times[name][i] = float(np.median(calls)) * 1e3
    return times


def paired_ratio(times_ms: dict, numerator: str, denominator: str) -> float:
    """Median over the rounds of ``numerator``'s time over ``denominator``'s in the same
    round (:func:`interleaved_times_ms`)."""
    return float(np.median(times_ms[numerator] / times_ms[denominator]))


def bare_likelihood(positions_m: np.ndarray, prep) -> np.ndarray:
    """The reference arithmetic: ranges and a Gaussian log-sum-exp over satellites."""
    # Written lean on purpose (max shift by hand, no scipy overhead) so that the reference
    # is not slower than it needs to be.
    # Ranges as |s|^2 - 2 p.s + |p|^2: one matrix product, numpy's fastest form.
    sv = prep.sv_enu_m
    sq = positions_m @ (-2.0 * sv.T)
    sq += (sv * sv).sum(1)
    sq += np.einsum('ij,ij->i', positions_m, positions_m)[:, None]
    z = (prep.pr_m - np.sqrt(sq, out=sq)) / prep.sigma_m
    a = -0.5 * z * z - np.log(prep.sigma_m)
    a_max = a.max(axis=1)
    return a_max + np.log(np.exp(a - a_max[:, None]).sum(axis=1))


def straight_state(stamp_ns: int, x_m: float, previous: DeadReckoningState | None = None
                   ) -> DeadReckoningState:
    """A dead-reckoning state of a vehicle driving straight along x at 8 m/s."""
    var = (0.0, 0.0) if previous is None else (previous.distance_var_m2 + 0.01,
                                               previous.yaw_var_rad2 + 1e-5)
    return DeadReckoningState(stamp_ns=stamp_ns, x_m=x_m, y_m=0.0, yaw_rad=0.0, speed_mps=8.0,
                              yaw_rate_rps=0.0, speed_var=0.0025, yaw_rate_var=1e-4,
                              distance_var_m2=var[0], yaw_var_rad2=var[1])


def _timed_engine(config: FilterConfig, epochs: list, frame: LocalFrame, seed: int,
                  camera_matches: int):
    """The report of an engine's first epoch, and a function that runs one more epoch
    (the first returned as a one-item list that each call updates to the latest).

    Every call advances the stamp by 1 s with 8 m of dead reckoning (through the engine,
    as fusion_node) and, with ``camera_matches``, that many camera matches spread over
    the interval, each within a few metres of the current estimate (matches that agree
    with GNSS: the fusion is computed, not excluded).
    """
    engine = EpochEngine(config, frame=frame, rng=np.random.default_rng(seed))
    rng = np.random.default_rng(seed + 1)
    state = {'i': 1, 'dr': straight_state(epochs[0].stamp_ns - 1_000_000_000, 0.0)}
    engine.add_dead_reckoning(state['dr'])
    engine.add_gnss(epochs[0])
    latest = list(engine.ready_reports())

    def one_epoch():
        template = epochs[state['i'] % len(epochs)]
        previous = latest[-1].result.stamp_ns
        stamp = previous + 1_000_000_000
        state['dr'] = straight_state(stamp, state['dr'].x_m + 8.0, state['dr'])
        engine.add_dead_reckoning(state['dr'])
        centre = latest[-1].result.position_enu_m
        for j in range(camera_matches):
            at = previous + (j + 1) * (1_000_000_000 // camera_matches)
            engine.add_camera(at, CameraMeasurement(
                stamp_ns=at, position_enu_m=centre + rng.normal(scale=3.0, size=3),
                score=1.0, frame_id=state['i'] * camera_matches + j))
        engine.add_gnss(replace(template, stamp_ns=stamp))
        latest[:] = list(engine.ready_reports())[-1:] or latest
        state['i'] += 1

    return latest, one_epoch


def _repeats(evaluations: int, repeats: int) -> int:
    return max(3, min(repeats, int(2e6 // evaluations) + 3))


def _bare_fn(latest: list, epoch, frame: LocalFrame, config: FilterConfig,
             evaluations: int):
    """The bare arithmetic over ``evaluations`` positions of the motion samples of the
    latest report (``latest[-1]``, an update), as a function to time."""
    positions = latest[-1].posterior_set.positions_m.reshape(-1, 3)
    positions = np.ascontiguousarray(np.resize(positions, (evaluations, 3)))
    prep = prepare_epoch(epoch, frame, positions.mean(0), config.measurement_var_m2, False)
    return lambda: bare_likelihood(positions, prep)


def bench(counts=DEFAULT_COUNTS, n_posteriors: int = BENCH_POSTERIORS,
          likelihood: str | None = None, repeats: int = 15, seed: int = 0,
          bias_model: str | None = None, camera_matches: int = CAMERA_MATCHES,
          default_config: bool = True) -> dict:
    """Median epoch times [ms] per particle count (GNSS only and with camera matches),
    the bare arithmetic's, and the package's default configuration.

    The rows use ``n_posteriors`` (default 10) and the package's bias model; the
    likelihood is evaluated for the motion samples only (``evaluations``, the size of the
    bare arithmetic)."""
    started = time.perf_counter()
    warm_up_kernels()
    warm_up_s = time.perf_counter() - started
    defaults = FilterConfig()
    bias_model = defaults.bias_model if bias_model is None else bias_model
    drive = make_emulated_drive(seed, faults=4, duration_s=60.0)
    epochs = [e for e in drive.gnss if e.n_sv == 12]
    frame = LocalFrame(*drive.origin_llh)
    rows = {}
    for n in counts:
        config = FilterConfig(n_particles=n, n_posteriors=n_posteriors,
                              acquisition_particles=0, bias_model=bias_model)
        if likelihood is not None:
            config = replace(config, likelihood=likelihood)
        evaluations = n * config.motion_sample_count
        reps = _repeats(evaluations, repeats)
        latest, one_epoch = _timed_engine(config, epochs, frame, seed, 0)
        # Epoch, camera epoch and yardstick in turn: each ratio pairs times of one round.
        fns = {'epoch': one_epoch}
        if camera_matches:
            fns['camera'] = _timed_engine(config, epochs, frame, seed, camera_matches)[1]
        fns['bare'] = _bare_fn(latest, epochs[1], frame, config, evaluations)
        times = interleaved_times_ms(fns, reps)
        rows[n] = {'epoch_ms': float(np.median(times['epoch'])),
                   'camera_epoch_ms': (float(np.median(times['camera']))
                                       if camera_matches else float('nan')),
                   'bare_likelihood_ms': float(np.median(times['bare'])),
                   'ratio': paired_ratio(times, 'epoch', 'bare'),
                   'camera_ratio': (paired_ratio(times, 'camera', 'bare')
                                    if camera_matches else float('nan')),
                   'evaluations': evaluations, 'likelihood': config.likelihood}
    result = {'epoch_ms_median': {str(n): r['epoch_ms'] for n, r in rows.items()},
              'camera_epoch_ms_median': {str(n): r['camera_epoch_ms']
                                         for n, r in rows.items()},
              'bare_likelihood_ms_median': {str(n): r['bare_likelihood_ms']
                                            for n, r in rows.items()},
              'details': {str(n): r for n, r in rows.items()},
              'n_posteriors': n_posteriors, 'bias_model': bias_model, 'satellites': 12,
              'camera_matches': camera_matches, 'kernel_warm_up_s': warm_up_s}
    if default_config:
        result['default_config'] = _default_config(defaults, epochs, frame, seed, repeats)
    result['peak_rss_mb'] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return result


def _default_config(config: FilterConfig, epochs: list, frame: LocalFrame, seed: int,
                    repeats: int) -> dict:
    """The package's default configuration (heading acquisition over: the working size),
    against the bare arithmetic at M * N evaluations (posteriors times particles) and at
    S * N (what its likelihood evaluates)."""
    config = replace(config, acquisition_particles=0)
    n, m, s = config.n_particles, config.n_posteriors, config.motion_sample_count
    latest, one_epoch = _timed_engine(config, epochs, frame, seed, 0)
    times = interleaved_times_ms(
        {'epoch': one_epoch, 'mn': _bare_fn(latest, epochs[1], frame, config, m * n),
         'sn': _bare_fn(latest, epochs[1], frame, config, s * n)},
        _repeats(n * s, repeats))
    return {'n_particles': n, 'n_posteriors': m, 'motion_samples': s,
            'epoch_ms_median': float(np.median(times['epoch'])),
            'bare_likelihood_ms_at_mn': float(np.median(times['mn'])),
            'bare_likelihood_ms_at_sn': float(np.median(times['sn'])),
            'ratio_at_mn': paired_ratio(times, 'epoch', 'mn'),
            'ratio_at_sn': paired_ratio(times, 'epoch', 'sn')}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='gnsscam_bench', description=__doc__.split('\n')[0])
    parser.add_argument('--particles', type=int, nargs='+', default=list(DEFAULT_COUNTS),
                        help='particle counts per posterior (default %(default)s)')
    parser.add_argument('--posteriors', type=int, default=BENCH_POSTERIORS,
                        help='posteriors M of the rows (default %(default)s)')
    parser.add_argument('--bias-model', choices=BIAS_MODELS, default=None,
                        help="bias model of the rows (default: the package's); 'none': "
                             'every posterior its own motion sample (the paper)')
    parser.add_argument('--likelihood', choices=('robust', 'particle_raim'), default=None)
    parser.add_argument('--camera-matches', type=int, default=CAMERA_MATCHES,
                        help='camera matches per epoch of the camera rows (0: none; '
                             'default %(default)s)')
    parser.add_argument('--no-default-config', action='store_true',
                        help="skip the package's default configuration")
    parser.add_argument('--json', type=Path, help='write the figures as JSON')
    parser.add_argument('--force', action='store_true', help='replace an existing --json')
    args = parser.parse_args(argv)
    if args.json is not None and args.json.exists() and not args.force:
        print(f'gnsscam_bench: {args.json} exists; pass --force to replace it',
              file=sys.stderr)
        return 4
    # glibc's default allocator settings for both the epoch and the bare arithmetic (the
    # yardstick is what it was; fusion_node keeps freed epoch arrays: nodes/memory.py).
    result = bench(args.particles, args.posteriors, args.likelihood,
                   bias_model=args.bias_model, camera_matches=args.camera_matches,
                   default_config=not args.no_default_config)
    print(f"kernels ready in {result['kernel_warm_up_s']:.2f} s (compiled or loaded from "
          'the cache)')
    print(f"M = {result['n_posteriors']} posteriors, bias model {result['bias_model']}; "
          'M*N below counts likelihood evaluations (the motion samples); camera: '
          f"{result['camera_matches']} matches per epoch")
    rows = [[n, d['evaluations'], d['epoch_ms'], d['bare_likelihood_ms'], d['ratio'],
             d['camera_epoch_ms'], d['camera_ratio'],
             d['epoch_ms'] / d['evaluations'] * 1e3]
            for n, d in result['details'].items()]
    print(format_table(['N/posterior', 'M*N', 'epoch [ms]', 'bare lik [ms]', 'ratio',
                        'camera epoch [ms]', 'camera ratio', 'us per 1k evals'], rows))
    default = result.get('default_config')
    if default:
        print(f"default configuration (N = {default['n_particles']}, M = "
              f"{default['n_posteriors']} posteriors from {default['motion_samples']} "
              f"motion samples): epoch {default['epoch_ms_median']:.2f} ms; bare arithmetic "
              f"at M*N {default['bare_likelihood_ms_at_mn']:.2f} ms (ratio "
              f"{default['ratio_at_mn']:.2f}), at S*N {default['bare_likelihood_ms_at_sn']:.2f}"
              f" ms (ratio {default['ratio_at_sn']:.2f})")
    print(f"peak RSS: {result['peak_rss_mb']:.0f} MB")
    if args.json is not None:
        # When, where and how (the load average at the start says if it ran alone).
        result = {'command': 'bench', **provenance('gnsscam_bench', argv if argv is not None
                                                   else sys.argv[1:]), **result}
        try:
            write_json_atomic(args.json, result, force=args.force)
        except (OSError, OutputExistsError) as err:
            print(f'gnsscam_bench: cannot write {args.json}: {err}', file=sys.stderr)
            return 4
    return 0


if __name__ == '__main__':
    sys.exit(main())
