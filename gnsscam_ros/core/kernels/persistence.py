"""The semivariogram of the snapshot solutions' offsets (``core.persistence``) in one pass.

An epoch measures the persisting share over the whole window (a minute of epochs) at two
lags; in numpy that was some twenty small array operations per lag, a quarter of a
millisecond an epoch. Same arithmetic here, value for value.
"""
from __future__ import annotations

import numpy as np

from . import kernel


@kernel
def median_increment_m2(t, d, lag_ns, tolerance):
    """Median squared increment of the offsets ``d`` (n, 2) at times ``t`` (n,, increasing)
    over pairs about ``lag_ns`` apart, and the number of pairs ((NaN, 0) without any).

    Each epoch pairs with the nearer of the two epochs around ``t - lag_ns`` (the later
    one on a tie), if that one is earlier than itself and within ``tolerance * lag_ns``
    of ``t - lag_ns``. The median is numpy's: NaN if any increment is NaN, the mean of
    the two middle values of an even count."""
    n = t.shape[0]
    sq = np.empty(n)
    count = 0
    limit = tolerance * lag_ns
    for i in range(n):
        target = t[i] - lag_ns
        j = np.searchsorted(t, target)              # as numpy's: the left side
        before = min(max(j - 1, 0), n - 1)
        after = min(max(j, 0), n - 1)
        pick = before if abs(t[before] - target) < abs(t[after] - target) else after
        if abs(t[pick] - target) <= limit and pick < i:
            dx = d[i, 0] - d[pick, 0]
            dy = d[i, 1] - d[pick, 1]
            sq[count] = dx * dx + dy * dy
            count += 1
    if count == 0:
        return np.nan, 0
    values = np.sort(sq[:count])
    if np.isnan(values[count - 1]):                   # NaN sorts last
        return np.nan, count
    half = count // 2
    if count % 2:
        return values[half], count
    return (values[half - 1] + values[half]) / 2.0, count


@kernel
def median_increments_m2(t, d, short_lag_ns, long_lag_ns, tolerance):
    """:func:`median_increment_m2` at the short and the long lag in one call:
    ``(median, pairs)`` of each, in that order."""
    short, n_short = median_increment_m2(t, d, short_lag_ns, tolerance)
    long, n_long = median_increment_m2(t, d, long_lag_ns, tolerance)
    return short, n_short, long, n_long
