"""Risk bound: inverse Bernoulli divergence, Gaussian KL, hazard mass."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import brentq
from oracles import bernoulli_kl, bernoulli_kl_gap, max_empirical_risk_exact
from scipy.stats import multivariate_normal

from gnsscam_ros.core import integrity


@pytest.mark.parametrize('q,eps', [(0.0, 0.3), (0.05, 0.24), (0.3, 0.5), (0.8, 0.01),
                                   (0.5, 2.0)])
def test_inverse_bernoulli_matches_numeric_root(q, eps):
    expected = brentq(lambda p: bernoulli_kl(q, p) - eps, q, 1 - 1e-15) - q
    assert np.isclose(integrity.inverse_bernoulli_exact(q, eps), expected, atol=1e-12)


def test_inverse_bernoulli_at_zero_risk_is_closed_form():
    # kl(0 || t) = -log(1 - t) = eps  =>  t = 1 - exp(-eps); the approximation gives 0.
    eps = 0.4
    assert np.isclose(integrity.inverse_bernoulli_exact(0.0, eps), 1 - np.exp(-eps))
    assert integrity.inverse_bernoulli_approx(0.0, eps) == 0.0


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(st.floats(0.0, 0.999), st.one_of(st.floats(1e-300, 1e-4), st.floats(1e-4, 5.0)))
def test_bound_is_at_least_the_empirical_risk(q, eps):
    """The gap is never negative, for budgets down to 1e-300 too (where the root lies
    below the resolution of doubles near q), and not short of the root by more than the
    resolution of the KL in doubles (~1e-16 nats; an accurate KL judges it)."""
    t = float(integrity.inverse_bernoulli_exact(q, eps))
    assert t >= 0.0 and q + t <= 1.0 + 1e-12, t
    divergence = bernoulli_kl_gap(q, t)
    assert divergence >= eps * (1.0 - 1e-6) - 1e-15 or q + t >= 1 - 1e-9, (t, divergence)
    if eps >= 1e-4:
        assert np.isclose(divergence, eps, rtol=1e-6) or q + t >= 1 - 1e-9


def test_approximation_is_second_order_accurate_for_small_eps():
    q, eps = 0.3, 1e-4
    exact = integrity.inverse_bernoulli_exact(q, eps)
    assert np.isclose(integrity.inverse_bernoulli_approx(q, eps), exact, rtol=0.01)


def test_risk_bound_epsilon_and_clipping():
    bound = integrity.risk_bound(np.array([0.0, 0.2, 0.99]), kl_nats=1.5, n_posteriors=10,
                                 delta=0.1)
    assert np.isclose(bound.epsilon, (1.5 + np.log(11 / 0.1)) / 10)
    assert np.all(bound.risk_bound >= bound.empirical_risk)
    assert np.all(bound.risk_bound <= 1.0)
    with pytest.raises(ValueError, match='unknown inverse'):
        integrity.risk_bound(np.array([0.1]), 0.0, 10, 0.1, method='bogus')


def test_gaussian_kl_known_values(rng):
    mean0, mean1 = np.zeros(3), np.array([1.0, 2.0, 0.0])
    cov = np.diag([1.0, 4.0, 9.0])
    assert np.isclose(integrity.gaussian_kl(mean0, cov, mean0, cov, floor_m2=0.0), 0.0)
    # Equal covariances: KL = 0.5 * mahalanobis^2.
    assert np.isclose(integrity.gaussian_kl(mean0, cov, mean1, cov, floor_m2=0.0),
                      0.5 * (1.0 + 4.0 / 4.0))
    # Against a Monte Carlo estimate with scipy densities.
    cov1 = np.diag([2.0, 1.0, 3.0])
    x = rng.multivariate_normal(mean0, cov, size=200000)
    mc = np.mean(multivariate_normal(mean0, cov).logpdf(x)
                 - multivariate_normal(mean1, cov1).logpdf(x))
    assert np.isclose(integrity.gaussian_kl(mean0, cov, mean1, cov1, floor_m2=0.0), mc,
                      rtol=0.02)


def test_hazard_mass_counts_weight_beyond_the_limit():
    pos = np.zeros((2, 4, 3))
    pos[0, :, 0] = [0.0, 5.0, 10.0, 20.0]
    pos[1, :, 1] = [0.0, 0.0, 0.0, 9.0]
    log_w = np.log(np.full((2, 4), 0.25))
    risk = integrity.hazard_mass(pos, log_w, np.zeros(3), np.array([8.0, 16.0]))
    # Set 0: 2 of 4 beyond 8 m, 1 beyond 16 m; set 1: 1 of 4 beyond 8 m, none beyond 16.
    np.testing.assert_allclose(risk, [(0.5 + 0.25) / 2, 0.25 / 2])
    # Vertical distance is ignored for a horizontal alert limit.
    pos[:, :, 2] = 100.0
    np.testing.assert_allclose(integrity.hazard_mass(pos, log_w, np.zeros(3),
                                                     np.array([8.0])), [0.375])


def test_inverse_methods_are_the_registry_of_the_parameter():
    methods = ('exact', 'approx')
    assert integrity.INVERSE_METHODS == tuple(integrity.INVERSE_BERNOULLI) == methods
    q, eps = np.array([0.0, 0.02, 0.3]), 0.05
    for name, inverse in integrity.INVERSE_BERNOULLI.items():
        assert integrity.inverse_method(name) is inverse
        np.testing.assert_array_equal(integrity.inverse_bernoulli(q, eps, name),
                                      inverse.gap(q, eps))
        q_max = integrity.max_empirical_risk(0.1, eps, name)
        assert q_max == inverse.max_empirical_risk(0.1, eps)
        assert np.isclose(integrity.upper_risk(q_max, eps, name), 0.1)
    np.testing.assert_array_equal(integrity.inverse_method('exact').gap(q, eps),
                                  integrity.inverse_bernoulli_exact(q, eps))
    for call in (lambda: integrity.inverse_method('bisect'),
                 lambda: integrity.max_empirical_risk(0.1, eps, 'bisect')):
        with pytest.raises(ValueError, match='unknown inverse Bernoulli method'):
            call()


@pytest.mark.parametrize('target', [0.01, 0.1, 0.3])
def test_compiled_threshold_equals_the_python_bisection(target):
    for eps in np.linspace(0.0, 0.5, 26):
        assert integrity.max_empirical_risk(target, eps) == max_empirical_risk_exact(
            target, eps)
