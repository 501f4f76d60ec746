"""The error model's passes over an epoch's residuals (``core.error_model``), a call each.

How many satellites are line of sight under the fit (the residuals' inflation) was some
twenty numpy calls on a dozen values; here it is two calls around numpy's exp (the
kernels' exp rounds differently), in numpy's arithmetic element for element.

Every epoch also pairs each satellite's residual with its own about one lag earlier, for
the correlation time. In Python that was a dictionary of per-satellite lists and two
bisections per satellite, 16 us of a 0.7 ms epoch at N = 120; here the last two lags of
residuals are rows of three flat buffers, in time order, and one call pairs the epoch.
"""
from __future__ import annotations

import math

import numpy as np

from . import kernel

_SQRT_2PI = math.sqrt(2.0 * math.pi)


@kernel
def mixture_exponents(r, cls, core_sd, wide_mean, wide_sd):
    """The exponents ``-z^2 / 2`` of each residual ``r`` (k,) under its class's core
    (row 0: ``z = r / s0``) and wide component (row 1: ``z = (r - mu) / s1``), (2, k);
    ``cls`` (k,) the classes, the other arguments per class."""
    k = r.shape[0]
    out = np.empty((2, k))
    for i in range(k):
        c = cls[i]
        z = (r[i] - 0.0) / core_sd[c]
        out[0, i] = -0.5 * z * z
        z = (r[i] - wide_mean[c]) / wide_sd[c]
        out[1, i] = -0.5 * z * z
    return out


@kernel
def core_shares(exponentials, cls, core_sd, wide_share, wide_sd):
    """Each residual's probability of the core, (k,), from the exponentials of
    :func:`mixture_exponents` (2, k): ``core / max(core + wide, 1e-300)`` with
    ``core = (1 - pi) N(r; 0, s0)``, ``wide = pi N(r; mu, s1)`` (a NaN stays NaN)."""
    k = cls.shape[0]
    out = np.empty(k)
    for i in range(k):
        c = cls[i]
        core = (1.0 - wide_share[c]) * (exponentials[0, i] / (core_sd[c] * _SQRT_2PI))
        wide = wide_share[c] * (exponentials[1, i] / (wide_sd[c] * _SQRT_2PI))
        total = core + wide
        if total < 1e-300:
            total = 1e-300
        out[i] = core / total
    return out


@kernel
def lagged_pairs(stamps, keys, values, first, end, stamp_ns, new_keys, new_values, lag_ns):
    """Pair each of the epoch's satellites with its own row closest to one lag back, and
    add the epoch's rows.

    Rows ``first .. end`` of the buffers ``stamps`` (int64 [ns], rising), ``keys``
    (int64) and ``values`` hold the earlier epochs; those older than two lags are
    forgotten, and the epoch's rows (``new_keys``, ``new_values`` at ``stamp_ns``) are
    written from ``end`` on (the caller leaves room for them). A satellite pairs with its
    row whose stamp is closest to ``stamp_ns - lag_ns`` (of two as close, the earlier) if
    that row is within half a lag of it.

    Returns:
        ``(first, end, pairs)``: the buffers' rows now, and (p, 3) pairs in the
        satellites' order: value now, value then, their spacing [s].
    """
    forget, target, tolerance = stamp_ns - 2 * lag_ns, stamp_ns - lag_ns, lag_ns // 2
    while first < end and stamps[first] < forget:
        first += 1
    # Only rows within the tolerance can pair, and a key's closest row is within it if
    # any of its rows is: the search runs over those rows alone.
    lo = first + np.searchsorted(stamps[first:end], target - tolerance)
    hi = first + np.searchsorted(stamps[first:end], target + tolerance, side='right')
    k = new_keys.shape[0]
    pairs = np.empty((k, 3))
    n = 0
    for s in range(k):
        best = -1
        for i in range(lo, hi):
            # Rows in time order: of two as close, the earlier stays.
            if keys[i] == new_keys[s] and (
                    best < 0 or abs(stamps[i] - target) < abs(stamps[best] - target)):
                best = i
        if best >= 0:
            pairs[n, 0] = new_values[s]
            pairs[n, 1] = values[best]
            pairs[n, 2] = (stamp_ns - stamps[best]) * 1e-9
            n += 1
    for s in range(k):
        stamps[end + s] = stamp_ns
        keys[end + s] = new_keys[s]
        values[end + s] = new_values[s]
    return first, end + k, pairs[:n]
