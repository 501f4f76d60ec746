"""The compiled posterior statistics (``core.kernels.posterior``) against the numpy oracles:
distances, hazard masses, protection level, pooled moments and their KL, the inverse
Bernoulli; and the fast exponential they use, the logarithm of the likelihood and the sine
and cosine of the headings (``core.kernels.elementary``)."""
import math

import numpy as np
import oracles
import pytest
from synthetic import FRAME, epoch_at

from gnsscam_ros.core import integrity
from gnsscam_ros.core.filter import UPDATED, FilterConfig, ParticleFilter
from gnsscam_ros.core.kernels import kernel
from gnsscam_ros.core.kernels import posterior as posterior_kernels
from gnsscam_ros.core.kernels import weights as weight_kernels
from gnsscam_ros.core.kernels.elementary import (SINCOS_LARGEST, exp, exp32, log,
                                                 sincos_into)
from gnsscam_ros.core.particles import MotionIncrement

SECOND = 1_000_000_000
# Risks that are no sum of the test clouds' equal weights: a comparison with q_max never
# hinges on the last bit of a sum (the kernel and the oracle add in different orders).
Q_MAX = (1e-4, 0.01234567, 0.0503217, 0.1111, 0.2718281, 0.5, 0.97531)


@kernel
def _exp_array(x, out):
    for i in range(x.shape[0]):
        out[i] = exp(x[i])


def test_fast_exp_is_within_two_ulp_and_flushes_below_the_normals():
    x = np.concatenate([np.random.default_rng(0).uniform(-708.0, 709.0, 200_000),
                        np.linspace(-1.0, 1.0, 2001), [0.0, -0.0, 1e-300, -707.9]])
    out = np.empty_like(x)
    _exp_array(x, out)
    # Against the exponential in extended precision, not np.exp: numpy's own float64 exp
    # is up to 1.5 ulp off in numpy 1.24-1.26 (0.7 in 2.x), which would decide the test.
    exact = np.exp(x.astype(np.longdouble))
    np.testing.assert_array_less(np.abs(out - exact), 4.5e-16 * exact)
    special = np.array([-np.inf, -800.0, -708.5, np.inf, 710.0, np.nan])
    out = np.empty_like(special)
    _exp_array(special, out)
    np.testing.assert_array_equal(out[:5], [0.0, 0.0, 0.0, np.inf, np.inf])
    assert np.isnan(out[5])


@kernel
def _exp32_array(x, out):
    for i in range(x.shape[0]):
        out[i] = exp32(x[i])


def test_single_precision_exp_is_within_two_ulp_and_flushes_below_the_normals():
    x = np.concatenate([np.random.default_rng(0).uniform(-86.99, 87.99, 200_000),
                        np.linspace(-1.0, 1.0, 2001), [0.0, -0.0, 1e-30, -86.99]]
                       ).astype(np.float32)
    out = np.empty_like(x)
    _exp32_array(x, out)
    exact = np.exp(x.astype(np.float64))
    ulp = np.spacing(exact.astype(np.float32)).astype(np.float64)
    assert np.max(np.abs(out - exact) / ulp) <= 2.0
    special = np.array([-np.inf, -100.0, -87.0, np.inf, 88.0, np.nan], dtype=np.float32)
    out = np.empty_like(special)
    _exp32_array(special, out)
    np.testing.assert_array_equal(out[:5], [0.0, 0.0, 0.0, np.inf, np.inf])
    assert np.isnan(out[5])


@kernel
def _log_array(x, out):
    for i in range(x.shape[0]):
        out[i] = log(x[i])


def test_fast_log_is_within_one_ulp_everywhere():
    rng = np.random.default_rng(0)
    x = np.concatenate([
        np.exp(rng.uniform(-744.0, 709.7, 200_000)),          # every binade, subnormals
        # The likelihood's inputs: float32 products of densities.
        rng.integers(1, 0x7F800000, 200_000, dtype=np.int64).astype(np.uint32)
        .view(np.float32).astype(np.float64),
        1.0 + np.linspace(-0.3, 0.42, 2001),                  # about 1 (and sqrt 2)
        [5e-324, 2.2250738585072014e-308, 0.5, 1.0, 2.0, 1.7976931348623157e308]])
    out = np.empty_like(x)
    _log_array(x, out)
    exact = np.log(x.astype(np.longdouble))
    # Within an ulp of the result (1 ulp: libm's own is within 0.52).
    np.testing.assert_array_less(np.abs(out - exact), np.spacing(np.abs(out)) * 1.0001
                                 + 1e-300)
    assert out[-3] == 0.0
    special = np.array([0.0, -0.0, np.inf, -1.0, -np.inf, np.nan])
    out = np.empty_like(special)
    _log_array(special, out)
    np.testing.assert_array_equal(out[:3], [-np.inf, -np.inf, np.inf])
    assert np.isnan(out[3:]).all()


@kernel
def _sincos_arrays(x, sin_out, cos_out):
    sincos_into(x, sin_out, cos_out)


def test_fast_sincos_is_within_one_ulp_up_to_its_largest_argument():
    rng = np.random.default_rng(0)
    x = np.concatenate([
        # Every binade from 1e-9 rad to the largest argument, both signs.
        rng.choice([-1.0, 1.0], 200_000) * np.exp(rng.uniform(np.log(1e-9),
                                                              np.log(SINCOS_LARGEST),
                                                              200_000)),
        rng.uniform(-4.0, 4.0, 100_000),                       # headings
        np.arange(-800, 801) * (np.pi / 4),                    # zeros and quadrant edges
        [0.0, -0.0, 5e-324, SINCOS_LARGEST, -SINCOS_LARGEST]])
    sin_x, cos_x = np.empty_like(x), np.empty_like(x)
    _sincos_arrays(x, sin_x, cos_x)
    exact = x.astype(np.longdouble)
    for got, want in ((sin_x, np.sin(exact)), (cos_x, np.cos(exact))):
        np.testing.assert_array_less(np.abs(got - want), np.spacing(np.abs(got)) * 1.0001
                                     + 1e-300)
    assert sin_x[-5] == 0.0 and cos_x[-5] == 1.0 and math.copysign(1.0, sin_x[-4]) < 0
    # NaN and infinity give NaN; one argument beyond the range takes libm's for all.
    special = np.array([np.nan, np.inf, -np.inf])
    sin_s, cos_s = np.empty(3), np.empty(3)
    _sincos_arrays(special, sin_s, cos_s)
    assert np.isnan(sin_s).all() and np.isnan(cos_s).all()
    beyond = np.array([0.5, 2.0 * SINCOS_LARGEST, 1e300])
    _sincos_arrays(beyond, sin_s, cos_s)
    assert list(sin_s) == [math.sin(v) for v in beyond]
    assert list(cos_s) == [math.cos(v) for v in beyond]


@pytest.mark.parametrize('heading_scale', [3.0, 2.0 * SINCOS_LARGEST])
def test_set_summary_and_displacement_equal_numpy(rng, heading_scale):
    """The set's summary (weighted mean, covariance, circular mean heading, effective
    sample size) and the weighted motion between two sets, against numpy; headings
    within the fast sine's range and beyond it (libm's then)."""
    n = 1037
    before = np.column_stack([rng.normal(0.0, 20.0, (n, 3)),
                              rng.uniform(-heading_scale, heading_scale, n)])
    after = before + rng.normal(0.0, 3.0, (n, 4))
    log_w = np.log(rng.dirichlet(np.full(n, 0.7)))
    w = np.exp(log_w)
    mean, cov, yaw, ess = weight_kernels.set_summary(before, log_w)
    expected_mean = w @ before[:, :3]
    d = before[:, :3] - expected_mean
    np.testing.assert_allclose(mean, expected_mean, atol=1e-12)
    np.testing.assert_allclose(cov, (w[:, None] * d).T @ d, rtol=1e-10, atol=1e-10)
    assert yaw == pytest.approx(np.arctan2(w @ np.sin(before[:, 3]),
                                           w @ np.cos(before[:, 3])), abs=1e-12)
    assert ess == pytest.approx(1.0 / np.sum(w * w), rel=1e-12)
    np.testing.assert_allclose(weight_kernels.weighted_displacement(before, after, log_w),
                               w @ (after[:, :2] - before[:, :2]), atol=1e-13)
    after[5, 1] = np.nan
    shift = weight_kernels.weighted_displacement(before, after, log_w)
    assert np.isfinite(shift[0]) and np.isnan(shift[1])


def cloud(rng, s, n, m, ties=False, zeros=False, horizontal=True, shared=False,
          view=True):
    """M posteriors over S samples of N particles 3 km from the origin. ``ties``: rounded
    coordinates and duplicated particles (as after resampling); ``zeros``: some zero
    weights; ``shared``: one weight row broadcast over the samples (the priors);
    ``view``: positions a view of (S, N, 4) particles (the filter's layout)."""
    particles = np.empty((s, n, 4))
    particles[..., :3] = [3000.0, -2000.0, 40.0] + rng.normal(0.0, 5.0, (s, n, 3))
    particles[..., 3] = rng.uniform(-3.0, 3.0, (s, n))
    if ties:
        particles[:, n // 2:] = particles[:, :n - n // 2]
        particles[..., :3] = np.round(particles[..., :3])
    log_w = np.log(rng.dirichlet(np.full(n, 0.5), 1 if shared else s))
    if zeros:
        log_w[:, ::7] = -np.inf
        log_w -= np.log(np.exp(log_w).sum(axis=1, keepdims=True))
    if shared:
        log_w = np.broadcast_to(log_w, (s, n))
    positions = particles[..., :3] if view else np.ascontiguousarray(particles[..., :3])
    offsets = rng.normal(0.0, 2.0, (m, 3))
    return integrity.PosteriorSet(positions, log_w, np.arange(m) % s, offsets, horizontal)


CASES = [dict(s=1, n=1, m=1), dict(s=3, n=5, m=7), dict(s=10, n=1000, m=10),
         dict(s=20, n=300, m=200), dict(s=4, n=500, m=10, ties=True),
         dict(s=4, n=500, m=10, ties=True, zeros=True),
         dict(s=3, n=400, m=9, horizontal=False),
         dict(s=5, n=400, m=10, shared=True, ties=True, view=False),
         dict(s=2, n=4000, m=4, zeros=True, view=False)]


@pytest.mark.parametrize('case', CASES)
def test_hazard_level_and_distances_equal_the_oracles(rng, case):
    posteriors = cloud(rng, **case)
    centre = np.array([3000.5, -2000.2, 40.3])
    radii = np.array([8.0, 3.0, 12.5, 0.0])
    dist, w = oracles.posterior_distances(posteriors, centre)
    got_dist, got_w = posteriors.distances(centre)
    np.testing.assert_array_equal(got_dist, dist)        # the same arithmetic, bit for bit
    np.testing.assert_allclose(got_w, w, rtol=1e-15, atol=0)
    reference = oracles.hazard_mass(dist, w, radii)
    for q_max in Q_MAX:
        masses, level = posteriors.risk_and_level(centre, radii, q_max)
        np.testing.assert_allclose(masses, reference, rtol=0, atol=1e-12)
        assert level == oracles.protection_level(dist, w, q_max), q_max
        assert posteriors.protection_level(centre, q_max) == level
        assert posteriors.protection_level(centre, q_max, (dist, w)) == level
    np.testing.assert_allclose(posteriors.hazard_mass(centre, radii), reference, atol=1e-12)
    assert posteriors.risk_and_level(centre, radii, 0.0)[1] == np.inf


def test_level_when_one_far_particle_crowds_the_histogram(rng):
    # Particles 1,000 and 10^6 km out stretch the bins: the crossing bin holds nearly all
    # particles (24,000: more than the first guess of its size, so it is gathered again
    # into room for every distance) and is split again before its sort.
    posteriors = cloud(rng, 4, 3000, 8)
    posteriors.positions_m[0, 0, 0] += 1e6
    posteriors.positions_m[1, 0, 0] += 1e9
    centre = np.array([3000.0, -2000.0, 40.0])
    dist, w = oracles.posterior_distances(posteriors, centre)
    for q_max in Q_MAX:
        assert posteriors.risk_and_level(centre, [8.0], q_max)[1] == oracles.protection_level(
            dist, w, q_max)


def test_gather_of_a_bin_is_the_histogram_arithmetic_in_order(rng):
    # Distances on and next to the bins' edges (where the product rounds either way) and
    # elsewhere; every bin gathered must be what the histogram's arithmetic puts in it.
    bins = posterior_kernels.LEVEL_BINS
    d_max = 7.3
    scale = bins / d_max
    edges = np.arange(bins) / scale
    dist = np.concatenate([edges, np.nextafter(edges, 0.0), np.nextafter(edges, 9.0),
                           rng.uniform(0.0, d_max, 3000), [d_max]])
    rng.shuffle(dist)
    dist = dist.reshape(1, -1)
    w = rng.uniform(0.0, 1.0, dist.shape)
    of_bin = np.minimum((dist[0] * scale).astype(np.int64), bins - 1)
    index = np.zeros(1, dtype=np.int64)
    for b in (0, 1, 17, bins // 2, bins - 2, bins - 1):
        values, weights = np.empty(dist.shape[1]), np.empty(dist.shape[1])
        k = posterior_kernels._gather_bin(dist, w, index, scale, b, values, weights)
        np.testing.assert_array_equal(values[:k], dist[0][of_bin == b])
        np.testing.assert_array_equal(weights[:k], w[0][of_bin == b])
        if k > 0:                                 # too little room: said, not truncated
            assert posterior_kernels._gather_bin(dist, w, index, scale, b, values[:k - 1],
                                                 weights[:k - 1]) == -1


def test_level_of_ties_is_a_value_and_zero_when_all_mass_fits():
    # Every posterior particle at 5 m: mass 1 strictly beyond 0, none beyond 5.
    sharp = integrity.PosteriorSet(np.zeros((1, 10, 3)), np.full((1, 10), -np.log(10)),
                                   np.zeros(4, int), np.array([[3.0, 4.0, 0.0]] * 4))
    assert sharp.risk_and_level(np.zeros(3), [5.0], 0.5)[1] == 5.0
    # All at the centre: nothing beyond 0.
    centred = integrity.PosteriorSet(np.zeros((1, 10, 3)), np.full((1, 10), -np.log(10)),
                                     np.zeros(2, int), np.zeros((2, 3)))
    assert centred.risk_and_level(np.zeros(3), [5.0], 0.01) == (pytest.approx([0.0]), 0.0)
    # Half the mass at 2 m, half at 6 m: q_max 0.6 admits 2 m; 0.4 only 6 m.
    pos = np.zeros((1, 4, 3))
    pos[0, :2, 0], pos[0, 2:, 0] = 2.0, 6.0
    half = integrity.PosteriorSet(pos, np.full((1, 4), -np.log(4)), np.zeros(1, int),
                                  np.zeros((1, 3)))
    assert half.protection_level(np.zeros(3), 0.6) == 2.0
    assert half.protection_level(np.zeros(3), 0.4) == 6.0
    assert half.protection_level(np.zeros(3), 1.0) == 0.0


def test_walk_reports_when_the_level_lies_below_the_values():
    values, weights = np.array([3.0, 1.0, 2.0, 2.0]), np.array([0.1, 0.2, 0.3, 0.4])
    assert posterior_kernels._walk(values.copy(), weights.copy(), 0.0, 0.35) == (2.0, False)
    assert posterior_kernels._walk(values.copy(), weights.copy(), 0.0, 0.05) == (3.0, False)
    assert posterior_kernels._walk(values.copy(), weights.copy(), 0.0, 0.85) == (1.0, False)
    assert posterior_kernels._walk(values.copy(), weights.copy(), 0.0, 1.0) == (1.0, True)


@pytest.mark.parametrize('case', CASES)
def test_pooled_moments_and_their_divergence_equal_the_oracles(rng, case):
    posteriors = cloud(rng, **case)
    mean, cov = posteriors.pooled_moments()
    ref_mean, ref_cov = oracles.pooled_moments(posteriors)
    scale = max(np.abs(ref_cov).max(), 1.0)
    np.testing.assert_allclose(mean, ref_mean, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(cov, ref_cov, rtol=0, atol=1e-9 * scale)
    # Priors: the same particles with one shared weight row and other offsets.
    m, n = posteriors.n_posteriors, posteriors.positions_m.shape[1]
    prior_log_w = np.log(rng.dirichlet(np.full(n, 2.0)))
    priors = integrity.PosteriorSet(posteriors.positions_m,
                                    np.broadcast_to(prior_log_w, posteriors.log_w.shape),
                                    posteriors.motion_index,
                                    posteriors.offsets_m + rng.normal(0.0, 1.0, (m, 1)),
                                    posteriors.horizontal)
    kl = posteriors.divergence_from(priors)
    reference = integrity.gaussian_kl(*oracles.pooled_moments(posteriors),
                                      *oracles.pooled_moments(priors))
    assert kl == pytest.approx(reference, rel=1e-9, abs=1e-9)
    # Other particles (a copy): two passes, the same divergence.
    copied = integrity.PosteriorSet(posteriors.positions_m.copy(), priors.log_w,
                                    priors.motion_index, priors.offsets_m)
    assert posteriors.divergence_from(copied) == pytest.approx(kl, rel=1e-12, abs=1e-12)


def test_gaussian_kl_kernel_equals_the_numpy_form(rng):
    for _ in range(20):
        a, b = rng.normal(size=(2, 3, 3))
        cov0, cov1 = a @ a.T, b @ b.T * 3.0
        mean0, mean1 = rng.normal(size=(2, 3)) * 4.0
        for floor in (0.0, 1e-2):
            assert posterior_kernels.gaussian_kl(mean0, cov0, mean1, cov1, floor) == (
                pytest.approx(integrity.gaussian_kl(mean0, cov0, mean1, cov1, floor),
                              rel=1e-10, abs=1e-12))


def test_inverse_bernoulli_equals_the_vectorised_oracle(rng):
    q = np.concatenate([[0.0, 1e-12, 0.5, 0.999], rng.uniform(0.0, 1.0, 200)])
    eps = np.concatenate([[0.3, 1e-4, 2.0, 0.01], rng.uniform(1e-4, 5.0, 200)])
    np.testing.assert_allclose(integrity.inverse_bernoulli_exact(q, eps),
                               oracles.inverse_bernoulli_exact(q, eps), rtol=0, atol=1e-15)
    grid = integrity.inverse_bernoulli_exact(q[:5, None], eps[None, :3])
    assert grid.shape == (5, 3)
    np.testing.assert_allclose(grid, oracles.inverse_bernoulli_exact(q[:5, None],
                                                                     eps[None, :3]),
                               atol=1e-15)
    scalar = integrity.inverse_bernoulli_exact(0.05, 0.24)
    assert np.ndim(scalar) == 0 and scalar == pytest.approx(
        float(oracles.inverse_bernoulli_exact(0.05, 0.24)), abs=1e-15)


def test_filter_bound_and_level_equal_the_oracles_on_its_posteriors():
    """A filter epoch's empirical risk and protection level are those of the numpy
    oracles on the posteriors it kept, for the q_max of its divergence budget."""
    cfg = FilterConfig(n_particles=500, acquisition_particles=0, init_position_sd_m=5.0,
                       init_vertical_sd_m=5.0, n_posteriors=100, alert_limit_m=25.0,
                       error_correlation_time_s=1.0, heading_acquisition_m=0.0,
                       integrity_settling_s=0.0)
    filt = ParticleFilter(cfg, frame=FRAME, rng=np.random.default_rng(3))
    for i in range(6):
        epoch = epoch_at(np.zeros(3), clock_m=100.0, stamp_ns=i * SECOND)
        result = filt.step(epoch, None if i == 0 else MotionIncrement.stationary(1.0))
        assert result.status == UPDATED
        dist, w = oracles.posterior_distances(filt.posterior_set, result.position_enu_m)
        np.testing.assert_allclose(result.risk.empirical_risk,
                                   oracles.hazard_mass(dist, w, cfg.alert_limits_m),
                                   rtol=0, atol=1e-12)
        # The budget and threshold by the oracles, from the epoch's KL: the PAC-Bayes
        # budget eps = (KL + log((M + 1) / delta)) / M, then the largest empirical risk
        # whose bound meets the target (scalar bisection).
        m = cfg.n_posteriors
        eps = (max(result.risk.kl_nats, 0.0) + np.log((m + 1) / cfg.risk_delta)) / m
        assert result.risk.epsilon == pytest.approx(eps, rel=1e-12)
        q_max = oracles.max_empirical_risk_exact(cfg.target_risk, eps)
        assert result.protection_level_m == oracles.protection_level(dist, w, q_max)
