"""Weighted particle sets: normalisation, effective size and the summary of one set.

The summary (mean, covariance, circular mean heading, effective sample size) is what an
epoch reports of its chosen set: one pass over it instead of five numpy reductions.
"""
from __future__ import annotations

import math

import numpy as np

from . import elementary, inline_kernel, kernel


@kernel
def log_sum_exp(values):
    """``log sum exp(values)`` of a (N,) array, shifted by its maximum (-inf when every
    value is -inf or the array is empty; NaN propagates)."""
    top = -np.inf
    for i in range(values.shape[0]):
        v = values[i]
        if v > top or v != v:
            top = v
    if not top > -np.inf:
        return top                                   # -inf, or NaN
    acc = 0.0
    for i in range(values.shape[0]):
        acc += math.exp(values[i] - top)
    return top + math.log(acc)


@kernel
def add_and_sum_rows(joint, extra):
    """``joint += extra`` in place, (S, N) each; returns the (S,) log-sum-exp of each row
    of the result (one pass for the sum, one for the shift)."""
    totals = np.empty(joint.shape[0])
    for s in range(joint.shape[0]):
        for i in range(joint.shape[1]):
            joint[s, i] += extra[s, i]
        totals[s] = log_sum_exp(joint[s])
    return totals


@kernel
def normalised(log_w):
    """Log-weights (N,) shifted so that their exponentials sum to one (a new array)."""
    return log_w - log_sum_exp(log_w)


@kernel
def effective_sample_size(log_w):
    """``1 / sum w^2`` of normalised log-weights (N,)."""
    acc = 0.0
    for i in range(log_w.shape[0]):
        acc += math.exp(2.0 * log_w[i])
    return 1.0 / acc


@inline_kernel
def _moments_about(ref, m, c, w_sum):
    """Mean (3,) and covariance (3, 3) from the weighted sums about ``ref``: ``m`` (3,)
    of ``w d`` and the upper triangle of ``c`` (3, 3) of ``w d d^T`` (``c`` is
    completed in place)."""
    mean = np.empty(3)
    for a in range(3):
        m[a] /= w_sum
    for a in range(3):
        mean[a] = ref[a] + m[a]
        for b in range(a, 3):
            c[a, b] = c[a, b] / w_sum - m[a] * m[b]
            c[b, a] = c[a, b]
    return mean, c


@kernel
def weighted_displacement(before, after, log_w):
    """``sum_i exp(log_w[i]) (after[i, :2] - before[i, :2])`` of two (N, >= 2) sets of the
    same particles: the horizontal motion of their weighted mean (2,), in one pass
    (NaN where a state is not finite)."""
    shift = np.zeros(2)
    for i in range(before.shape[0]):
        w = elementary.exp(log_w[i])
        shift[0] += w * (after[i, 0] - before[i, 0])
        shift[1] += w * (after[i, 1] - before[i, 1])
    return shift


@kernel
def weighted_moments(points, log_w):
    """Weighted mean (3,) and covariance (3, 3) of the first three columns of ``points``
    (N, >= 3) under normalised log-weights ``log_w`` (N,), in one pass about the first
    point (relative coordinates are small: the one-pass formula loses nothing to
    cancellation)."""
    ref = points[0, :3].copy()
    m = np.zeros(3)
    c = np.zeros((3, 3))
    d = np.empty(3)
    w_sum = 0.0
    for i in range(points.shape[0]):
        w = math.exp(log_w[i])
        w_sum += w
        for a in range(3):
            d[a] = points[i, a] - ref[a]
        for a in range(3):
            wd = w * d[a]
            m[a] += wd
            for b in range(a, 3):
                c[a, b] += wd * d[b]
    return _moments_about(ref, m, c, w_sum)


@kernel
def set_summary(particles, log_w):
    """Weighted mean (3,), covariance (3, 3), circular mean heading and effective sample
    size of one set (N, 4) with normalised log-weights (N,), in one kernel (moments about
    the first particle, as :func:`weighted_moments`)."""
    n = particles.shape[0]
    ref = particles[0, :3].copy()
    m = np.zeros(3)
    c = np.zeros((3, 3))
    d = np.empty(3)
    # The weights and the headings' sines and cosines in vectorised passes
    # (elementary.exp, elementary.sincos_into): libm's in the loop below, one call each
    # per particle, were four fifths of this kernel.
    weight = np.empty(n)
    heading = np.empty(n)
    for i in range(n):
        weight[i] = elementary.exp(log_w[i])
        heading[i] = particles[i, 3]
    sin_h = np.empty(n)
    cos_h = np.empty(n)
    elementary.sincos_into(heading, sin_h, cos_h)
    w_sum = 0.0
    w_sq = 0.0
    sin_sum = 0.0
    cos_sum = 0.0
    for i in range(n):
        w = weight[i]
        w_sum += w
        w_sq += w * w
        sin_sum += w * sin_h[i]
        cos_sum += w * cos_h[i]
        for a in range(3):
            d[a] = particles[i, a] - ref[a]
        for a in range(3):
            wd = w * d[a]
            m[a] += wd
            for b in range(a, 3):
                c[a, b] += wd * d[b]
    mean, cov = _moments_about(ref, m, c, w_sum)
    return mean, cov, math.atan2(sin_sum, cos_sum), w_sum * w_sum / w_sq


#: What :func:`set_problem` finds, by code (0: nothing).
SET_PROBLEMS = ('non-finite particles', 'particles beyond the bound',
                'particle weights are not a distribution')


@kernel
def set_problem(particles, log_w, bound):
    """0 when the set (N, 4) is finite and within ``bound`` in every coordinate and its
    log-weights (N,) are a distribution (no NaN, no +inf, at least one finite); else 1 +
    the index in ``SET_PROBLEMS`` of the first problem (one pass)."""
    n = particles.shape[0]
    for i in range(n):
        for a in range(particles.shape[1]):
            v = particles[i, a]
            if not math.isfinite(v):
                return 1
            if abs(v) > bound:
                return 2
    if log_w.shape[0] != n:
        return 3
    finite = False
    for i in range(n):
        v = log_w[i]
        if v != v or v == np.inf:
            return 3
        if v > -np.inf:
            finite = True
    return 0 if finite else 3
