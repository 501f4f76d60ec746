"""``gnsscam_bench``: time one GNSS epoch of the filter and the bare likelihood arithmetic.

Prints, for each particle count N per posterior (M posteriors, 12 satellites), the median
wall time of a full filter epoch (propagate, clock, likelihood, EM weights, choice,
risk bound, resampling) next to the bare arithmetic on the same M*N array (ranges plus a
Gaussian log-sum-exp over satellites), and the peak resident memory.
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
from ..core.filter import FilterConfig
from ..core.frames import LocalFrame
from ..core.gnss import prepare_epoch
from ..core.motion import DeadReckoningState
from ..datasets.emulated.drive import make_emulated_drive
from ..io.atomic import OutputExistsError, write_json_atomic
from ..io.tables import format_table

DEFAULT_COUNTS = (120, 1000, 10000, 100000)


def _median_ms(fn, repeats: int) -> float:
    fn()                                   # warm-up: allocations, caches
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return float(np.median(times) * 1e3)


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


def bench(counts=DEFAULT_COUNTS, n_posteriors: int | None = None,
          likelihood: str | None = None, repeats: int = 15, seed: int = 0,
          bias_model: str | None = None) -> dict:
    """Median epoch times [ms] per particle count, and the bare arithmetic's.

    ``n_posteriors`` and ``bias_model`` default to the package's (M = 200 posteriors from
    10 motion samples with bias hypotheses); the likelihood is evaluated for the motion
    samples only (``evaluations``)."""
    defaults = FilterConfig()
    n_posteriors = defaults.n_posteriors if n_posteriors is None else n_posteriors
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
        engine = EpochEngine(config, frame=frame, rng=np.random.default_rng(seed))
        filt = engine.filter
        state = {'i': 1, 'dr': straight_state(epochs[0].stamp_ns - 1_000_000_000, 0.0)}
        engine.add_dead_reckoning(state['dr'])
        engine.add_gnss(epochs[0])
        list(engine.ready_reports())

        def one_epoch():
            # Advance the stamp every call so each call is a fresh, valid epoch, with 8 m
            # of dead reckoning over the interval (through the engine, as fusion_node).
            template = epochs[state['i'] % len(epochs)]
            stamp = filt.last_stamp_ns + 1_000_000_000
            state['dr'] = straight_state(stamp, state['dr'].x_m + 8.0, state['dr'])
            engine.add_dead_reckoning(state['dr'])
            engine.add_gnss(replace(template, stamp_ns=stamp))
            list(engine.ready_reports())
            state['i'] += 1

        evaluations = n * config.motion_sample_count
        reps = max(3, min(repeats, int(2e6 // evaluations) + 3))
        epoch_ms = _median_ms(one_epoch, reps)
        positions = np.ascontiguousarray(filt.posteriors[..., :3].reshape(-1, 3))
        prep = prepare_epoch(epochs[1], frame, positions.mean(0), config.measurement_var_m2,
                             False)
        bare_ms = _median_ms(lambda: bare_likelihood(positions, prep), reps)
        rows[n] = {'epoch_ms': epoch_ms, 'bare_likelihood_ms': bare_ms,
                   'ratio': epoch_ms / bare_ms, 'evaluations': evaluations,
                   'likelihood': config.likelihood}
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return {'epoch_ms_median': {str(n): r['epoch_ms'] for n, r in rows.items()},
            'bare_likelihood_ms_median': {str(n): r['bare_likelihood_ms']
                                          for n, r in rows.items()},
            'details': {str(n): r for n, r in rows.items()},
            'n_posteriors': n_posteriors, 'bias_model': bias_model, 'satellites': 12,
            'peak_rss_mb': peak_mb}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='gnsscam_bench', description=__doc__.split('\n')[0])
    parser.add_argument('--particles', type=int, nargs='+', default=list(DEFAULT_COUNTS),
                        help='particle counts per posterior (default %(default)s)')
    parser.add_argument('--posteriors', type=int, default=None,
                        help='posteriors M (default: the package default)')
    parser.add_argument('--bias-model', choices=('cn0', 'none'), default=None,
                        help="'none': every posterior its own motion sample (the paper)")
    parser.add_argument('--likelihood', choices=('robust', 'particle_raim'), default=None)
    parser.add_argument('--json', type=Path, help='write the figures as JSON')
    parser.add_argument('--force', action='store_true', help='replace an existing --json')
    args = parser.parse_args(argv)
    if args.json is not None and args.json.exists() and not args.force:
        print(f'gnsscam_bench: {args.json} exists; pass --force to replace it',
              file=sys.stderr)
        return 4
    result = bench(args.particles, args.posteriors, args.likelihood,
                   bias_model=args.bias_model)
    print(f"M = {result['n_posteriors']} posteriors, bias model {result['bias_model']}; "
          'M*N below counts likelihood evaluations (the motion samples)')
    rows = [[n, d['evaluations'], d['epoch_ms'], d['bare_likelihood_ms'], d['ratio'],
             d['epoch_ms'] / d['evaluations'] * 1e3]
            for n, d in result['details'].items()]
    print(format_table(['N/posterior', 'M*N', 'epoch [ms]', 'bare lik [ms]', 'ratio',
                        'us per 1k evals'], rows))
    print(f"peak RSS: {result['peak_rss_mb']:.0f} MB")
    if args.json is not None:
        try:
            write_json_atomic(args.json, result, force=args.force)
        except (OSError, OutputExistsError) as err:
            print(f'gnsscam_bench: cannot write {args.json}: {err}', file=sys.stderr)
            return 4
    return 0


if __name__ == '__main__':
    sys.exit(main())
