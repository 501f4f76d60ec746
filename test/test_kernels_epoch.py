"""One filter epoch through the compiled kernels against the same epoch through the numpy
oracles (test/oracles.py), from the same state and the same random stream.

The propagated sets are bit-identical; the joint log-weights agree to 1e-4 nats (the
filter's robust likelihood runs in float32 on relative coordinates; test_kernels_gnss
holds its float64 path to 1e-6), so the choice of motion sample is the same and the
estimate agrees to 1e-4 m (covariance to a relative 1e-5). The risk bound and protection
level of the epoch are held to the oracles on the posteriors the filter kept
(test_kernels_posterior).
"""
import copy
from dataclasses import replace

import numpy as np
import oracles
import pytest
from synthetic import FRAME, epoch_at, sky

from gnsscam_ros.core import gnss
from gnsscam_ros.core.filter import UPDATED, FilterConfig, ParticleFilter
from gnsscam_ros.core.fusion import CameraMeasurement
from gnsscam_ros.core.particles import MotionIncrement, motion_samples
from gnsscam_ros.core.persistence import persisting_worth, tempering_exponent
from gnsscam_ros.core.types import GLONASS, GPS

S_NS = 1_000_000_000
SYSTEMS = np.array([GPS] * 6 + [GLONASS] * 4)


def drive_epoch(k: int, rng) -> tuple:
    """Epoch k of a vehicle driving east at 8 m/s, pseudoranges with 3 m noise and one
    NLOS-like fault; the motion since epoch k - 1."""
    truth = np.array([8.0 * k, 2.0, 0.0])
    epoch = epoch_at(truth, clock_m=[500.0, 540.0], sv_ecef=sky(10, seed=5),
                     stamp_ns=k * S_NS, system=SYSTEMS)
    pr = epoch.pr_m + rng.normal(scale=3.0, size=10)
    pr[3] += 40.0
    motion = MotionIncrement(dt_s=1.0, distance_m=8.0, dyaw_rad=0.0, distance_var_m2=0.01,
                             dyaw_var_rad2=1e-5)
    return replace(epoch, pr_m=pr), motion, truth


def oracle_choice(filt: ParticleFilter, epoch, motion, camera):
    """The motion samples, their joint log-weights and totals, by the numpy oracles, from
    ``filt``'s state and random streams (``filt`` is a copy: its generators advance)."""
    cfg = filt.config
    distance, dyaw = motion_samples(motion, cfg.motion_sample_count,
                                    cfg.motion_perturbation_scale, filt.rng)
    pos_var = cfg.motion.position_process_var_m2(motion.dt_s, motion.distance_m)
    priors = oracles.propagate(filt.particles, distance, dyaw, motion.dup_m, pos_var,
                               cfg.yaw_propagation_var_rad2 * motion.dt_s,
                               filt.noise.take((distance.shape[0], filt.particles.shape[0],
                                                4)))
    centre, cov = oracles.weighted_mean_cov(priors[0, :, :3], filt.log_w)
    check = gnss.check_epoch(epoch)
    prep = gnss.prepare_epoch(epoch.subset(check.keep), filt.frame, centre,
                              cfg.measurement_var_m2, cfg.use_reported_variance,
                              filt.errors if cfg.error_model == 'adaptive' else None)
    residual = prep.pr_m - oracles.ranges(centre[None], prep.sv_enu_m)[0]
    spread = min(float(np.sqrt(np.trace(cov))), cfg.clock_kernel_max_m)
    clock_w = oracles.clock_inlier_weights(residual, prep.sigma_m, prep.sys_index,
                                           prep.n_systems, spread)
    m, n = priors.shape[:2]
    e = oracles.clock_corrected_residuals(priors[..., :3].reshape(-1, 3), prep,
                                          clock_w).reshape(m, n, -1)
    if prep.wide_share is None:
        log_lik = oracles.robust_log_likelihood(e / prep.sigma_m, np.log(prep.sigma_m),
                                                cfg.outlier_prob, cfg.outlier_range_m).log_lik
    else:
        log_lik = oracles.mixture_log_likelihood(e, prep.sigma_m, prep.wide_share,
                                                 prep.wide_mean_m, prep.wide_sd_m,
                                                 gnss.FAULT_SHARE, cfg.outlier_range_m)
    tempering = tempering_exponent(filt.persistence.persistent_share,
                                   persisting_worth(motion.dt_s, cfg.error_correlation_time_s))
    joint = filt.log_w + tempering * log_lik
    if camera:
        total = np.log(np.exp(joint).sum(axis=1))
        matches = np.array([c.position_enu_m for c in camera])
        log_q = oracles.camera_log_q(priors[..., :3], matches, cfg.camera_temperature_m,
                                     cfg.camera_gate_m)
        joint = joint + oracles.fuse_camera(joint - total[:, None], log_q,
                                            cfg.camera_kl_threshold_nats,
                                            cfg.camera_elsewhere_prob).log_q_mix
    top = joint.max(axis=1, keepdims=True)
    total = top[:, 0] + np.log(np.exp(joint - top).sum(axis=1))
    return priors, joint - total[:, None], total


@pytest.mark.parametrize('error_model', ['adaptive', 'stated'])
@pytest.mark.parametrize('with_camera', [False, True])
def test_an_epoch_through_the_kernels_is_the_epoch_through_the_oracles(
        with_camera, error_model):
    rng = np.random.default_rng(2)
    config = FilterConfig(n_particles=400, acquisition_particles=0, n_posteriors=12,
                          n_motion_samples=6, heading_acquisition_m=16.0,
                          error_model=error_model)
    filt = ParticleFilter(config, frame=FRAME, rng=np.random.default_rng(7))
    for k in range(6):
        epoch, motion, _ = drive_epoch(k, rng)
        assert filt.step(epoch, motion if k else None).status == UPDATED
    epoch, motion, truth = drive_epoch(6, rng)
    camera = ([CameraMeasurement(6 * S_NS - 100_000_000 * j,
                                 truth + rng.normal(scale=2.0, size=3), 1.0, j)
               for j in range(3)] if with_camera else None)
    reference = copy.deepcopy(filt)
    result = filt.step(epoch, motion, camera)
    priors, post_log_w, total = oracle_choice(reference, epoch, motion, camera)

    # To rounding: numpy 1.24's float64 sin/cos (the oracle's) are not libm's (the kernel's)
    # to the last bit (test_kernels_gnss.test_propagation_is_the_oracle_to_rounding).
    np.testing.assert_allclose(filt.sample_particles, priors, rtol=0, atol=1e-12)
    np.testing.assert_allclose(result.total_log_lik, total, atol=1e-4)
    assert result.chosen_sample == int(np.argmax(total))
    np.testing.assert_allclose(filt.sample_log_w, post_log_w, atol=1e-4)
    mean, cov = oracles.weighted_mean_cov(priors[result.chosen_sample, :, :3],
                                          post_log_w[result.chosen_sample])
    np.testing.assert_allclose(result.position_enu_m, mean, atol=1e-4)
    np.testing.assert_allclose(result.covariance_m2, cov, rtol=1e-5, atol=1e-6)
    if with_camera:
        assert result.camera_alpha is not None and not result.camera_excluded
