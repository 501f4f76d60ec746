"""The filter object: convergence on exact geometry, bad input, parameters."""
from dataclasses import replace

import numpy as np
import pytest
from synthetic import FRAME, epoch_at, sky

from gnsscam_ros.core import gnss
from gnsscam_ros.core.filter import (PROPAGATED, REJECTED, UPDATED, WAITING, FilterConfig,
                                     ParticleFilter)
from gnsscam_ros.core.particles import MotionIncrement
from gnsscam_ros.core.verdict import STALE, integrity_verdict

SECOND = 1_000_000_000


def config(**kw):
    # Errors correlated over 2.5 s: 0.2 of an independent epoch per 1 s epoch, so that a
    # few noise-free epochs acquire the heading (the default 10 s takes four times longer).
    base = dict(n_particles=400, acquisition_particles=800, heading_acquisition_m=20.0,
                init_position_sd_m=10.0, init_vertical_sd_m=10.0,
                error_correlation_time_s=2.5)
    base.update(kw)
    return FilterConfig(**base)


def drive_east(filt, n_epochs, speed=8.0, start=0, sv=None, clock=5000.0):
    """Feed exact epochs of a vehicle driving east at ``speed`` m/s."""
    results = []
    for i in range(start, start + n_epochs):
        pos = np.array([speed * i, 0.0, 0.0])
        epoch = epoch_at(pos, clock_m=clock + 3.0 * i, sv_ecef=sv, stamp_ns=i * SECOND)
        motion = None if i == start else MotionIncrement(1.0, speed, 0.0, 0.01, 1e-6)
        results.append(filt.step(epoch, motion))
    return results


@pytest.mark.slow
@pytest.mark.parametrize('likelihood', ['robust', 'particle_raim'])
def test_converges_on_exact_geometry(likelihood):
    filt = ParticleFilter(config(likelihood=likelihood, error_correlation_time_s=0.0),
                          frame=FRAME, rng=np.random.default_rng(1))
    results = drive_east(filt, 40)
    assert all(r.status == UPDATED for r in results)
    errors = [np.linalg.norm(r.position_enu_m[:2] - [8.0 * i, 0.0])
              for i, r in enumerate(results)]
    assert np.mean(errors[-10:]) < 2.0
    heading_error = np.angle(np.exp(1j * results[-1].yaw_rad))
    assert abs(heading_error) < np.radians(10)


def _spread_growth_m2(travelled_m: float, dt_s: float) -> float:
    """Variance of the east displacement of the particles over one GNSS-less step [m^2]."""
    cfg = config(motion_perturbation_scale=0.0)
    filt = ParticleFilter(cfg, frame=FRAME, rng=np.random.default_rng(9))
    drive_east(filt, 5, speed=0.0)
    before = filt.particles[:, 0].copy()
    blind = epoch_at([0.0, 0.0, 0.0], stamp_ns=int((4 + dt_s) * SECOND))
    blind = replace(blind, pr_m=np.full_like(blind.pr_m, np.nan))
    # Driving north: the east spread grows by the process noise only.
    heading_north = MotionIncrement(dt_s, travelled_m, 0.0, 1e-12, 1e-12)
    filt.particles[:, 3] = np.pi / 2
    assert filt.step(blind, heading_north).status == PROPAGATED
    # A step without GNSS keeps the particles in order: each one's own displacement.
    return float(np.var(filt.particles[:, 0] - before))


def test_process_noise_grows_with_the_distance_driven_not_with_time_at_rest():
    cfg = config()                       # the process noise of the runs below
    at_rest = _spread_growth_m2(0.0, 30.0)
    moving = _spread_growth_m2(150.0, 30.0)
    # Measured against the parameters (sampling error of 800 particles: ~5 %).
    assert at_rest == pytest.approx(cfg.propagation_var_m2 * 30.0, rel=0.15)
    assert moving == pytest.approx(cfg.propagation_var_m2 * 30.0
                                   + cfg.propagation_var_m2_per_m * 150.0, rel=0.15)
    assert moving > 10.0 * at_rest


def test_time_going_backwards_is_rejected_and_state_kept():
    filt = ParticleFilter(config(), frame=FRAME, rng=np.random.default_rng(2))
    drive_east(filt, 5)
    before = filt.particles.copy()
    late = epoch_at([0.0, 0.0, 0.0], stamp_ns=2 * SECOND)
    result = filt.step(late, MotionIncrement(1.0, 8.0, 0.0, 0.01, 1e-6))
    assert result.status == REJECTED and 'backwards' in result.reason
    np.testing.assert_array_equal(filt.particles, before)
    assert filt.last_stamp_ns == 4 * SECOND


def test_unusable_epoch_propagates_without_integrity():
    filt = ParticleFilter(config(), frame=FRAME, rng=np.random.default_rng(3))
    drive_east(filt, 5)
    epoch = epoch_at([40.0, 0.0, 0.0], stamp_ns=5 * SECOND)
    pr = epoch.pr_m.copy()
    pr[:5] = np.nan                                  # 3 finite satellites left
    result = filt.step(replace(epoch, pr_m=pr), MotionIncrement(1.0, 8.0, 0.0, 0.01, 1e-6))
    assert result.status == PROPAGATED
    assert result.risk is None
    assert integrity_verdict(result, filt.config).level == STALE
    assert result.rejected == {'non_finite': 5}
    assert abs(result.position_enu_m[0] - 40.0) < 5.0       # still dead reckoning
    # The next good epoch is used again.
    nxt = filt.step(epoch_at([48.0, 0.0, 0.0], stamp_ns=6 * SECOND),
                    MotionIncrement(1.0, 8.0, 0.0, 0.01, 1e-6))
    assert nxt.status == UPDATED


def test_duplicates_and_infinities_do_not_crash():
    filt = ParticleFilter(config(), frame=FRAME, rng=np.random.default_rng(4))
    drive_east(filt, 3)
    epoch = epoch_at([24.0, 0.0, 0.0], sv_ecef=sky(10), stamp_ns=3 * SECOND)
    sv_id = epoch.sv_id.copy()
    sv_id[1] = sv_id[0]
    sv = epoch.sv_pos_ecef_m.copy()
    sv[2] = np.inf
    result = filt.step(replace(epoch, sv_id=sv_id, sv_pos_ecef_m=sv), None)
    assert result.status == UPDATED and result.n_satellites == 7
    assert result.rejected == {'non_finite': 1, 'duplicate': 2}
    assert np.all(np.isfinite(result.position_enu_m))


def test_waits_for_a_usable_first_epoch():
    filt = ParticleFilter(config(), frame=FRAME, rng=np.random.default_rng(5))
    epoch = epoch_at([0.0, 0.0, 0.0], sv_ecef=sky(3))
    result = filt.step(epoch, None)
    assert result.status == WAITING and not filt.initialised


def test_map_origin_far_from_the_first_fix_is_refused_with_the_reason():
    from gnsscam_ros.core.frames import LocalFrame
    # An origin left at (0, 0, 0) is thousands of km from the vehicle: the filter would move
    # particles in a tilted plane. It waits and says why instead.
    filt = ParticleFilter(config(), frame=LocalFrame(0.0, 0.0, 0.0),
                          rng=np.random.default_rng(4))
    result = filt.step(epoch_at([0.0, 0.0, 0.0], stamp_ns=0), None)
    assert result.status == WAITING and 'check map_origin_llh' in result.reason
    assert filt.particles is None
    # 50 km away is still a frame.
    near = LocalFrame(*FRAME.enu_to_geodetic(np.array([30e3, 40e3, 0.0])))
    filt = ParticleFilter(config(), frame=near, rng=np.random.default_rng(4))
    assert filt.step(epoch_at([0.0, 0.0, 0.0], stamp_ns=0), None).status == UPDATED


def test_integrity_flag_follows_target_and_alert_limit():
    filt = ParticleFilter(config(inverse_bernoulli='approx', integrity_settling_s=5.0),
                          frame=FRAME, rng=np.random.default_rng(6))
    result = drive_east(filt, 20)[-1]
    bound = result.risk.risk_bound[0]
    verdict = integrity_verdict(result, filt.config)
    # OK exactly when the protection level is within the alert limit (once settled, with
    # the motion known), which implies the bound at the alert limit meets the target.
    assert verdict.valid
    assert verdict.ok == (result.protection_level_m <= filt.config.alert_limit_m)
    assert not verdict.ok or bound <= filt.config.target_risk
    filt.set_parameters(alert_limit_m=0.5)          # a limit inside the cloud
    after = drive_east(filt, 1, start=20)[0]
    assert after.risk.alert_limits_m[0] == 0.5
    assert after.risk.empirical_risk[0] > 0.5
    assert not integrity_verdict(after, filt.config).ok


def test_invalid_configuration_is_refused_with_reasons():
    with pytest.raises(ValueError, match='target_risk'):
        FilterConfig(target_risk=1.5)
    filt = ParticleFilter(config(), frame=FRAME)
    with pytest.raises(ValueError, match='likelihood'):
        filt.set_parameters(likelihood='magic')
    assert filt.config.likelihood == 'robust'


def test_likelihood_parameters_changed_between_epochs_take_effect():
    filt = ParticleFilter(config(), frame=FRAME, rng=np.random.default_rng(7))
    drive_east(filt, 3)
    filt.set_parameters(likelihood='particle_raim', dirichlet_alpha=1.5)
    assert filt.likelihood == gnss.ParticleRaimLikelihood(1.5)
    filt.set_parameters(likelihood='robust', outlier_prob=0.1)
    assert filt.likelihood == gnss.RobustLikelihood(0.1, 300.0)
    assert drive_east(filt, 2, start=3)[-1].status == UPDATED


def test_same_seed_same_result():
    out = []
    for _ in range(2):
        filt = ParticleFilter(config(), frame=FRAME, rng=np.random.default_rng(7))
        out.append(drive_east(filt, 8)[-1].position_enu_m)
    np.testing.assert_array_equal(out[0], out[1])


def test_a_static_receiver_settles_without_a_heading_and_must_acquire_one_to_move():
    cfg = config(integrity_settling_s=5.0, heading_acquisition_m=40.0)
    filt = ParticleFilter(cfg, frame=FRAME, rng=np.random.default_rng(3))
    still = MotionIncrement(1.0, 0.0, 0.0, 1e-6, 1e-8)
    results = [filt.step(epoch_at([0.0, 0.0, 0.0], clock_m=5000.0, stamp_ns=i * SECOND),
                         None if i == 0 else still) for i in range(8)]
    # Seen not to move (from the second epoch): the heading does not matter; integrity
    # settles 5 s later.
    assert [integrity_verdict(r, cfg).valid for r in results] == [False] * 6 + [True] * 2
    # It moves: the heading it never needed is unknown, so acquisition and settling again.
    moving = [filt.step(epoch_at([8.0 * k, 0.0, 0.0], clock_m=5000.0,
                                 stamp_ns=(8 + k) * SECOND),
                        MotionIncrement(1.0, 8.0, 0.0, 0.01, 1e-6)) for k in range(1, 8)]
    verdicts = [integrity_verdict(r, cfg) for r in moving]
    assert not any(v.valid for v in verdicts)
    assert all('settling' in v.message for v in verdicts)
