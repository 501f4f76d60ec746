"""Tests of the camera distribution over particles (gnsscam_ros.core.camera)."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.special import logsumexp

from gnsscam_ros.core.camera import camera_log_distribution, propagate_match_state


def test_propagate_constant_acceleration():
    pos = propagate_match_state([1.0, 2.0, 3.0], [2.0, 0.0, -1.0], [0.0, 4.0, 2.0], 0.5)
    # x + v dt + a dt^2 / 2 by hand.
    np.testing.assert_allclose(pos, [1.0 + 1.0, 2.0 + 0.5, 3.0 - 0.5 + 0.25])


def test_propagate_zero_dt_is_identity_and_negative_dt_goes_back():
    x, v, a = np.array([5.0, -3.0, 1.0]), np.array([10.0, 1.0, 0.0]), np.array([1, 0, 0])
    np.testing.assert_array_equal(propagate_match_state(x, v, a, 0.0), x)
    fwd = propagate_match_state(x, v, a, 0.2)
    # Going back from fwd with the velocity at fwd returns to x.
    back = propagate_match_state(fwd, v + a * 0.2, a, -0.2)
    np.testing.assert_allclose(back, x, atol=1e-12)


def test_propagate_rejects_non_finite():
    with pytest.raises(ValueError):
        propagate_match_state([0, 0, 0], [0, 0, 0], [0, 0, 0], float('nan'))
    with pytest.raises(ValueError):
        propagate_match_state([0, np.inf, 0], [0, 0, 0], [0, 0, 0], 1.0)


def test_log_distribution_hand_example():
    parts = np.array([[0.0, 0.0, 0.0], [3.0, 4.0, 0.0], [0.0, 0.0, 10.0]])
    logq = camera_log_distribution(parts, [0.0, 0.0, 0.0], temperature_m=5.0)
    # distances 0, 5, 10 -> weights 1, e^-1, e^-2
    w = np.exp([0.0, -1.0, -2.0])
    np.testing.assert_allclose(np.exp(logq), w / w.sum())


def test_log_distribution_2d_uses_horizontal_distance():
    parts2 = np.array([[0.0, 0.0], [3.0, 4.0]])
    parts3 = np.array([[0.0, 0.0, 100.0], [3.0, 4.0, -50.0]])
    match = [0.0, 0.0, 7.0]
    a = camera_log_distribution(parts2, match, 2.0)
    b = camera_log_distribution(parts3 * [1, 1, 0], [0.0, 0.0, 0.0], 2.0)
    np.testing.assert_allclose(a, b)


def test_log_distribution_far_particles_stay_finite():
    # exp(-1e6 / 5) underflows; the log-space softmax must not.
    parts = np.array([[1e6, 0.0, 0.0], [1e6 + 5.0, 0.0, 0.0]])
    logq = camera_log_distribution(parts, [0.0, 0.0, 0.0], 5.0)
    assert np.all(np.isfinite(logq))
    np.testing.assert_allclose(np.exp(logq), [1 / (1 + np.exp(-1)), 1 / (1 + np.e)])


@pytest.mark.parametrize('bad', [0.0, -1.0, float('nan'), float('inf')])
def test_log_distribution_rejects_bad_temperature(bad):
    with pytest.raises(ValueError):
        camera_log_distribution(np.zeros((2, 3)), np.zeros(3), bad)


def test_log_distribution_rejects_bad_shapes():
    with pytest.raises(ValueError):
        camera_log_distribution(np.zeros((0, 3)), np.zeros(3))
    with pytest.raises(ValueError):
        camera_log_distribution(np.zeros((4, 4)), np.zeros(3))
    with pytest.raises(ValueError):
        camera_log_distribution(np.zeros((4, 3)), np.zeros(2))


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 50), st.floats(0.1, 100.0), st.integers(0, 2**32 - 1))
def test_log_distribution_normalised_and_monotone(p, temperature, seed):
    rng = np.random.default_rng(seed)
    parts = rng.normal(0.0, 50.0, (p, 3))
    match = rng.normal(0.0, 50.0, 3)
    logq = camera_log_distribution(parts, match, temperature)
    assert logq.shape == (p,)
    assert logsumexp(logq) == pytest.approx(0.0, abs=1e-9)
    # Closer particles are never less likely.
    d = np.linalg.norm(parts - match, axis=1)
    order = np.argsort(d)
    assert np.all(np.diff(logq[order]) <= 1e-12)
