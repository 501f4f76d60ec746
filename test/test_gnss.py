"""GNSS module: checks, Earth rotation, clock handling and likelihoods on exact geometry."""
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from synthetic import (C_MPS, FRAME, WGS84_A_M, WGS84_OMEGA_RPS, enu_to_ecef, epoch_at,
                       light_time_range, sky)

from gnsscam_ros.core import gnss
from gnsscam_ros.core.filter import FilterConfig
from gnsscam_ros.core.frames import sagnac_corrected
from gnsscam_ros.core.snapshot import solve_snapshot
from gnsscam_ros.core.types import GLONASS, GPS

TRUTH_ENU = np.array([12.0, -7.0, 3.0])


def grid_around(centre, half=20.0, step=1.0):
    g = np.arange(-half, half + step / 2, step)
    e, n = np.meshgrid(g, g)
    return np.stack([e.ravel() + centre[0], n.ravel() + centre[1],
                     np.full(e.size, centre[2])], 1)


def test_noise_free_snapshot_recovers_position_and_clock():
    epoch = epoch_at(TRUTH_ENU, clock_m=-136_933.5)
    fix = solve_snapshot(epoch)
    assert fix.converged
    np.testing.assert_allclose(FRAME.ecef_to_enu(fix.ecef_m), TRUTH_ENU, atol=1e-3)
    np.testing.assert_allclose(fix.clock_m, [-136_933.5], atol=1e-3)


def test_snapshot_two_constellations_separate_clocks():
    system = np.array([GPS] * 5 + [GLONASS] * 5)
    epoch = epoch_at(TRUTH_ENU, clock_m=[500.0, 530.0], sv_ecef=sky(10, seed=2),
                     system=system)
    fix = solve_snapshot(epoch)
    np.testing.assert_allclose(FRAME.ecef_to_enu(fix.ecef_m), TRUTH_ENU, atol=1e-3)
    np.testing.assert_allclose(fix.clock_m, [500.0, 530.0], atol=1e-3)


def test_sagnac_correction_matters_and_is_exact():
    """The corrected range equals the light-time range solved from first principles
    (synthetic.light_time_range), and its difference from the straight distance is the
    published first-order Earth-rotation correction omega_E (x_s y_r - y_s x_r) / c
    (IS-GPS-200, 20.3.3.4.3.4): tens of metres here."""
    epoch = epoch_at(TRUTH_ENU, clock_m=0.0)
    rx = enu_to_ecef(TRUTH_ENU)
    sv = epoch.sv_pos_ecef_m
    corrected = np.linalg.norm(sagnac_corrected(sv, rx) - rx, axis=1)
    raw = np.linalg.norm(sv - rx, axis=1)
    # One rotation with the flight time of the straight distance is what the code does;
    # the exact light time differs by omega |sv| (delta range / c) ~ 0.2 mm.
    np.testing.assert_allclose(corrected, epoch.pr_m, rtol=0, atol=1e-3)
    first_order = WGS84_OMEGA_RPS * (sv[:, 0] * rx[1] - sv[:, 1] * rx[0]) / C_MPS
    np.testing.assert_allclose(corrected - raw, first_order, rtol=0, atol=1e-3)
    assert np.max(np.abs(first_order)) > 5.0           # tens of metres at mid latitudes


def test_sagnac_correction_at_a_known_geometry():
    """A receiver on the equator at 0 deg longitude, a satellite due east at GPS radius in
    the equatorial plane: the Earth turns the receiver towards the satellite during the
    flight, shortening the range by omega_E a r_s sin(lambda_s) / c (35.7 m here)."""
    rx = np.array([WGS84_A_M, 0.0, 0.0])
    lon = np.radians(60.0)
    sv = np.array([[26_560e3 * np.cos(lon), 26_560e3 * np.sin(lon), 0.0]])
    shortening = WGS84_OMEGA_RPS * WGS84_A_M * 26_560e3 * np.sin(lon) / C_MPS
    assert shortening == pytest.approx(35.68, abs=0.01)
    corrected = np.linalg.norm(sagnac_corrected(sv, rx) - rx, axis=1)
    raw = np.linalg.norm(sv - rx, axis=1)
    assert raw - corrected == pytest.approx([shortening], abs=1e-3)
    assert corrected == pytest.approx(light_time_range(sv, rx), abs=1e-3)


def prepared(epoch, centre=TRUTH_ENU):
    return gnss.prepare_epoch(epoch, FRAME, centre, 10.0, False)


def joint_of(likelihood, pts, prep, clock_w):
    """The likelihood's joint log-weights of one set of points under a uniform prior."""
    model = gnss.make_likelihood(FilterConfig(likelihood=likelihood))
    uniform = np.full(len(pts), -np.log(len(pts)))
    return model.joint(pts[None], prep, clock_w, 1.0, uniform)


@pytest.mark.parametrize('likelihood', ['particle_raim', 'robust'])
def test_likelihood_peaks_at_truth_with_unknown_clock(likelihood):
    system = np.array([GPS] * 6 + [GLONASS] * 4)
    epoch = epoch_at(TRUTH_ENU, clock_m=[80_000.0, 80_040.0], sv_ecef=sky(10, seed=4),
                     system=system)
    centre = TRUTH_ENU + np.array([6.0, -4.0, 0.0])     # the prior is off the truth
    prep = prepared(epoch, centre)
    pts = grid_around(TRUTH_ENU)
    lik = joint_of(likelihood, pts, prep, gnss.clock_weights(prep, centre, 8.0))
    best = pts[np.argmax(lik.joint[0])]
    np.testing.assert_allclose(best[:2], TRUTH_ENU[:2], atol=1.01)


def test_faulty_satellite_gets_lowest_mixture_weight():
    epoch = epoch_at(TRUTH_ENU, clock_m=100.0, sv_ecef=sky(9, seed=5))
    pr = epoch.pr_m.copy()
    pr[3] += 80.0
    prep = prepared(replace(epoch, pr_m=pr))
    rng = np.random.default_rng(0)
    pts = TRUTH_ENU + rng.normal(scale=3.0, size=(2000, 3))
    w = gnss.clock_weights(prep, TRUTH_ENU, 3.0)
    assert w[3] < 1e-6 * w.max()                       # the fault is out of the clock
    lik = joint_of('particle_raim', pts, prep, w)
    assert np.argmin(lik.gamma[0]) == 3
    assert np.isclose(lik.gamma[0].sum(), 1.0)
    # The robust model's inlier share says the same.
    uniform = np.full(len(pts), -np.log(len(pts)))
    probability, share = gnss.robust_inlier_shares(pts, uniform, prep, w, 0.3, 300.0)
    assert np.argmin(share) == 3 and np.isclose(share.sum(), 1.0)
    assert probability[3] < 0.01 < 0.9 < np.delete(probability, 3).min()


@settings(max_examples=30, deadline=None)
@given(st.floats(-1e5, 1e5), st.floats(-1e3, 1e3))
def test_likelihood_invariant_to_per_system_clock(shift_gps, shift_glo):
    system = np.array([GPS] * 5 + [GLONASS] * 4)
    base = epoch_at(TRUTH_ENU, clock_m=0.0, sv_ecef=sky(9, seed=6), system=system)
    shifted = replace(base, pr_m=base.pr_m + np.where(system == GPS, shift_gps, shift_glo))
    pts = grid_around(TRUTH_ENU, half=10.0, step=5.0)
    out = []
    for ep in (base, shifted):
        prep = prepared(ep)
        out.append(joint_of('robust', pts, prep, gnss.clock_weights(prep, TRUTH_ENU, 3.0)))
    np.testing.assert_allclose(out[0].joint, out[1].joint, atol=1e-6)


def test_check_epoch_rejects_bad_satellites():
    epoch = epoch_at(TRUTH_ENU, sv_ecef=sky(8))
    pr = epoch.pr_m.copy()
    pr[0] = np.nan
    pr[1] = np.inf
    sv_id = epoch.sv_id.copy()
    sv_id[3] = sv_id[2]                               # a duplicated satellite
    check = gnss.check_epoch(replace(epoch, pr_m=pr, sv_id=sv_id))
    assert check.rejected == {'non_finite': 2, 'duplicate': 2}
    assert check.usable and check.keep.sum() == 4
    pr[4] = np.nan
    check = gnss.check_epoch(replace(epoch, pr_m=pr, sv_id=sv_id))
    assert not check.usable and '3 usable' in check.reason


def test_the_kept_satellites_are_the_epoch_itself_only_when_all_pass():
    epoch = epoch_at(TRUTH_ENU, sv_ecef=sky(8))
    assert gnss.kept_satellites(epoch, gnss.check_epoch(epoch)) is epoch
    pr = epoch.pr_m.copy()
    pr[2] = np.nan
    bad = replace(epoch, pr_m=pr)
    kept = gnss.kept_satellites(bad, gnss.check_epoch(bad))
    assert kept.n_sv == 7 and np.isfinite(kept.pr_m).all()
    np.testing.assert_array_equal(kept.sv_id, np.delete(epoch.sv_id, 2))


def test_single_satellite_constellation_is_set_aside():
    system = np.array([GPS] * 6 + [GLONASS])
    epoch = epoch_at(TRUTH_ENU, sv_ecef=sky(7, seed=3), system=system)
    prep = prepared(epoch)
    assert prep.pr_m.shape == (6,) and prep.n_systems == 1


def test_likelihood_objects_are_the_registry_of_the_likelihood_parameter():
    assert gnss.LIKELIHOODS == tuple(gnss.LIKELIHOOD_MODELS) == ('particle_raim', 'robust')
    raim = gnss.make_likelihood(FilterConfig(likelihood='particle_raim', dirichlet_alpha=1.2))
    robust = gnss.make_likelihood(FilterConfig(outlier_prob=0.2).gnss)
    assert raim == gnss.ParticleRaimLikelihood(1.2)
    assert robust == gnss.RobustLikelihood(0.2, FilterConfig().outlier_range_m)
    with pytest.raises(ValueError, match='likelihood must be one of'):
        gnss.make_likelihood(SimpleNamespace(likelihood='gauss'))
