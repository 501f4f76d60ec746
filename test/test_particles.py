"""Known-answer and property tests of the particle machinery."""
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from gnsscam_ros.core.particles import (SYSTEMATIC, MotionIncrement, effective_sample_size,
                                        motion_samples, normalize_log_weights, propagate,
                                        systematic_resample, weighted_mean_cov)


def test_equal_weights_resample_to_identity(rng):
    n = 257
    idx = systematic_resample(np.full(n, -np.log(n)), rng)
    np.testing.assert_array_equal(idx, np.arange(n))


def test_single_weight_collapses(rng):
    log_w = np.full(50, -np.inf)
    log_w[17] = 0.0
    assert np.all(systematic_resample(log_w, rng) == 17)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-30, 0), min_size=2, max_size=200), st.integers(0, 2 ** 31))
def test_systematic_counts_stay_within_one_of_expectation(raw, seed):
    log_w = normalize_log_weights(np.array(raw))
    idx = systematic_resample(log_w, np.random.default_rng(seed))
    n = len(raw)
    counts = np.bincount(idx, minlength=n)
    assert counts.sum() == n
    # Systematic resampling: each count is floor or ceil of n * w (up to rounding).
    assert np.all(np.abs(counts - n * np.exp(log_w)) < 1.0 + 1e-9)


def test_effective_sample_size_extremes():
    n = 100
    assert np.isclose(effective_sample_size(np.full(n, -np.log(n))), n)
    one = np.full(n, -np.inf)
    one[3] = 0.0
    assert np.isclose(effective_sample_size(one), 1.0)


def test_motion_sample_zero_is_the_measurement(rng):
    motion = MotionIncrement(1.0, 10.0, 0.1, 0.04, 1e-4)
    distance, dyaw = motion_samples(motion, 10, 3.0, rng)
    assert distance[0] == 10.0 and dyaw[0] == 0.1
    assert np.std(distance[1:]) > 0.0


def _normals(rng, shape):
    return rng.standard_normal(shape, dtype=np.float32)


def test_propagate_straight_and_turning_without_noise(rng):
    particles = np.array([[0.0, 0.0, 0.0, 0.0], [5.0, 5.0, 1.0, np.pi / 2]])
    out = propagate(particles, np.array([10.0]), np.array([0.0]), 0.0, np.zeros(3), 0.0,
                    _normals(rng, (1, 2, 4)))
    np.testing.assert_allclose(out[0, 0, :3], [10.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(out[0, 1, :3], [5.0, 15.0, 1.0], atol=1e-12)
    # A quarter turn over an arc: mid-heading chord of a constant turn rate.
    out = propagate(particles[:1], np.array([10.0]), np.array([np.pi / 2]), 0.0, np.zeros(3),
                    0.0, _normals(rng, (1, 1, 4)))
    np.testing.assert_allclose(out[0, 0, :2], 10.0 * np.array([np.cos(np.pi / 4),
                                                              np.sin(np.pi / 4)]))
    assert np.isclose(out[0, 0, 3], np.pi / 2)


def test_propagate_noise_matches_variance(rng):
    particles = np.zeros((20000, 4))
    out = propagate(particles, np.zeros(2), np.zeros(2), 0.0, np.array([4.0, 4.0, 0.25]),
                    0.01, _normals(rng, (2, 20000, 4)))
    sd = out.reshape(-1, 4).std(axis=0)
    np.testing.assert_allclose(sd, [2.0, 2.0, 0.5, 0.1], rtol=0.03)


def test_weighted_mean_cov_matches_numpy(rng):
    pts = rng.normal(size=(500, 3))
    w = rng.random(500)
    mean, cov = weighted_mean_cov(pts, np.log(w / w.sum()))
    np.testing.assert_allclose(mean, np.average(pts, axis=0, weights=w))
    np.testing.assert_allclose(cov, np.cov(pts.T, aweights=w, bias=True))


def _comb(log_w, pointers):
    """The selection the four resampling uses made before they shared one resampler."""
    cdf = np.cumsum(np.exp(log_w - np.max(log_w)))
    cdf /= cdf[-1]
    return np.minimum(np.searchsorted(cdf, pointers, side='right'), log_w.shape[0] - 1)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-30, 0), min_size=2, max_size=300), st.integers(1, 400),
       st.integers(0, 2 ** 31))
def test_the_resampler_selects_what_each_use_selected_before(raw, count, seed):
    log_w = normalize_log_weights(np.array(raw))
    n = len(raw)
    # The filter's resampling, thinned to a working size at the end of heading acquisition.
    a, b = np.random.default_rng(seed), np.random.default_rng(seed)
    full = _comb(log_w, (a.random() + np.arange(n)) / n)
    np.testing.assert_array_equal(SYSTEMATIC.resample(log_w, b), full)
    a, b = np.random.default_rng(seed), np.random.default_rng(seed)
    full = _comb(log_w, (a.random() + np.arange(n)) / n)
    thinned = full[np.round(np.linspace(0, n - 1, count)).astype(int)]
    np.testing.assert_array_equal(SYSTEMATIC.resample(log_w, b, count), thinned)
    # A new set size while running: resampled, then drawn with replacement.
    a, b = np.random.default_rng(seed), np.random.default_rng(seed)
    resized = a.choice(_comb(log_w, (a.random() + np.arange(n)) / n), size=count,
                       replace=True)
    np.testing.assert_array_equal(SYSTEMATIC.resize(log_w, b, count), resized)
    assert a.random() == b.random()                   # the same draws were consumed
    # The published cloud: deterministic mid-slot pointers over `count` slots.
    published = (np.arange(n) if n <= count
                 else _comb(log_w, (np.arange(count) + 0.5) / count))
    np.testing.assert_array_equal(SYSTEMATIC.subsample(log_w, count), published)
    np.testing.assert_array_equal(SYSTEMATIC.subsample(log_w, 0), np.arange(n))


def test_thinning_keeps_every_kth_particle_and_at_least_the_count():
    assert SYSTEMATIC.thin(10_000, 1000) == slice(None, None, 10)
    assert len(range(10_000)[SYSTEMATIC.thin(10_000, 3000)]) == 3334
    assert SYSTEMATIC.thin(500, 1000).step == 1
