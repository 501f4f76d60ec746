"""The error model's passes over the residuals equal the numpy forms and the per-satellite
lists of ``test/oracles.py``: the line-of-sight count inflates the residuals the mixture
is fitted to, the pairs' sums carry over the window, and both carry on from epoch to
epoch."""
import numpy as np
import oracles

from gnsscam_ros.core.error_model import N_CLASSES
from gnsscam_ros.core.kernels.mixture import line_of_sight
from gnsscam_ros.core.kernels.residuals import lagged_pairs

S = 1_000_000_000


def test_the_line_of_sight_count_is_the_sum_of_the_core_probabilities(rng):
    for k in (1, 5, 12, 13, 64):
        for _ in range(50):
            cls = rng.integers(0, N_CLASSES, k)
            # As the EM keeps them: the wide component at least twice the core (where
            # both densities underflow the ratio then gives the wide one, as 0 / 0 did).
            s0 = rng.uniform(0.3, 10.0, N_CLASSES)
            s1 = s0 * rng.uniform(2.0, 10.0, N_CLASSES)
            pi, mu = rng.uniform(0.01, 0.9, N_CLASSES), rng.uniform(0.0, 30.0, N_CLASSES)
            r = rng.standard_t(2.0, k) * rng.choice([1.0, 10.0, 1e3])
            want = oracles.core_shares(r, s0[cls], pi[cls], mu[cls], s1[cls]).sum()
            assert abs(line_of_sight(r, cls, s0, pi, mu, s1) - want) <= 1e-12 * k


def test_residuals_of_kilometres_count_as_nlos_and_weights_of_zero_decide():
    cls = np.zeros(3, dtype=np.int64)
    one = np.ones(1)
    assert line_of_sight(np.full(3, 5e3), cls, 3 * one, 0.3 * one, 0 * one, 20 * one) == 0.0
    r = np.array([0.0, 10.0, -4.0])
    assert line_of_sight(r, cls, 3 * one, 0.0 * one, 0 * one, 20 * one) == 3.0
    assert line_of_sight(r, cls, 3 * one, 1.0 * one, 0 * one, 20 * one) == 0.0


def test_lagged_pairs_equal_the_per_satellite_lists_and_their_sums(rng):
    lag_ns = 2 * S
    oracle = oracles.LaggedPairs(lag_ns)
    buffers = (np.empty(10_000, dtype=np.int64), np.empty(10_000, dtype=np.int64),
               np.empty(10_000))
    first = end = 0
    stamp, paired = 10**18, 0
    sums, want = np.zeros(5), np.zeros(5)
    for _ in range(400):
        # Rates from 5 Hz to a gap of seconds, stamps on the tolerance's edges too.
        stamp += int(rng.choice([1, S // 5, S // 2, S, S, S + 1, 3 * S // 2, 3 * S]))
        keys = rng.choice(40, size=int(rng.integers(0, 20)), replace=False)
        if keys.shape[0] and rng.random() < 0.1:
            keys = np.append(keys, keys[0])            # a satellite listed twice
        values = rng.normal(0.0, 5.0, keys.shape[0])
        clip = rng.uniform(3.0, 20.0, keys.shape[0])
        decay = float(rng.uniform(0.9, 1.0))
        first, end, pairs = lagged_pairs(*buffers, first, end, stamp, keys, values, lag_ns,
                                         clip, sums, decay)
        expected = oracle.pairs(stamp, keys, np.clip(values, -clip, clip))
        np.testing.assert_array_equal(pairs, expected)
        x, y, lag = expected.T
        want = want * decay + (x @ y, x @ x, y @ y, lag.sum(), x.shape[0])
        np.testing.assert_allclose(sums, want, rtol=1e-12)
        paired += expected.shape[0]
    assert paired > 1000
