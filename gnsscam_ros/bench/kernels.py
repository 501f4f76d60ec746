"""``python -m gnsscam_ros.bench.kernels``: time the compiled camera and posterior kernels.

Prints median wall times [ms] of

* the posterior statistics of one epoch (pooled moments of posteriors and priors and
  their KL, hazard mass, risk bound, threshold and protection level) at S = 10 motion
  samples of N = 10,000 particles with M = 10 posteriors, and at the default
  configuration's sizes (S = 10, N = 4,000, M = 200 today);
* the camera fusion of K = 10 matches at S = 10, N = 10,000;

each next to the numpy implementation they replaced (``test/oracles.py`` of a source
checkout; left out when it is not there), and the time to compile the kernels (an empty
numba cache) and to load them from the cache, each in a fresh process.
"""
from __future__ import annotations

import argparse
import importlib
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.special import logsumexp

from .filter import median_ms as _median_ms
from ..core import integrity
from ..core.config import FilterConfig
from ..core.fusion import camera_fusion

TEST_DIR = Path(__file__).resolve().parents[2] / 'test'
_WARM_UP = ('import time; t0 = time.perf_counter(); '
            'from gnsscam_ros.core.kernels import camera, posterior; '
            't1 = time.perf_counter(); camera.warm_up(); t2 = time.perf_counter(); '
            'posterior.warm_up(); t3 = time.perf_counter(); '
            'print(t1 - t0, t2 - t1, t3 - t2)')


def _oracles():
    """``test/oracles.py`` of a source checkout, or None."""
    if not (TEST_DIR / 'oracles.py').is_file():
        return None
    sys.path.insert(0, str(TEST_DIR))
    try:
        return importlib.import_module('oracles')
    finally:
        sys.path.remove(str(TEST_DIR))


def posterior_case(rng: np.random.Generator, s: int, n: int, m: int):
    """Posteriors (Dirichlet weights, bias offsets) and priors (uniform weights) over S
    samples of N particles, as ``ParticleFilter._integrity`` builds them."""
    particles = np.empty((s, n, 4))
    particles[..., :3] = [3000.0, -2000.0, 40.0] + rng.normal(0.0, 5.0, (s, n, 3))
    particles[..., 3] = rng.uniform(-np.pi, np.pi, (s, n))
    pos = particles[..., :3]
    log_w = np.log(rng.dirichlet(np.full(n, 0.5), s))
    index = np.arange(m) % s
    posteriors = integrity.PosteriorSet(pos, log_w, index, rng.normal(0.0, 2.0, (m, 3)))
    priors = integrity.PosteriorSet(pos, np.broadcast_to(np.full(n, -np.log(n)), (s, n)),
                                    index, rng.normal(0.0, 2.0, (m, 3)))
    return posteriors, priors


def integrity_epoch(posteriors, priors, mean, limits, target: float, delta: float):
    """The risk bound and protection level as ``ParticleFilter._integrity`` computes them."""
    kl = posteriors.divergence_from(priors)
    m = posteriors.n_posteriors
    q_max = integrity.max_empirical_risk(target, integrity.divergence_budget(kl, m, delta))
    empirical, level = posteriors.risk_and_level(mean, limits, q_max)
    return integrity.risk_bound(empirical, kl, m, delta).risk_bound, level


def camera_case(rng: np.random.Generator, s: int, n: int, k: int):
    particles = np.empty((s, n, 4))
    particles[..., :3] = [3000.0, -2000.0, 40.0] + rng.normal(0.0, 5.0, (s, n, 3))
    particles[..., 3] = 0.0
    matches = [3000.0, -2000.0, 40.0] + rng.normal(0.0, 8.0, (k, 3))
    joint = rng.normal(0.0, 3.0, (s, n))
    return particles, matches, joint - logsumexp(joint, axis=1, keepdims=True)


def compile_times() -> tuple[list[float], list[float]]:
    """Seconds of (import, camera warm-up, posterior warm-up) in a fresh process with an
    empty numba cache (compilation), then again with that cache (loading)."""
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        runs = []
        for _ in range(2):
            out = subprocess.run([sys.executable, '-c', _WARM_UP], env=env, check=True,
                                 capture_output=True, text=True).stdout
            runs.append([float(v) for v in out.split()])
    return runs[0], runs[1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m gnsscam_ros.bench.kernels',
                                     description=__doc__.split('\n')[0])
    parser.add_argument('--repeats', type=int, default=20)
    parser.add_argument('--no-compile', action='store_true',
                        help='skip the compile and cache-load timing (two processes)')
    args = parser.parse_args(argv)
    oracles = _oracles()
    rng = np.random.default_rng(0)
    limits = np.array([8.0])
    rows = []
    # The default configuration's sizes read from it, so that the row follows the default.
    defaults = FilterConfig()
    default_sizes = (defaults.n_motion_samples, defaults.n_particles, defaults.n_posteriors)
    for s, n, m in ((10, 10_000, 10), default_sizes):
        posteriors, priors = posterior_case(rng, s, n, m)
        mean = np.array([3000.3, -2000.1, 40.0])
        # M = 10 cannot certify 0.1 (q_max = 0, no level): a target it can meet.
        target = 0.1 if integrity.certifiable_target(m, 0.1, 1.0) < 0.1 else 0.5
        new = _median_ms(lambda: integrity_epoch(posteriors, priors, mean, limits, target,
                                                 0.1), args.repeats)
        old = float('nan') if oracles is None else _median_ms(
            lambda: oracles.integrity_epoch(posteriors, priors, mean, limits, target, 0.1),
            args.repeats)
        rows.append((f'posterior statistics S={s} N={n} M={m} (target {target:g})', old,
                     new))
    particles, matches, log_p = camera_case(rng, 10, 10_000, 10)
    new = _median_ms(lambda: camera_fusion(particles, matches, log_p, 5.0, 20.0, 5.0, 1e-3),
                     args.repeats)
    old = float('nan') if oracles is None else _median_ms(
        lambda: oracles.fuse_camera(log_p, oracles.camera_log_q(particles, matches, 5.0,
                                                                20.0), 5.0, 1e-3),
        args.repeats)
    rows.append(('camera fusion K=10 S=10 N=10000', old, new))
    print(f'{"":52s} {"numpy ms":>9s} {"kernel ms":>9s} {"speed-up":>8s}')
    for name, old, new in rows:
        print(f'{name:52s} {old:9.2f} {new:9.2f} {old / new:7.1f}x')
    if not args.no_compile:
        compiled, cached = compile_times()
        for label, run in (('compile (empty cache)', compiled), ('load (cached)', cached)):
            print(f'{label:22s} import {run[0]:.2f} s, camera {run[1]:.2f} s, '
                  f'posterior {run[2]:.2f} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
