"""The error model's pairs of residuals one lag apart (``core.error_model``), one call an
epoch (how many satellites the fit takes for line of sight is ``kernels.mixture``'s).

Every epoch pairs each satellite's residual with its own about one lag earlier, for
the correlation time. In Python that was a dictionary of per-satellite lists and two
bisections per satellite, 16 us of a 0.7 ms epoch at N = 120; here the last two lags of
residuals are rows of three flat buffers, in time order, and one call pairs the epoch.
"""
from __future__ import annotations

import numpy as np

from . import kernel


@kernel
def lagged_pairs(stamps, keys, values, first, end, stamp_ns, new_keys, new_values, lag_ns,
                 clip, sums, decay):
    """Pair each of the epoch's satellites with its own row closest to one lag back, add
    the epoch's rows, and fold the pairs into the window's sums.

    Rows ``first .. end`` of the buffers ``stamps`` (int64 [ns], rising), ``keys``
    (int64) and ``values`` hold the earlier epochs; those older than two lags are
    forgotten, and the epoch's rows (``new_keys``, ``new_values`` clipped to ``+-clip``
    (k,), at ``stamp_ns``) are written from ``end`` on (the caller leaves room for them).
    A satellite pairs with its row whose stamp is closest to ``stamp_ns - lag_ns`` (of
    two as close, the earlier) if that row is within half a lag of it. ``sums`` (5,),
    the pairs' ``xy, xx, yy, lag, count`` over the window, are first multiplied by
    ``decay`` (what the window forgets since the last epoch), then take the epoch's.

    Returns:
        ``(first, end, pairs)``: the buffers' rows now, and (p, 3) pairs in the
        satellites' order: value now (clipped), value then, their spacing [s].
    """
    forget, target, tolerance = stamp_ns - 2 * lag_ns, stamp_ns - lag_ns, lag_ns // 2
    while first < end and stamps[first] < forget:
        first += 1
    # Only rows within the tolerance can pair, and a key's closest row is within it if
    # any of its rows is: the search runs over those rows alone.
    lo = first + np.searchsorted(stamps[first:end], target - tolerance)
    hi = first + np.searchsorted(stamps[first:end], target + tolerance, side='right')
    k = new_keys.shape[0]
    clipped = np.empty(k)
    for s in range(k):
        clipped[s] = min(max(new_values[s], -clip[s]), clip[s])
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
            pairs[n, 0] = clipped[s]
            pairs[n, 1] = values[best]
            pairs[n, 2] = (stamp_ns - stamps[best]) * 1e-9
            n += 1
    for c in range(5):
        sums[c] *= decay
    for p in range(n):
        sums[0] += pairs[p, 0] * pairs[p, 1]
        sums[1] += pairs[p, 0] * pairs[p, 0]
        sums[2] += pairs[p, 1] * pairs[p, 1]
        sums[3] += pairs[p, 2]
        sums[4] += 1.0
    for s in range(k):
        stamps[end + s] = stamp_ns
        keys[end + s] = new_keys[s]
        values[end + s] = clipped[s]
    return first, end + k, pairs[:n]
