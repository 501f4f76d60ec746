"""The bias hypotheses' compiled linear algebra equals numpy's forms (``test/oracles.py``:
BLAS products, LAPACK's inverse, pseudo-inverse and eigenvalues) to rounding, on
geometries from well spread to singular; the Gauss-Markov steps and hidden faults to the
bit.
"""
import numpy as np
import oracles
import pytest

from gnsscam_ros.core.bias import (BiasHypotheses, BiasModel, beyond_cloud, hidden_fault_sizes,
                                   leverages, with_hidden_faults)


def geometry(rng, k):
    az, el = rng.uniform(0, 2 * np.pi, k), rng.uniform(0.1, 1.5, k)
    return np.stack([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)], 1)


def spd(rng, scale):
    a = rng.normal(0.0, scale, (3, 3))
    return a @ a.T + 1e-3 * np.eye(3)


@pytest.mark.parametrize('k, systems, m', [(5, 1, 7), (8, 2, 200), (12, 3, 10), (4, 1, 1),
                                           (30, 4, 50)])
def test_leverages_and_update_equal_numpy_to_rounding(rng, k, systems, m):
    for _ in range(20):
        line = geometry(rng, k)
        sys_index = np.sort(rng.integers(0, systems, k))
        weights = rng.uniform(0.0, 0.3, k)
        weights[rng.integers(0, k)] = 0.0          # a satellite the update ignores
        np.testing.assert_allclose(
            leverages(line, weights, sys_index, systems),
            oracles.bias_leverages(line, weights, sys_index, systems), rtol=0, atol=1e-9)
        biases = rng.normal(0.0, 5.0, (k, m))
        faults = np.zeros((k, m))
        faults[np.arange(m) % k, np.arange(m)] = rng.normal(0.0, 20.0, m)
        prior = spd(rng, 3.0)
        posterior = prior * rng.uniform(0.3, 1.2)  # sometimes less information: clipped
        for fault_biases in (faults, None):
            hyp = BiasHypotheses(BiasModel(1.0, 0.0, 40.0, 50.0), m, rng)
            hyp.offsets_m = rng.normal(0.0, 3.0, (m, 3))
            hyp.fault_offsets_m = rng.normal(0.0, 1.0, (m, 3))
            expected = oracles.bias_update(hyp.offsets_m, hyp.fault_offsets_m,
                                           biases + faults, line, weights, sys_index,
                                           systems, prior, posterior, fault_biases)
            got = hyp.update(biases + faults, line, weights, sys_index, systems, prior,
                             posterior, fault_biases)
            scale = np.abs(expected[0]).max()
            np.testing.assert_allclose(got, expected[0], rtol=0, atol=1e-9 * scale)
            np.testing.assert_allclose(hyp.fault_offsets_m, expected[1], rtol=0,
                                       atol=1e-9 * scale)


@pytest.mark.parametrize('k, m', [(1, 1), (5, 12), (12, 10), (12, 200), (64, 30)])
def test_hidden_faults_equal_numpy_to_the_bit(rng, k, m):
    for _ in range(20):
        biases = rng.normal(0.0, 5.0, (k, m))
        core, largest = rng.uniform(0.3, 20.0, k), rng.uniform(10.0, 200.0, k)
        leverage = rng.uniform(0.0, 1.0, k)
        leverage[rng.integers(0, k)] = 1.0                # no redundancy: capped
        np.testing.assert_array_equal(
            with_hidden_faults(biases, hidden_fault_sizes(core, leverage, 1.5, largest)),
            oracles.hidden_faults(biases, core, leverage, 1.5, largest))


@pytest.mark.parametrize('tau', [0.0, 2.0, 50.0])
def test_biases_step_as_numpy_to_the_bit(rng, tau):
    seed = int(rng.integers(1 << 30))
    hyp = BiasHypotheses(BiasModel(1.0, 0.0, 40.0, 50.0), 7, np.random.default_rng(seed))
    oracle = oracles.GaussMarkovBiases(7, np.random.default_rng(seed))
    stamp = 10**18
    for _ in range(200):
        # Satellites coming and going, a repeated stamp, gaps beyond the memory.
        stamp += int(rng.choice([0, 10**8, 10**9, 10**9, 3 * 10**9, 10**12]))
        keys = rng.choice(80, size=int(rng.integers(1, 30)), replace=False)
        sigma = rng.uniform(0.5, 10.0, keys.shape[0])
        np.testing.assert_array_equal(hyp.biases_at(stamp, keys, None, sigma, tau),
                                      oracle.step(stamp, keys, sigma, tau))


@pytest.mark.parametrize('dims', [2, 3])
def test_beyond_cloud_equals_numpy_to_rounding(rng, dims):
    for m in (1, 3, 200):
        for cloud_scale in (0.1, 3.0, 30.0):              # from narrow to wider than all
            offsets = rng.normal(0.0, 5.0, (m, 3))
            faults = rng.normal(0.0, 2.0, (m, 3))
            cloud = spd(rng, cloud_scale)
            # The square root of the excess's eigenvalues that are zero but for rounding
            # (1e-16 of it) is 1e-8 of it: the two forms agree to that.
            np.testing.assert_allclose(beyond_cloud(offsets, faults, cloud, dims),
                                       oracles.bias_beyond_cloud(offsets, faults, cloud,
                                                                 dims), rtol=0, atol=1e-6)
    # The offsets along one direction only (the moment singular), and none at all.
    line = np.outer(rng.normal(0.0, 4.0, 20), [0.6, 0.8, 0.0])
    for offsets in (line, np.zeros((20, 3))):
        np.testing.assert_allclose(
            beyond_cloud(offsets, np.zeros((20, 3)), np.eye(3), dims),
            oracles.bias_beyond_cloud(offsets, np.zeros((20, 3)), np.eye(3), dims),
            rtol=0, atol=1e-9)


def test_the_small_symmetric_decompositions_are_numpys(rng):
    # Eigenvalues and vectors (up to sign, on distinct eigenvalues), inverse and
    # pseudo-inverse of 1 x 1 to 8 x 8 symmetric matrices: spread, repeated eigenvalues,
    # singular, indefinite, zero.
    from gnsscam_ros.core.kernels import bias as bias_kernels
    for n in range(1, 9):
        for _ in range(30):
            a = rng.normal(size=(n, n))
            spd_matrix = a @ a.T + 1e-3 * np.eye(n)
            indefinite = a + a.T
            low_rank = np.outer(a[0], a[0])
            for matrix in (spd_matrix, indefinite, low_rank, np.eye(n), np.zeros((n, n))):
                values, vectors = bias_kernels.symmetric_eigen(matrix)
                want = np.linalg.eigvalsh(matrix)
                scale = max(np.abs(want).max(), 1e-300)
                np.testing.assert_allclose(values, want, rtol=0, atol=1e-12 * scale)
                np.testing.assert_allclose(vectors @ vectors.T, np.eye(n), atol=1e-12)
                np.testing.assert_allclose((vectors * values) @ vectors.T, matrix, rtol=0,
                                           atol=1e-12 * scale)
                np.testing.assert_allclose(
                    bias_kernels._pseudo_inverse(matrix), np.linalg.pinv(matrix), rtol=0,
                    atol=1e-8 * np.abs(np.linalg.pinv(matrix)).max(initial=1.0))
            for matrix in (spd_matrix, indefinite):          # Cholesky, and its fallback
                want = np.linalg.inv(matrix)
                np.testing.assert_allclose(bias_kernels._inverse(matrix), want, rtol=0,
                                           atol=1e-8 * np.abs(want).max())
        # A matrix that is not finite has no inverse: NaN, never a finite stand-in.
        for bad in (np.inf, np.nan):
            matrix = np.eye(n)
            matrix[-1, 0] = matrix[0, -1] = bad
            assert np.isnan(bias_kernels._inverse(matrix)).all()
