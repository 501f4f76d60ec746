"""Tests of the camera match state moved to the GNSS epoch (gnsscam_ros.core.camera)."""
import numpy as np
import pytest

from gnsscam_ros.core.camera import propagate_match_state


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
