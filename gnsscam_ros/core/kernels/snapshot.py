"""The snapshot solution of one epoch (``core.consistency.snapshot_position``) in one
compiled pass: its Gauss-Newton and reweighted least-squares steps (``robust_snapshot``),
each least squares a Householder QR of a dozen rows in the kernel (``_qr_solve``).
"""
from __future__ import annotations

import math

import numpy as np

from . import kernel

#: float64 machine epsilon (numpy's lstsq cut-off is ``eps * max(rows, columns)``).
_EPS = float(np.finfo(np.float64).eps)
#: Smallest ``|R_jj|`` of the QR relative to the largest before a system counts as rank
#: deficient and goes to LAPACK's minimum-norm solution instead. Well above rounding
#: (the columns are unit directions and clock indicators, scaled by 1/sigma): only a
#: degenerate geometry comes near it.
_QR_RANK_TOLERANCE = 1e-10


@kernel
def _qr_solve(a, b, out):
    """Least squares ``min |a x - b|`` for a (k, n) ``a`` of full column rank, k >= n, by
    Householder QR; ``a`` and ``b`` are overwritten. Writes ``x`` into ``out`` (n,) and
    returns True; False (``out`` undefined) where ``a`` is rank deficient to
    ``_QR_RANK_TOLERANCE``.

    LAPACK's ``gelsd`` (numpy's lstsq) on these systems of a dozen rows spent more in its
    workspace queries and SVD than in arithmetic: nine solves were most of the snapshot's
    50 us. The QR gives the same solution to rounding (nanometres on 2e7 m ranges).
    """
    k, n = a.shape
    largest = 0.0
    for j in range(n):
        # The reflection that zeroes column j below the diagonal.
        norm = 0.0
        for i in range(j, k):
            norm += a[i, j] * a[i, j]
        norm = math.sqrt(norm)
        if norm == 0.0:
            return False
        alpha = -norm if a[j, j] >= 0.0 else norm
        v0 = a[j, j] - alpha
        # v = (v0, a[j+1:, j]); H = I - 2 v v^T / v^T v, and v^T v = -2 alpha v0.
        vtv = -2.0 * alpha * v0
        a[j, j] = alpha
        for c in range(j + 1, n):
            dot = v0 * a[j, c]
            for i in range(j + 1, k):
                dot += a[i, j] * a[i, c]
            f = 2.0 * dot / vtv
            a[j, c] -= f * v0
            for i in range(j + 1, k):
                a[i, c] -= f * a[i, j]
        dot = v0 * b[j]
        for i in range(j + 1, k):
            dot += a[i, j] * b[i]
        f = 2.0 * dot / vtv
        b[j] -= f * v0
        for i in range(j + 1, k):
            b[i] -= f * a[i, j]
        largest = max(largest, abs(alpha))
    for j in range(n):
        if not abs(a[j, j]) > _QR_RANK_TOLERANCE * largest:
            return False
    for j in range(n - 1, -1, -1):
        total = b[j]
        for c in range(j + 1, n):
            total -= a[j, c] * out[c]
        out[j] = total / a[j, j]
    return True


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

    Each step is numpy's arithmetic, operation for operation, but for the least squares:
    a Householder QR (``_qr_solve``), and LAPACK's ``gelsd`` as numpy's ``lstsq`` calls it
    (numba's ``np.linalg.lstsq``, the same cut-off ``rcond = eps * max(k, n)``) only for a
    rank-deficient system, whose minimum-norm solution the QR does not give. The two
    agree to rounding: ranges of 2e7 m round to 4e-9 m, so the solution moves by
    nanometres between solvers (and the filter's estimate, through the error model that
    learns from its residuals, by about 1e-7 m).

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
    # The QR's working copies (it overwrites them; LAPACK may still need the originals).
    qr_a = np.empty((k, n))
    qr_b = np.empty(k)
    delta = np.empty(n)
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
        qr_a[:] = a_w
        qr_b[:] = b_w
        if not _qr_solve(qr_a, qr_b, delta):
            delta = np.linalg.lstsq(a_w, b_w, rcond)[0]
        for a in range(3):
            x[a] = x[a] + delta[a]
        if step >= plain_steps - 1:
            fit = np.dot(jac, delta)
            for j in range(k):
                post = (resid[j] - fit[j]) / (cauchy_scale * sigma[j])
                robust_w[j] = 1.0 / math.sqrt(1.0 + post * post)
    return np.isfinite(x[0]) and np.isfinite(x[1]) and np.isfinite(x[2])
