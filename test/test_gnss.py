"""GNSS module: checks, Earth rotation, clock handling and likelihoods on exact geometry."""
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from synthetic import FRAME, epoch_at, sky

from gnsscam_ros.core import gnss
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
    epoch = epoch_at(TRUTH_ENU, clock_m=0.0)
    rx = FRAME.enu_to_ecef(TRUTH_ENU)
    corrected = np.linalg.norm(sagnac_corrected(epoch.sv_pos_ecef_m, rx) - rx, axis=1)
    raw = np.linalg.norm(epoch.sv_pos_ecef_m - rx, axis=1)
    np.testing.assert_allclose(corrected, epoch.pr_m, atol=1e-4)
    assert np.max(np.abs(raw - epoch.pr_m)) > 5.0      # tens of metres at mid latitudes


def test_ranges_match_direct_norm(rng):
    pts = rng.normal(scale=50.0, size=(100, 3))
    sv = FRAME.ecef_to_enu(sky())
    direct = np.linalg.norm(sv[None] - pts[:, None], axis=2)
    np.testing.assert_allclose(gnss.ranges(pts, sv), direct, atol=1e-5)


def prepared(epoch, centre=TRUTH_ENU):
    return gnss.prepare_epoch(epoch, FRAME, centre, 10.0, False)


@pytest.mark.parametrize('likelihood', ['particle_raim', 'robust'])
def test_likelihood_peaks_at_truth_with_unknown_clock(likelihood):
    system = np.array([GPS] * 6 + [GLONASS] * 4)
    epoch = epoch_at(TRUTH_ENU, clock_m=[80_000.0, 80_040.0], sv_ecef=sky(10, seed=4),
                     system=system)
    centre = TRUTH_ENU + np.array([6.0, -4.0, 0.0])     # the prior is off the truth
    prep = prepared(epoch, centre)
    pts = grid_around(TRUTH_ENU)
    res_c = prep.pr_m - gnss.ranges(centre[None], prep.sv_enu_m)[0]
    w = gnss.clock_inlier_weights(res_c, prep.sigma_m, prep.sys_index, prep.n_systems, 8.0)
    z = (gnss.clock_corrected_residuals(pts, prep, w) / prep.sigma_m)[None]
    if likelihood == 'particle_raim':
        lik = gnss.particle_raim_log_likelihood(z, np.log(prep.sigma_m),
                                                np.full(len(pts), -np.log(len(pts))), 1.01)
    else:
        lik = gnss.robust_log_likelihood(z, np.log(prep.sigma_m), 0.3, 300.0)
    best = pts[np.argmax(lik.log_lik[0])]
    np.testing.assert_allclose(best[:2], TRUTH_ENU[:2], atol=1.01)


def test_faulty_satellite_gets_lowest_mixture_weight():
    epoch = epoch_at(TRUTH_ENU, clock_m=100.0, sv_ecef=sky(9, seed=5))
    pr = epoch.pr_m.copy()
    pr[3] += 80.0
    prep = prepared(replace(epoch, pr_m=pr))
    rng = np.random.default_rng(0)
    pts = TRUTH_ENU + rng.normal(scale=3.0, size=(2000, 3))
    res_c = prep.pr_m - gnss.ranges(TRUTH_ENU[None], prep.sv_enu_m)[0]
    w = gnss.clock_inlier_weights(res_c, prep.sigma_m, prep.sys_index, prep.n_systems, 3.0)
    assert w[3] < 1e-6 * w.max()                       # the fault is out of the clock
    z = (gnss.clock_corrected_residuals(pts, prep, w) / prep.sigma_m)[None]
    lik = gnss.particle_raim_log_likelihood(z, np.log(prep.sigma_m),
                                            np.full(len(pts), -np.log(len(pts))), 1.01)
    assert np.argmin(lik.gamma[0]) == 3
    assert np.isclose(lik.gamma[0].sum(), 1.0)


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
        res_c = prep.pr_m - gnss.ranges(TRUTH_ENU[None], prep.sv_enu_m)[0]
        w = gnss.clock_inlier_weights(res_c, prep.sigma_m, prep.sys_index, prep.n_systems,
                                      3.0)
        z = (gnss.clock_corrected_residuals(pts, prep, w) / prep.sigma_m)[None]
        out.append(gnss.robust_log_likelihood(z, np.log(prep.sigma_m), 0.3, 300.0).log_lik)
    np.testing.assert_allclose(out[0], out[1], atol=1e-6)


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


def test_single_satellite_constellation_is_set_aside():
    system = np.array([GPS] * 6 + [GLONASS])
    epoch = epoch_at(TRUTH_ENU, sv_ecef=sky(7, seed=3), system=system)
    prep = prepared(epoch)
    assert prep.pr_m.shape == (6,) and prep.n_systems == 1


def test_likelihood_objects_are_the_registry_of_the_likelihood_parameter():
    from gnsscam_ros.core.filter import FilterConfig
    assert gnss.LIKELIHOODS == tuple(gnss.LIKELIHOOD_MODELS) == ('particle_raim', 'robust')
    raim = gnss.make_likelihood(FilterConfig(likelihood='particle_raim', dirichlet_alpha=1.2))
    robust = gnss.make_likelihood(FilterConfig(outlier_prob=0.2).gnss)
    assert raim == gnss.ParticleRaimLikelihood(1.2)
    assert robust == gnss.RobustLikelihood(0.2, FilterConfig().outlier_range_m)
    with pytest.raises(ValueError, match='likelihood must be one of'):
        gnss.make_likelihood(SimpleNamespace(likelihood='gauss'))
    # The objects compute what the functions compute, and the chosen set's weights.
    rng = np.random.default_rng(3)
    z = rng.normal(size=(3, 50, 7))
    log_sigma = np.log(rng.uniform(2.0, 5.0, 7))
    prior = np.full(50, -np.log(50))
    lik = raim.log_likelihood(z, log_sigma, prior)
    ref = gnss.particle_raim_log_likelihood(z, log_sigma, prior, 1.2)
    np.testing.assert_array_equal(lik.log_lik, ref.log_lik)
    np.testing.assert_array_equal(raim.mixture_weights(lik, z, log_sigma, 2), ref.gamma[2])
    lik = robust.log_likelihood(z, log_sigma, prior)
    ref = gnss.robust_log_likelihood(z, log_sigma, 0.2, 300.0)
    np.testing.assert_array_equal(lik.log_lik, ref.log_lik)
    assert lik.gamma is None                     # not computed for every set
    np.testing.assert_allclose(robust.mixture_weights(lik, z, log_sigma, 1), ref.gamma[1],
                               rtol=1e-12)
