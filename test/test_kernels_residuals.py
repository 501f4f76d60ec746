"""The error model's passes over the residuals (core.kernels.residuals) equal the numpy
forms and the per-satellite lists of ``test/oracles.py`` to the bit: the line-of-sight
count inflates the residuals the mixture is fitted to, the pairs' sums carry over the
window, and both carry on from epoch to epoch."""
import numpy as np
import oracles

from gnsscam_ros.core.error_model import N_CLASSES
from gnsscam_ros.core.kernels.residuals import core_shares, lagged_pairs, mixture_exponents

S = 1_000_000_000


def test_core_shares_equal_numpy_to_the_bit(rng):
    for k in (1, 5, 12, 13, 64):
        for _ in range(50):
            cls = rng.integers(0, N_CLASSES, k)
            s0, s1 = rng.uniform(0.3, 10.0, N_CLASSES), rng.uniform(5.0, 60.0, N_CLASSES)
            pi, mu = rng.uniform(0.0, 0.9, N_CLASSES), rng.uniform(0.0, 30.0, N_CLASSES)
            r = rng.standard_t(2.0, k) * rng.choice([1.0, 10.0, 1e3])
            got = core_shares(np.exp(mixture_exponents(r, cls, s0, mu, s1)), cls, s0, pi, s1)
            np.testing.assert_array_equal(
                got, oracles.core_shares(r, s0[cls], pi[cls], mu[cls], s1[cls]))


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
