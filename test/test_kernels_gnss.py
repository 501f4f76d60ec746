"""The compiled epoch kernels against their numpy oracles (test/oracles.py).

Tolerances: ranges are taken directly as |s - p| in the kernels and as
|s|^2 - 2 p.s + |p|^2 in the oracle (whose rounding is up to ~1e-6 m at 2e7 m), so
residuals agree to 1e-5 m and joint log-weights to 1e-6 nats; everything else is the
same arithmetic in another order (1e-9 and below). The robust likelihood's float32 path
(relative coordinates) is held to 1e-4 nats, of the oracle and of its float64 path.
"""
from dataclasses import replace

import numpy as np
import oracles
import pytest
from scipy.special import logsumexp
from synthetic import FRAME, epoch_at, sky

from gnsscam_ros.core import gnss
from gnsscam_ros.core.consistency import snapshot_position
from gnsscam_ros.core.frames import row_norms
from gnsscam_ros.core.kernels import gnss as gnss_kernels
from gnsscam_ros.core.particles import propagate, weighted_mean_cov
from gnsscam_ros.core.types import GLONASS, GPS

TRUTH_ENU = np.array([12.0, -7.0, 3.0])


def faulty_two_system_epoch(seed: int):
    system = np.array([GPS] * 7 + [GLONASS] * 5)
    epoch = epoch_at(TRUTH_ENU, clock_m=[3_000.0, 3_050.0], sv_ecef=sky(12, seed=seed),
                     system=system)
    rng = np.random.default_rng(seed)
    pr = epoch.pr_m + rng.normal(scale=3.0, size=12)
    pr[[2, 9]] += [60.0, 25.0]                         # an NLOS-like fault per system
    return gnss.prepare_epoch(replace(epoch, pr_m=pr), FRAME, TRUTH_ENU, 10.0, False)


@pytest.fixture(params=[1, 2])
def case(request):
    rng = np.random.default_rng(request.param)
    prep = faulty_two_system_epoch(request.param)
    # S = 3 sets of N = 517 particles (not a multiple of the kernels' block), spread 30 m.
    sets = TRUTH_ENU + rng.normal(scale=30.0, size=(3, 517, 3))
    prior = rng.normal(size=517)
    prior -= np.log(np.exp(prior).sum())
    clock_w = gnss.clock_weights(prep, TRUTH_ENU + 5.0, 3.0)
    z = (oracles.clock_corrected_residuals(sets.reshape(-1, 3), prep, clock_w)
         / prep.sigma_m).reshape(3, 517, -1)
    return prep, sets, prior, clock_w, z


def test_clock_weights_match_the_oracle(case):
    prep, *_ = case
    centre = TRUTH_ENU + 5.0
    residual = prep.pr_m - oracles.ranges(centre[None], prep.sv_enu_m)[0]
    expected = oracles.clock_inlier_weights(residual, prep.sigma_m, prep.sys_index,
                                            prep.n_systems, 3.0)
    np.testing.assert_allclose(gnss.clock_weights(prep, centre, 3.0), expected, atol=1e-12)


def test_clock_weights_take_the_ranges_of_frames_row_norms_to_the_bit(rng):
    # The kernel sums the squares left to right, as numpy's add.reduce does for three.
    for seed in range(20):
        prep = faulty_two_system_epoch(seed)
        for centre in TRUTH_ENU + rng.normal(scale=[50.0, 50.0, 20.0], size=(10, 3)):
            residual = prep.pr_m - row_norms(prep.sv_enu_m - centre)
            np.testing.assert_array_equal(
                gnss.clock_weights(prep, centre, 3.0),
                gnss_kernels.clock_inlier_weights(residual, prep.sigma_m, prep.sys_index,
                                                  prep.n_systems, 3.0, 3))


def test_residuals_match_the_oracle(case):
    prep, sets, _, clock_w, z = case
    residual = gnss.clock_corrected_residuals(sets.reshape(-1, 3), prep, clock_w)
    np.testing.assert_allclose(residual / prep.sigma_m, z.reshape(-1, z.shape[-1]),
                               atol=1e-5)


@pytest.mark.parametrize('single, tolerance', [(False, 1e-6), (True, 1e-4)])
@pytest.mark.parametrize('tempering', [1.0, 0.2])
def test_robust_joint_matches_the_oracle(case, tempering, single, tolerance):
    prep, sets, prior, clock_w, z = case
    lik = gnss.RobustLikelihood(0.3, 300.0, single_precision=single).joint(
        sets, prep, clock_w, tempering, prior)
    expected = prior + tempering * oracles.robust_log_likelihood(
        z, np.log(prep.sigma_m), 0.3, 300.0).log_lik
    np.testing.assert_allclose(lik.joint, expected, atol=tolerance)
    np.testing.assert_allclose(lik.total, np.log(np.exp(expected).sum(axis=1)),
                               atol=tolerance)


@pytest.mark.parametrize('spread_m', [3.0, 30.0, 300.0])
def test_single_precision_robust_joint_is_within_1e4_nats_of_float64(spread_m):
    """Clouds from 3 m to 300 m (offsets past the float32 path's 1 km bound included:
    their blocks take the float64 residuals), GPS + GLONASS with a fault each, clock
    offsets of 3 km."""
    rng = np.random.default_rng(7)
    prep = faulty_two_system_epoch(7)
    sets = TRUTH_ENU + rng.normal(scale=spread_m, size=(10, 2000, 3))
    sets[4, 100] += [4000.0, -2500.0, 10.0]           # far out: an exact block
    prior = np.full(2000, -np.log(2000.0))
    clock_w = gnss.clock_weights(prep, TRUTH_ENU, 3.0)
    double = gnss.RobustLikelihood(0.3, 300.0, single_precision=False).joint(
        sets, prep, clock_w, 1.0, prior)
    single = gnss.RobustLikelihood(0.3, 300.0).joint(sets, prep, clock_w, 1.0, prior)
    np.testing.assert_allclose(single.joint, double.joint, atol=1e-4)
    np.testing.assert_allclose(single.total, double.total, atol=1e-5)
    geometry = gnss.relative_geometry(sets, prep, clock_w)
    assert geometry is not None and 500.0 < geometry.max_offset_m[0] <= 1000.0
    assert np.linalg.norm(sets[4, 100] - geometry.centre_m[0]) > geometry.max_offset_m[0]
    # The inlier shares on the same views, the set with the exact block among them.
    for chosen in (0, 4):
        post = double.joint[chosen] - double.total[chosen]
        exact = gnss.robust_inlier_shares(sets[chosen], post, prep, clock_w, 0.3, 300.0)
        fast = gnss.robust_inlier_shares(sets[chosen], post, prep, clock_w, 0.3, 300.0,
                                         single.geometry, chosen)
        np.testing.assert_allclose(fast, exact, atol=1e-5)


@pytest.mark.parametrize('n', [1, 31, 32, 33, 2000])
def test_relative_views_equal_numpy_to_the_bit(n):
    """The float32 likelihood's views (one of all sets, or one per set with its own clock
    weights) are numpy's arithmetic to the bit: they decide which particles take the
    float64 path and what the float32 one computes."""
    rng = np.random.default_rng(n)
    prep = faulty_two_system_epoch(n)
    sets = TRUTH_ENU + rng.normal(scale=rng.uniform(1.0, 300.0), size=(4, n, 3))
    rows = np.stack([gnss.clock_weights(prep, TRUTH_ENU + [10.0 * s, 0.0, 0.0], 3.0)
                     for s in range(4)])
    one = gnss.relative_geometry(sets, prep, rows[0])
    each = gnss.relative_geometry(sets, prep, rows)
    for got, g, expected in [(one, 0, oracles.relative_geometry(sets, prep, rows[0]))] + [
            (each, s, oracles.relative_geometry(sets[s:s + 1], prep, rows[s]))
            for s in range(4)]:
        for value, reference in zip((got.centre_m[g], got.unit[g], got.base_m[g],
                                     got.half_inv_range[g], got.max_offset_m[g]), expected):
            np.testing.assert_array_equal(value, reference)
    sets[2, 0, 1] = np.nan                   # a poisoned particle: no float32 view
    assert gnss.relative_geometry(sets, prep, rows[0]) is None
    assert gnss.relative_geometry(sets, prep, rows) is None
    assert gnss.relative_geometry(sets[:2], prep, rows[:2]) is not None


@pytest.mark.parametrize('model', [gnss.RobustLikelihood(0.3, 300.0),
                                   gnss.RobustLikelihood(0.3, 300.0, single_precision=False),
                                   gnss.ParticleRaimLikelihood(1.05)])
def test_sets_with_clock_weights_of_their_own_are_weighed_as_alone(case, model):
    # The consistency test weighs a cloud and the cloud moved 40 m in one call, each
    # with the clock weights (and float32 centre) of its own place: to the bit what two
    # calls give.
    prep, sets, prior, clock_w, _ = case
    moved = sets[0] + [40.0, -25.0, 0.0]
    at_moved = gnss.clock_weights(prep, TRUTH_ENU + [45.0, -20.0, 0.0], 3.0)
    both = model.joint(np.stack((sets[0], moved)), prep, np.stack((clock_w, at_moved)), 0.7,
                       prior)
    for row, (points, weights) in enumerate(((sets[0], clock_w), (moved, at_moved))):
        alone = model.joint(points[None], prep, weights, 0.7, prior)
        assert np.array_equal(both.joint[row], alone.joint[0])
        assert both.total[row] == alone.total[0]


def test_single_precision_is_not_used_where_a_density_leaves_its_range(case):
    """No outlier floor (eps = 0): a density underflows float32 long before float64, so
    the joint is the float64 one, bit for bit."""
    prep, sets, prior, clock_w, _ = case
    single = gnss.RobustLikelihood(0.0, 300.0).joint(sets, prep, clock_w, 1.0, prior)
    double = gnss.RobustLikelihood(0.0, 300.0, single_precision=False).joint(
        sets, prep, clock_w, 1.0, prior)
    np.testing.assert_array_equal(single.joint, double.joint)


@pytest.mark.parametrize('tempering', [1.0, 0.2])
def test_particle_raim_joint_matches_the_oracle(case, tempering):
    prep, sets, prior, clock_w, z = case
    lik = gnss.ParticleRaimLikelihood(1.05).joint(sets, prep, clock_w, tempering, prior)
    expected = oracles.particle_raim_log_likelihood(z, np.log(prep.sigma_m), prior, 1.05)
    np.testing.assert_allclose(lik.joint, prior + tempering * expected.log_lik, atol=1e-6)
    np.testing.assert_allclose(lik.gamma, expected.gamma, atol=1e-9)


@pytest.mark.parametrize('n', [1, 3, 4, 63, 64, 65, 517])
def test_log_sum_exp_kernel_equals_scipy(n):
    """Lengths around its four partial results and its blocks; values spread over 2,000
    nats (most exponentials underflow), a -inf among them, and all -inf."""
    rng = np.random.default_rng(n)
    values = rng.uniform(-1000.0, 1000.0, n)
    if n > 1:
        values[n // 2] = -np.inf
    expected = logsumexp(values)
    assert gnss_kernels._log_sum_exp(values) == pytest.approx(expected, rel=1e-15, abs=1e-12)
    shifted = values - values.max() - 0.5
    assert gnss_kernels._log_sum_exp(shifted) == pytest.approx(logsumexp(shifted), abs=1e-14)
    assert gnss_kernels._log_sum_exp(np.full(n, -np.inf)) == -np.inf


def inlier_shares(single, sets, prior, prep, clock_w):
    """The robust inlier shares of ``sets[1]``: float64, or float32 on the views the
    float32 joint of every set took (as the filter takes them)."""
    geometry = None
    if single:
        likelihood = gnss.RobustLikelihood(0.3, 300.0)
        geometry = likelihood.joint(sets, prep, clock_w, 1.0, prior).geometry
        assert geometry is not None
    return gnss.robust_inlier_shares(sets[1], prior, prep, clock_w, 0.3, 300.0, geometry, 1)


@pytest.mark.parametrize('single, tolerance', [(False, 1e-9), (True, 1e-5)])
def test_robust_inlier_shares_match_the_oracle(case, single, tolerance):
    prep, sets, prior, clock_w, z = case
    probability, share = inlier_shares(single, sets, prior, prep, clock_w)
    log_sigma = np.log(prep.sigma_m)
    np.testing.assert_allclose(
        probability, oracles.robust_inlier_probability(z[1], log_sigma, 0.3, 300.0, prior),
        atol=tolerance)
    np.testing.assert_allclose(
        share, oracles.robust_log_likelihood(z[1:2], log_sigma, 0.3, 300.0).gamma[0],
        atol=tolerance)


def with_learned_mixture(prep):
    """The epoch under a learned error mixture: NLOS components of 0.05-0.4 weight whose
    flat tops end 8-40 m out, so a 30 m cloud puts residuals below 0, on the tops and
    beyond them."""
    k = prep.pr_m.shape[0]
    rng = np.random.default_rng(k)
    return replace(prep, wide_share=rng.uniform(0.05, 0.4, k),
                   wide_mean_m=rng.uniform(0.0, 20.0, k), wide_sd_m=rng.uniform(4.0, 10.0, k))


@pytest.mark.parametrize('single, tolerance', [(False, 1e-6), (True, 1e-4)])
def test_robust_joint_under_a_learned_mixture_matches_the_oracle(case, single, tolerance):
    prep, sets, prior, clock_w, z = case
    prep = with_learned_mixture(prep)
    e = z * prep.sigma_m
    lik = gnss.RobustLikelihood(0.3, 300.0, single_precision=single).joint(
        sets, prep, clock_w, 0.4, prior)
    expected = prior + 0.4 * oracles.mixture_log_likelihood(
        e, prep.sigma_m, prep.wide_share, prep.wide_mean_m, prep.wide_sd_m,
        gnss.FAULT_SHARE, 300.0)
    # Every region of the density is in the test: below 0, on the flat top, beyond it.
    top = prep.wide_mean_m + 2.0 * prep.wide_sd_m
    assert (e < 0).mean() > 0.2 and ((e > 0) & (e < top)).mean() > 0.2
    assert (e > top).mean() > 0.05
    np.testing.assert_allclose(lik.joint, expected, atol=tolerance)
    np.testing.assert_allclose(lik.total, np.log(np.exp(expected).sum(axis=1)),
                               atol=tolerance)


@pytest.mark.parametrize('single, tolerance', [(False, 1e-9), (True, 1e-5)])
def test_robust_inlier_shares_under_a_learned_mixture_match_the_oracle(
        case, single, tolerance):
    prep, sets, prior, clock_w, z = case
    prep = with_learned_mixture(prep)
    probability, share = inlier_shares(single, sets, prior, prep, clock_w)
    core, whole = oracles.mixture_densities(z[1] * prep.sigma_m, prep.sigma_m,
                                            prep.wide_share, prep.wide_mean_m, prep.wide_sd_m,
                                            gnss.FAULT_SHARE, 300.0)
    inlier = core / whole
    np.testing.assert_allclose(probability, np.exp(prior) @ inlier, atol=tolerance)
    np.testing.assert_allclose(share, inlier.mean(axis=0) / inlier.mean(axis=0).sum(),
                               atol=tolerance)


@pytest.mark.parametrize('single', [False, True])
def test_robust_joint_keeps_a_tiny_outlier_floor_finite(single):
    # eps / range of 1e-12 over 64 satellites: the product of the floors (1e-768) would
    # underflow; the kernel takes a log per group of satellites instead (float32: a log
    # per 3 satellites, of a product rounded to a few float32 ulp: 1e-4 over the 22).
    rng = np.random.default_rng(4)
    sky_64 = sky(64, seed=7)
    epoch = epoch_at(TRUTH_ENU, clock_m=0.0, sv_ecef=sky_64)
    prep = gnss.prepare_epoch(epoch, FRAME, TRUTH_ENU, 10.0, False)
    far = TRUTH_ENU + rng.normal(scale=5_000.0, size=(1, 50, 3))  # every satellite an outlier
    clock_w = gnss.clock_weights(prep, TRUTH_ENU, 3.0)
    lik = gnss.RobustLikelihood(1e-9, 1e3, single_precision=single).joint(
        far, prep, clock_w, 1.0, np.zeros(50))
    assert np.isfinite(lik.joint).all()
    z = (oracles.clock_corrected_residuals(far[0], prep, clock_w) / prep.sigma_m)[None]
    expected = oracles.robust_log_likelihood(z, np.log(prep.sigma_m), 1e-9, 1e3).log_lik
    np.testing.assert_allclose(lik.joint, expected, rtol=0.0 if single else 1e-9,
                               atol=1e-4 if single else 0.0)


def test_propagation_is_the_oracle_to_rounding(rng):
    particles = np.c_[rng.normal(scale=20.0, size=(300, 3)), rng.uniform(-3, 3, 300)]
    args = (np.array([8.0, 8.4, 7.5]), np.array([0.1, 0.13, 0.06]), 0.4,
            np.array([0.3, 0.3, 0.2]), 3e-4)
    noise = np.random.default_rng(9).standard_normal((3, 300, 4), dtype=np.float32)
    moved = propagate(particles, *args, noise)
    # The same arithmetic, but the kernel's sin/cos are libm's and the oracle's numpy's:
    # numpy 1.24 (Debian 12) computes float64 sin/cos with its own SIMD code, a few ulp
    # (1e-14 m here) from libm; numpy 1.26 and 2.x give libm's bits.
    np.testing.assert_allclose(moved, oracles.propagate(particles, *args, noise), rtol=0,
                               atol=1e-12)
    log_w = rng.normal(size=300)
    log_w -= np.log(np.exp(log_w).sum())
    mean, cov = weighted_mean_cov(moved[0], log_w)
    ref_mean, ref_cov = oracles.weighted_mean_cov(moved[0, :, :3], log_w)
    np.testing.assert_allclose(mean, ref_mean, atol=1e-9)
    np.testing.assert_allclose(cov, ref_cov, atol=1e-9)


def test_snapshot_position_is_the_numpy_oracle():
    # The kernel does numpy's arithmetic step for step, its least squares by a Householder
    # QR where numpy's lstsq takes LAPACK's SVD: the two agree to rounding, which on 2e7 m
    # ranges moves a solution by nanometres (1e-8 m over these cases); 1e-6 m bounds it.
    rng = np.random.default_rng(4)
    for trial in range(60):
        n_systems = 1 + trial % 3
        sys_index = np.arange(12) % n_systems
        sv = FRAME.ecef_to_enu(sky(12, seed=trial))
        truth = rng.normal(scale=200.0, size=3)
        pr = (np.linalg.norm(sv - truth, axis=1) + 300.0 + 40.0 * sys_index
              + rng.normal(scale=3.0, size=12))
        pr[rng.integers(12)] += rng.uniform(0.0, 100.0)             # an NLOS delay
        sigma = rng.uniform(2.0, 8.0, 12)
        start = truth + rng.normal(scale=50.0, size=3)
        got = snapshot_position(sv, pr, sigma, sys_index, n_systems, start)
        want = oracles.snapshot_position(sv, pr, sigma, sys_index, n_systems, start)
        np.testing.assert_allclose(got, want, rtol=0.0, atol=1e-6)
    # A constellation index without a satellite leaves its clock column empty: rank
    # deficient, the QR hands the system to LAPACK's minimum-norm solution, numpy's own.
    gap = np.arange(12) % 2 * 2
    got = snapshot_position(sv, pr, sigma, gap, 3, start)
    want = oracles.snapshot_position(sv, pr, sigma, gap, 3, start)
    assert got is not None
    np.testing.assert_allclose(got, want, rtol=0.0, atol=1e-6)
    # No solution: too few satellites, a poisoned start, a zero sigma.
    assert snapshot_position(sv[:5], pr[:5], sigma[:5], sys_index[:5], 2, start) is None
    assert snapshot_position(sv, pr, sigma, sys_index, n_systems, start * np.nan) is None
    assert snapshot_position(sv, pr, sigma * 0.0, sys_index, n_systems, start) is None


def test_satellite_checks_match_the_oracle():
    # Random epochs with every kind of bad satellite, several in one epoch and one
    # satellite failing several checks (the first reason counts).
    rng = np.random.default_rng(11)
    specials = [np.nan, np.inf, -np.inf, 0.0, -5.0, 1e160, 2e8, 1e13]
    for trial in range(300):
        k = int(rng.integers(1, 40))
        epoch = epoch_at(TRUTH_ENU, clock_m=0.0, sv_ecef=sky(k, seed=trial))
        arrays = {name: getattr(epoch, name).astype(float).copy()
                  for name in ('pr_m', 'var_m2', 'elevation_deg', 'cn0_dbhz')}
        sv = epoch.sv_pos_ecef_m.copy()
        sv_id = rng.integers(1, 6, k) if trial % 3 == 0 else epoch.sv_id
        for _ in range(int(rng.integers(0, 6))):
            i = int(rng.integers(k))
            target = rng.choice(['pr_m', 'var_m2', 'elevation_deg', 'cn0_dbhz', 'sv'])
            value = rng.choice(specials + [rng.uniform(-90, 90)])
            if target == 'sv':
                sv[i, int(rng.integers(3))] = value
            else:
                arrays[target][i] = value
        bad = replace(epoch, sv_pos_ecef_m=sv, sv_id=sv_id, **arrays)
        masks = {'elevation_mask_deg': 10.0, 'cn0_mask_dbhz': 20.0} if trial % 2 else {}
        check = gnss.check_epoch(bad, **masks)
        keep, rejected = oracles.satellite_rejections(bad, **masks)
        np.testing.assert_array_equal(check.keep, keep)
        assert check.rejected == rejected


def test_constellations_of_one_satellite_are_set_aside_in_system_order():
    system = np.array([GLONASS, GPS, 5, GLONASS, GPS, GPS, 7])
    epoch = epoch_at(TRUTH_ENU, clock_m=0.0, sv_ecef=sky(7, seed=2), system=system)
    prep = gnss.prepare_epoch(epoch, FRAME, TRUTH_ENU, 10.0, False)
    assert prep.n_systems == 2
    # GPS (1) before GLONASS (4); systems 5 and 7 have one satellite each.
    np.testing.assert_array_equal(prep.sys_index, [1, 0, 1, 0, 0])
    np.testing.assert_array_equal(prep.sv_key // 1000, [GLONASS, GPS, GLONASS, GPS, GPS])
