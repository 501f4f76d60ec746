"""The error model's lagged residual pairs (core.kernels.correlation) equal the
per-satellite lists of ``test/oracles.py`` to the bit: the pairs' sums carry over the
window, and they decide the correlation time the bias hypotheses take."""
import numpy as np
import oracles

from gnsscam_ros.core.kernels.correlation import lagged_pairs

S = 1_000_000_000


def test_lagged_pairs_equal_the_per_satellite_lists(rng):
    lag_ns = 2 * S
    oracle = oracles.LaggedPairs(lag_ns)
    buffers = (np.empty(10_000, dtype=np.int64), np.empty(10_000, dtype=np.int64),
               np.empty(10_000))
    first = end = 0
    stamp, paired = 10**18, 0
    for _ in range(400):
        # Rates from 5 Hz to a gap of seconds, stamps on the tolerance's edges too.
        stamp += int(rng.choice([1, S // 5, S // 2, S, S, S + 1, 3 * S // 2, 3 * S]))
        keys = rng.choice(40, size=int(rng.integers(0, 20)), replace=False)
        if keys.shape[0] and rng.random() < 0.1:
            keys = np.append(keys, keys[0])            # a satellite listed twice
        values = rng.normal(0.0, 5.0, keys.shape[0])
        first, end, pairs = lagged_pairs(*buffers, first, end, stamp, keys, values, lag_ns)
        expected = oracle.pairs(stamp, keys, values)
        np.testing.assert_array_equal(pairs, expected)
        paired += expected.shape[0]
    assert paired > 1000
