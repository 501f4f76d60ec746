"""The snapshot solution of one epoch (``core.consistency.snapshot_position``) in one
compiled pass: its Gauss-Newton and reweighted least-squares steps, each numpy's
arithmetic to the bit (``robust_snapshot``).
"""
from __future__ import annotations

import math

import numpy as np

from . import kernel

#: float64 machine epsilon (numpy's lstsq cut-off is ``eps * max(rows, columns)``).
_EPS = float(np.finfo(np.float64).eps)


@kernel
def robust_snapshot(sv, pr, sigma, sys_index, n_systems, start, plain_steps, robust_steps,
                    cauchy_scale, x):
    """Snapshot position of one epoch: ``plain_steps`` Gauss-Newton steps of weighted
    least squares, then ``robust_steps`` of iteratively reweighted least squares with a
    Cauchy loss of scale ``cauchy_scale * sigma`` (``core.consistency.snapshot_position``
    says why). The unknowns are the position and one clock per constellation, the clocks
    estimated afresh at every step. Writes the position into ``x`` (3,); returns False
    where there is none (non-finite or absurd input, a non-finite system, a non-finite
    result).

    Each step is numpy's arithmetic, operation for operation, and its least squares is
    LAPACK's ``gelsd`` as numpy's ``lstsq`` calls it (numba's ``np.linalg.lstsq``, the
    same cut-off ``rcond = eps * max(k, n)``): the solution is numpy's to the bit. That
    matters: ranges of 2e7 m round to 4e-9 m, so a solver that differed in the last bits
    moved the solution by nanometres, and through the error model that learns from its
    residuals, the filter's estimate by 1e-7 m (the reference epochs, which hold it to
    1e-9). The least squares is the one BLAS/LAPACK use of the kernels; a system of a
    dozen rows runs on the calling thread.

    Args:
        sv: (k, 3) satellite positions [m].
        pr: (k,) pseudoranges [m].
        sigma: (k,) error standard deviations [m].
        sys_index: (k,) constellation of each satellite.
        n_systems: Number of constellations.
        start: (3,) linearisation point [m].
    """
    k = pr.shape[0]
    n = 3 + n_systems
    # A poisoned state (a non-finite or absurd starting point) has no snapshot solution.
    for a in range(3):
        if not (np.isfinite(start[a]) and abs(start[a]) < 1e8):
            return False
    for j in range(k):
        if not (np.isfinite(sv[j, 0]) and np.isfinite(sv[j, 1]) and np.isfinite(sv[j, 2])
                and np.isfinite(pr[j]) and np.isfinite(sigma[j]) and sigma[j] > 0.0):
            return False
    rcond = _EPS * max(k, n)
    jac = np.zeros((k, n))
    a_w = np.empty((k, n))
    b_w = np.empty(k)
    resid = np.empty(k)
    robust_w = np.ones(k)
    for a in range(3):
        x[a] = start[a]
    for j in range(k):
        jac[j, 3 + sys_index[j]] = 1.0
    for step in range(plain_steps + robust_steps):
        for j in range(k):
            ox, oy, oz = sv[j, 0] - x[0], sv[j, 1] - x[1], sv[j, 2] - x[2]
            rng = math.sqrt((ox * ox + oy * oy) + oz * oz)
            jac[j, 0] = -ox / rng
            jac[j, 1] = -oy / rng
            jac[j, 2] = -oz / rng
            resid[j] = pr[j] - rng
            # The clocks are re-estimated at every step: the residual is before them.
            w = robust_w[j] / sigma[j]
            for c in range(n):
                a_w[j, c] = jac[j, c] * w
                if not np.isfinite(a_w[j, c]):
                    return False
            b_w[j] = resid[j] * w
            if not np.isfinite(b_w[j]):
                return False
        delta = np.linalg.lstsq(a_w, b_w, rcond)[0]
        for a in range(3):
            x[a] = x[a] + delta[a]
        if step >= plain_steps - 1:
            fit = np.dot(jac, delta)
            for j in range(k):
                post = (resid[j] - fit[j]) / (cauchy_scale * sigma[j])
                robust_w[j] = 1.0 / math.sqrt(1.0 + post * post)
    return np.isfinite(x[0]) and np.isfinite(x[1]) and np.isfinite(x[2])
