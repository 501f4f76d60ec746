"""The particle filter: one object runs a GNSS epoch end to end.

propagate (S motion samples) -> GNSS likelihood (and camera) -> choose the sample with the
highest total log-likelihood -> risk bound and protection level over M posteriors ->
resample.

S motion samples are drawn around the measured odometry, each moving the previous particle
set (paper §2, §7); the estimate is the one with the highest total log-likelihood. The M
posteriors of the risk bound (paper §6) are those samples, each displaced by a bias
hypothesis (``core.bias``: what slowly varying pseudorange biases do to the estimate);
posterior j uses sample ``j mod S``. With ``bias_model = 'none'`` S = M and the posteriors
are the motion samples alone, as in the paper.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.special import logsumexp

from . import gnss, integrity
from .bias import BiasHypotheses, BiasModel
from .fusion import CameraMeasurement, camera_log_q, fuse_camera
from .frames import LocalFrame
from .particles import (POS, YAW, MotionIncrement, effective_sample_size, motion_samples,
                        normalize_log_weights, propagate, systematic_resample,
                        weighted_mean_cov)
from .snapshot import solve_snapshot
from .types import GnssEpoch

PARTICLE_RAIM = 'particle_raim'
ROBUST = 'robust'
LIKELIHOODS = (PARTICLE_RAIM, ROBUST)

# Bias models of the posteriors behind the risk bound (core.bias).
BIAS_CN0 = 'cn0'         # Gauss-Markov bias per satellite, size from C/N0 (default)
BIAS_NONE = 'none'       # motion perturbations only (the paper's construction)
BIAS_MODELS = (BIAS_CN0, BIAS_NONE)

# Epoch outcomes.
UPDATED = 'updated'            # GNSS update applied; integrity computed
PROPAGATED = 'propagated'      # epoch unusable: motion only, integrity not available
REJECTED = 'rejected'          # epoch refused (time going backwards): state unchanged
WAITING = 'waiting'            # no initial fix yet
#: Farthest a given map frame origin may be from the first fix [m]. The filter moves
#: particles in the frame's east-north plane and treats its up axis as vertical; 100 km
#: away they are ~1 degree off the local ones, 6,000 km away (an origin left at 0, 0)
#: meaningless, so such an origin is a configuration error, not a frame.
MAX_ORIGIN_DISTANCE_M = 100_000.0
#: Heading uncertainty accrued over a dead-reckoning gap beyond which the heading counts
#: as lost and is acquired again (distance ``heading_acquisition_m``) [rad].
HEADING_LOST_RAD = 0.5


@dataclass(frozen=True)
class FilterConfig:
    """Filter parameters (the node parameters of ``config/fusion.yaml`` map onto these).

    Attributes:
        n_particles: Particles per posterior N.
        n_posteriors: Posteriors M behind the risk bound and the protection level. With
            the exact inverse Bernoulli the bound can never fall below
            ``1 - exp(-log((M + 1) / delta) / M)``: 0.375 for M = 10, 0.037 for M = 200
            (delta = 0.1). Bias hypotheses make extra posteriors cheap (no likelihood).
        n_motion_samples: Motion samples drawn around the odometry and weighed by the
            measurements (the estimate is the best of them); posterior j uses sample
            ``j mod n_motion_samples`` and its own bias hypothesis. With
            ``bias_model = 'none'`` every posterior has its own sample (this is ignored).
        measurement_var_m2: Pseudorange variance [m^2] (paper Table 1: 10).
        use_reported_variance: Use max(measurement_var_m2, the receiver's variance).
        propagation_var_m2: Horizontal position process noise per axis per second [m^2/s]
            (paper Table 1 uses 3 m^2; with odometry this good, 0.3 measured better on
            smartLoc, see README).
        vertical_propagation_var_m2: Height process noise per second [m^2/s]; a road
            vehicle's height changes slowly and GNSS observes it poorly.
        yaw_propagation_var_rad2: Heading process noise per second [rad^2/s].
        motion_perturbation_scale: Inflation of the odometry noise for the M samples.
        likelihood: 'particle_raim' (paper's mixture) or 'robust' (Gaussian + outlier floor).
        error_correlation_time_s: GNSS errors closer in time than this are not independent
            evidence: each epoch's log-likelihood is tempered by min(1, dt / this); 0 = off.
        clock_kernel_max_m: Cap on how much the prior's spread widens the clock's inlier
            kernel [m]. NLOS errors are positive; a kernel wide enough to take them in biases
            the clock, and through it the height, by tens of metres.
        heading_acquisition_m: The heading is unknown at start and observable only once the
            vehicle has moved well beyond the GNSS errors. Until it has travelled this far
            the set holds ``acquisition_particles`` particles (when that is more than
            ``n_particles``), so that the 4D (position, height, heading) search is covered
            densely and does not lock onto a wrong heading by sampling luck.
        acquisition_particles: Set size during heading acquisition; 0 or fewer than
            ``n_particles``: no enlargement. An absolute count, not a multiple of N: how
            many particles cover the search (the initial spread times the heading circle)
            depends on that volume, not on the working size, so a large N gains nothing
            from an enlargement and would pay ten times its epoch cost for the first 100 m.
        dirichlet_alpha: Dirichlet prior concentration in the EM pooling.
        outlier_prob: Outlier probability of the robust likelihood.
        outlier_range_m: Width of the robust likelihood's uniform outlier density [m].
        resample_ess_fraction: Resample when ESS < this * N.
        init_position_sd_m: Horizontal spread of the initial set around the first fix [m].
        init_vertical_sd_m: Vertical spread of the initial set [m]; snapshot heights in a
            street canyon are tens of metres off, so this is wider than the horizontal one.
        min_satellites: Fewest satellites for an update.
        elevation_mask_deg: Satellites below are dropped [deg].
        cn0_mask_dbhz: Satellites below are dropped [dB-Hz].
        alert_limit_m: Alert limit of the integrity flag [m].
        target_risk: Integrity is insufficient when the risk bound exceeds this.
        risk_delta: Confidence parameter delta of the bound.
        inverse_bernoulli: 'exact' (bisection) or 'approx' (the paper's closed form, which
            collapses to 0 when no posterior mass is hazardous: reproduction only).
        bias_model: 'cn0' (each posterior carries a Gauss-Markov pseudorange bias per
            satellite, its size from C/N0, propagated into the estimate; core.bias) or
            'none' (posteriors differ by motion perturbations only, as in the paper).
        bias_floor_m: Smallest bias standard deviation at high C/N0 [m].
        bias_residual_scale: Bias standard deviation at high C/N0 per metre of smoothed
            residual RMS at the estimate (calibrated on smartLoc, see README).
        bias_cn0_knee_dbhz: Below this C/N0 the bias grows 10 dB per decade [dB-Hz].
        bias_correlation_time_s: Correlation time of the biases [s] (smartLoc: ~50 s).
        max_speed_mps: Fastest the vehicle may move while its motion is unknown (dead
            reckoning lost or reset) [m/s]: the set spreads by this speed times the gap.
        max_yaw_rate_rps: Fastest heading change while the motion is unknown [rad/s].
        integrity_settling_s: Integrity is not certified before the heading is acquired
            (at the start, and again after a dead-reckoning gap long enough to lose it)
            and this long after [s]: the set starts on a snapshot fix, which carries the
            biases' whole effect, while the bias hypotheses start from none and need the
            filter's own memory to grow into it (measured: the level fell below the error
            at the end of acquisition on the emulated drive).
        horizontal_risk: Alert limits on horizontal error (True) or 3D error.
        extra_alert_limits_m: Further alert limits whose risk is computed (evaluation).
        use_camera: Fuse camera matches when they are given (False = Particle RAIM only).
        camera_temperature_m: Softmax temperature of the camera distribution [m].
        camera_gate_m: Beyond this distance from a match a particle is no more likely
            under the camera than the rest of the map (the "elsewhere" cell) [m].
        camera_elsewhere_prob: GNSS probability that the vehicle is outside the cloud.
        camera_kl_threshold_nats: The camera is excluded for an epoch when every image's
            KL(Q_j || P) against the GNSS distribution exceeds this [nats]; with every
            match beyond the gate KL -> log(1 / camera_elsewhere_prob) = 6.9.
    """

    n_particles: int = 1000
    n_posteriors: int = 200
    n_motion_samples: int = 10
    measurement_var_m2: float = 10.0
    use_reported_variance: bool = True
    propagation_var_m2: float = 0.3
    vertical_propagation_var_m2: float = 0.3
    yaw_propagation_var_rad2: float = 3e-4
    motion_perturbation_scale: float = 3.0
    likelihood: str = ROBUST
    error_correlation_time_s: float = 5.0
    clock_kernel_max_m: float = 3.0
    heading_acquisition_m: float = 100.0
    acquisition_particles: int = 10_000
    dirichlet_alpha: float = 1.01
    outlier_prob: float = 0.3
    outlier_range_m: float = 300.0
    resample_ess_fraction: float = 0.5
    init_position_sd_m: float = 30.0
    init_vertical_sd_m: float = 60.0
    min_satellites: int = 4
    elevation_mask_deg: float = 0.0
    cn0_mask_dbhz: float = 0.0
    alert_limit_m: float = 8.0
    target_risk: float = 0.1
    risk_delta: float = 0.1
    inverse_bernoulli: str = integrity.EXACT
    bias_model: str = BIAS_CN0
    bias_floor_m: float = 2.0
    bias_residual_scale: float = 0.23
    bias_cn0_knee_dbhz: float = 41.6
    bias_correlation_time_s: float = 50.0
    max_speed_mps: float = 40.0
    max_yaw_rate_rps: float = 1.0
    integrity_settling_s: float = 30.0
    horizontal_risk: bool = True
    extra_alert_limits_m: tuple = ()
    use_camera: bool = True
    camera_temperature_m: float = 5.0
    camera_gate_m: float = 20.0
    camera_elsewhere_prob: float = 1e-3
    camera_kl_threshold_nats: float = 5.0

    def __post_init__(self):
        problems = []
        if self.n_particles < 2:
            problems.append('n_particles must be >= 2')
        if self.acquisition_particles < 0:
            problems.append('acquisition_particles must be >= 0')
        if self.n_posteriors < 1:
            problems.append('n_posteriors must be >= 1')
        if self.n_motion_samples < 1:
            problems.append('n_motion_samples must be >= 1')
        if self.bias_model not in BIAS_MODELS:
            problems.append(f'bias_model must be one of {BIAS_MODELS}')
        for name in ('measurement_var_m2', 'alert_limit_m', 'camera_temperature_m',
                     'camera_kl_threshold_nats', 'camera_gate_m'):
            if not getattr(self, name) > 0.0:
                problems.append(f'{name} must be > 0')
        for name in ('propagation_var_m2', 'vertical_propagation_var_m2',
                     'yaw_propagation_var_rad2',
                     'motion_perturbation_scale', 'error_correlation_time_s',
                     'heading_acquisition_m', 'bias_floor_m', 'bias_residual_scale',
                     'bias_correlation_time_s',
                     'max_speed_mps', 'max_yaw_rate_rps', 'integrity_settling_s'):
            if not getattr(self, name) >= 0.0:
                problems.append(f'{name} must be >= 0')
        if self.likelihood not in LIKELIHOODS:
            problems.append(f'likelihood must be one of {LIKELIHOODS}')
        if self.inverse_bernoulli not in integrity.INVERSE_METHODS:
            problems.append(f'inverse_bernoulli must be one of {integrity.INVERSE_METHODS}')
        if not 0.0 < self.target_risk < 1.0:
            problems.append('target_risk must be in (0, 1)')
        if not 0.0 < self.risk_delta <= 1.0:
            problems.append('risk_delta must be in (0, 1]')
        if not 0.0 <= self.resample_ess_fraction <= 1.0:
            problems.append('resample_ess_fraction must be in [0, 1]')
        if not self.dirichlet_alpha >= 1.0:
            problems.append('dirichlet_alpha must be >= 1')
        if not 0.0 < self.camera_elsewhere_prob < 1.0:
            problems.append('camera_elsewhere_prob must be in (0, 1)')
        if not 0.0 < self.outlier_prob < 1.0:
            problems.append('outlier_prob must be in (0, 1)')
        if self.min_satellites < 4:
            problems.append('min_satellites must be >= 4 (position and clock)')
        if problems:
            raise ValueError('invalid filter configuration: ' + '; '.join(problems))

    @property
    def alert_limits_m(self) -> np.ndarray:
        """The flag's alert limit first, then the extra ones."""
        extra = [a for a in self.extra_alert_limits_m if a != self.alert_limit_m]
        return np.array([self.alert_limit_m, *extra], dtype=float)

    @property
    def motion_sample_count(self) -> int:
        """Motion samples weighed per epoch (every posterior's own without bias model)."""
        if self.bias_model == BIAS_NONE:
            return self.n_posteriors
        return min(self.n_motion_samples, self.n_posteriors)

    @property
    def bias(self) -> BiasModel:
        return BiasModel(floor_m=self.bias_floor_m, residual_scale=self.bias_residual_scale,
                         cn0_knee_dbhz=self.bias_cn0_knee_dbhz,
                         correlation_time_s=self.bias_correlation_time_s)


@dataclass
class EpochResult:
    """What one GNSS epoch produced.

    Attributes:
        stamp_ns: Epoch time [ns].
        status: 'updated', 'propagated', 'rejected' or 'waiting'.
        reason: Why the epoch was not used for an update ('' when it was).
        position_enu_m: (3,) estimate in the map frame [m] (None while waiting).
        covariance_m2: (3, 3) covariance of the chosen posterior [m^2].
        yaw_rad: Heading estimate [rad].
        chosen: Index of the chosen posterior.
        total_log_lik: (M,) total log-likelihood of each posterior.
        risk: Risk bound for ``config.alert_limits_m`` (None when not updated).
        protection_level_m: Horizontal (or 3D, see ``horizontal_risk``) protection level:
            the smallest radius around the estimate whose risk bound is at most the target
            [m]; inf when none is, None when not updated.
        integrity_ok: The solution is an update, the filter has settled
            (``integrity_settling_s``), the motion over the interval is known and the
            protection level is within the alert limit (False when unknown).
        integrity_reason: Why integrity is not OK ('' when it is).
        integrity_valid: Everything but the protection level allows OK (settled, motion
            known): the flag at any alert limit L is ``integrity_valid and PL <= L``.
        motion_unknown_s: Part of the interval without dead reckoning [s].
        n_satellites: Satellites used in the update.
        rejected: ``{reason: count}`` of satellites dropped by the checks.
        gamma: (k,) mixture weights of the chosen posterior.
        ess: Effective sample size of the chosen posterior before resampling.
        resampled: Whether the chosen posterior was resampled.
        camera_frame_ids: Frame ids of the camera measurements offered this epoch.
        camera_alpha: (K,) mixture weights alpha*_j of the chosen posterior.
        camera_kl_nats: (K,) KL(Q_j || P) of the chosen posterior.
        camera_excluded: The camera disagreed with GNSS and was left out this epoch.
    """

    stamp_ns: int
    status: str
    reason: str = ''
    position_enu_m: np.ndarray | None = None
    covariance_m2: np.ndarray | None = None
    yaw_rad: float = float('nan')
    chosen: int = -1
    total_log_lik: np.ndarray | None = None
    risk: integrity.RiskBound | None = None
    protection_level_m: float | None = None
    integrity_ok: bool = False
    integrity_reason: str = ''
    integrity_valid: bool = False
    motion_unknown_s: float = 0.0
    n_satellites: int = 0
    rejected: dict = field(default_factory=dict)
    gamma: np.ndarray | None = None
    ess: float = float('nan')
    resampled: bool = False
    camera_frame_ids: tuple = ()
    camera_alpha: np.ndarray | None = None
    camera_kl_nats: np.ndarray | None = None
    camera_excluded: bool = False


class ParticleFilter:
    """Particle RAIM filter over (east, north, up, yaw) with integrity risk.

    Args:
        config: Parameters.
        frame: The map frame; None anchors it at the first robust fix.
        rng: Random generator (explicit, for reproducible runs).
    """

    def __init__(self, config: FilterConfig, frame: LocalFrame | None = None,
                 rng: np.random.Generator | None = None):
        self.config = config
        self.frame = frame
        self.rng = rng if rng is not None else np.random.default_rng()
        self.particles: np.ndarray | None = None        # (N, 4) chosen set
        self.log_w: np.ndarray | None = None            # (N,)
        self.posteriors: np.ndarray | None = None       # (S, N, 4) motion samples, last epoch
        self.posterior_log_w: np.ndarray | None = None  # (S, N)
        # The M posteriors of the last update as the risk bound saw them.
        self.posterior_set: integrity.PosteriorSet | None = None
        self.bias = BiasHypotheses(config.bias, config.n_posteriors, self.rng)
        self.last_stamp_ns: int | None = None
        self.distance_since_init_m = 0.0
        self.acquired_stamp_ns: int | None = None      # end of heading acquisition
        self._motion_unknown_s = 0.0                    # of the epoch being processed
        self.last_result: EpochResult | None = None

    @property
    def initialised(self) -> bool:
        return self.particles is not None

    def set_parameters(self, **changes) -> None:
        """Change parameters between epochs (validated; the old ones stay on error)."""
        new = replace(self.config, **changes)
        if (new.bias != self.config.bias or new.n_posteriors != self.config.n_posteriors):
            self.bias = BiasHypotheses(new.bias, new.n_posteriors, self.rng)
        if new.n_particles != self.config.n_particles and self.initialised:
            idx = systematic_resample(self.log_w, self.rng)
            idx = self.rng.choice(idx, size=new.n_particles, replace=True)
            self.particles = self.particles[idx]
            self.log_w = np.full(new.n_particles, -np.log(new.n_particles))
        self.config = new

    # ------------------------------------------------------------------ epochs
    def step(self, epoch: GnssEpoch, motion: MotionIncrement | None,
             camera: list[CameraMeasurement] | None = None) -> EpochResult:
        """Process one GNSS epoch.

        Args:
            epoch: The pseudoranges of the epoch.
            motion: Motion since the previous epoch; None: no dead reckoning at all, the
                motion is unknown (see ``MotionIncrement.unknown_s``).
            camera: Camera matches of the images since the previous epoch, moved to this
                epoch (``fusion.match_at_epoch``); None or empty for GNSS only.

        Returns:
            The epoch's result; bad input never raises, it is reported in the result.
        """
        cfg = self.config
        if self.last_stamp_ns is not None and epoch.stamp_ns <= self.last_stamp_ns:
            return EpochResult(stamp_ns=epoch.stamp_ns, status=REJECTED,
                               reason=f'time went backwards or repeated: {epoch.stamp_ns} '
                                      f'<= {self.last_stamp_ns} ns')
        check = gnss.check_epoch(epoch, cfg.min_satellites, cfg.elevation_mask_deg,
                                 cfg.cn0_mask_dbhz)
        if not self.initialised:
            return self._initialise(epoch, check)
        dt_s = (epoch.stamp_ns - self.last_stamp_ns) * 1e-9
        if motion is None:
            motion = MotionIncrement.unknown(dt_s)
        distance, dyaw = motion_samples(motion, cfg.motion_sample_count,
                                        cfg.motion_perturbation_scale, self.rng)
        # Over a gap in the dead reckoning the vehicle may be anywhere its maximum speed
        # takes it: one standard deviation per axis is that distance (and likewise for the
        # heading), so the protection level grows with the gap.
        gap_m2 = (cfg.max_speed_mps * motion.unknown_s) ** 2
        priors = propagate(self.particles, distance, dyaw, motion.dup_m,
                           np.array([cfg.propagation_var_m2, cfg.propagation_var_m2,
                                     cfg.vertical_propagation_var_m2]) * dt_s
                           + np.array([gap_m2, gap_m2, 0.0]),
                           cfg.yaw_propagation_var_rad2 * dt_s
                           + (cfg.max_yaw_rate_rps * motion.unknown_s) ** 2, self.rng)
        self._motion_unknown_s = float(motion.unknown_s)
        if motion.unknown_s * cfg.max_yaw_rate_rps > HEADING_LOST_RAD:
            # Without dead reckoning the heading drifts by up to max_yaw_rate_rps: beyond
            # HEADING_LOST_RAD it is unknown, is acquired again, and integrity settles
            # again before it is certified. A shorter gap (a late or restarted dead
            # reckoner) costs only its own epoch (ERROR) and the spread it adds.
            self.acquired_stamp_ns = None
            self.distance_since_init_m = 0.0
        self.last_stamp_ns = epoch.stamp_ns
        self.distance_since_init_m += abs(motion.distance_m)
        prep = None
        if check.usable:
            centre, cov = weighted_mean_cov(priors[0, :, POS], self.log_w)
            prep = gnss.prepare_epoch(epoch.subset(check.keep), self.frame, centre,
                                      cfg.measurement_var_m2, cfg.use_reported_variance)
            if prep.pr_m.shape[0] < prep.n_systems + 3:
                prep = None
                check = replace(check, usable=False,
                                reason='too few satellites once single-satellite '
                                       'constellations are set aside')
        if prep is None:
            return self._propagate_only(epoch, check, priors)
        return self._update(epoch, check, priors, prep, centre, cov, dt_s, camera)

    def _initialise(self, epoch: GnssEpoch, check: gnss.GnssCheck) -> EpochResult:
        cfg = self.config
        if not check.usable:
            return EpochResult(stamp_ns=epoch.stamp_ns, status=WAITING, reason=check.reason,
                               rejected=check.rejected)
        try:
            fix = solve_snapshot(epoch.subset(check.keep),
                                 measurement_var_m2=cfg.measurement_var_m2)
        except ValueError as err:
            return EpochResult(stamp_ns=epoch.stamp_ns, status=WAITING, reason=str(err),
                               rejected=check.rejected)
        if not fix.converged:
            return EpochResult(stamp_ns=epoch.stamp_ns, status=WAITING,
                               reason='initial snapshot fix did not converge',
                               rejected=check.rejected)
        if self.frame is None:
            self.frame = LocalFrame.from_ecef(fix.ecef_m)
        distance = float(np.linalg.norm(self.frame.ecef_to_enu(fix.ecef_m)))
        if distance > MAX_ORIGIN_DISTANCE_M:
            return EpochResult(
                stamp_ns=epoch.stamp_ns, status=WAITING, rejected=check.rejected,
                reason=f'the map frame origin (lat, lon, h) = '
                       f'{tuple(round(v, 6) for v in self.frame.origin_llh)} is '
                       f'{distance / 1e3:.0f} km from the first fix (more than '
                       f'{MAX_ORIGIN_DISTANCE_M / 1e3:.0f} km): check map_origin_llh')
        n = max(cfg.n_particles, cfg.acquisition_particles)
        self.particles = np.empty((n, 4))
        sd = np.array([cfg.init_position_sd_m, cfg.init_position_sd_m, cfg.init_vertical_sd_m])
        self.particles[:, POS] = self.frame.ecef_to_enu(fix.ecef_m) + (
            sd * self.rng.standard_normal((n, 3)))
        # Heading is unknown before the vehicle has moved: spread it over the circle and let
        # the GNSS updates pick the particles that move the right way.
        self.particles[:, YAW] = self.rng.uniform(-np.pi, np.pi, n)
        self.log_w = np.full(n, -np.log(n))
        self.last_stamp_ns = epoch.stamp_ns
        # Evaluate the first epoch's measurements on the fresh set.
        priors = np.repeat(self.particles[None], cfg.motion_sample_count, axis=0)
        self._motion_unknown_s = 0.0
        centre, cov = weighted_mean_cov(self.particles[:, POS], self.log_w)
        prep = gnss.prepare_epoch(epoch.subset(check.keep), self.frame, centre,
                                  cfg.measurement_var_m2, cfg.use_reported_variance)
        return self._update(epoch, check, priors, prep, centre, cov, dt_s=0.0)

    def _propagate_only(self, epoch: GnssEpoch, check: gnss.GnssCheck,
                        priors: np.ndarray) -> EpochResult:
        # No usable measurements: keep the measured-motion sample and report no integrity.
        self.particles = priors[0]
        self.posteriors = priors
        self.posterior_log_w = np.broadcast_to(self.log_w, priors.shape[:2]).copy()
        mean, cov = weighted_mean_cov(self.particles[:, POS], self.log_w)
        result = EpochResult(stamp_ns=epoch.stamp_ns, status=PROPAGATED, reason=check.reason,
                             position_enu_m=mean, covariance_m2=cov,
                             yaw_rad=self._circular_mean(self.particles[:, YAW], self.log_w),
                             chosen=0, rejected=check.rejected, integrity_ok=False,
                             integrity_reason=f'no GNSS update: {check.reason}',
                             motion_unknown_s=self._motion_unknown_s)
        self.last_result = result
        return result

    def _update(self, epoch: GnssEpoch, check: gnss.GnssCheck, priors: np.ndarray,
                prep: gnss.PreparedEpoch, centre: np.ndarray, cov: np.ndarray,
                dt_s: float, camera: list[CameraMeasurement] | None = None) -> EpochResult:
        cfg = self.config
        m, n = priors.shape[:2]
        # Receiver clock: robust inlier weights at the prior's centre, then per particle.
        centre_residual = prep.pr_m - gnss.ranges(centre[None], prep.sv_enu_m)[0]
        spread_m = min(float(np.sqrt(max(np.trace(cov), 0.0))), cfg.clock_kernel_max_m)
        clock_w = gnss.clock_inlier_weights(centre_residual, prep.sigma_m, prep.sys_index,
                                            prep.n_systems, spread_m)
        residual = gnss.clock_corrected_residuals(priors[..., POS].reshape(-1, 3), prep,
                                                  clock_w)
        residual /= prep.sigma_m
        z = residual.reshape(m, n, -1)
        log_sigma = np.log(prep.sigma_m)
        if cfg.likelihood == PARTICLE_RAIM:
            lik = gnss.particle_raim_log_likelihood(z, log_sigma, self.log_w,
                                                    cfg.dirichlet_alpha)
        else:
            lik = gnss.robust_log_likelihood(z, log_sigma, cfg.outlier_prob,
                                             cfg.outlier_range_m, inlier_share=False)
        evidence = self._evidence_weight(dt_s)
        log_lik = lik.log_lik * evidence
        joint = self.log_w[None, :] + log_lik
        fusion = None
        if camera and cfg.use_camera:
            # Camera and GNSS distributions share the domain: the particles of each set.
            log_p = joint - logsumexp(joint, axis=1, keepdims=True)
            log_q = camera_log_q(priors[..., POS],
                                 np.array([c.position_enu_m[:3] for c in camera]),
                                 cfg.camera_temperature_m, cfg.camera_gate_m)
            fusion = fuse_camera(log_p, log_q, cfg.camera_kl_threshold_nats,
                                 cfg.camera_elsewhere_prob)
            joint = joint + fusion.log_q_mix
        total = logsumexp(joint, axis=1)
        post_log_w = joint - total[:, None]
        chosen = int(np.argmax(total))
        # The chosen set's inlier probability of each satellite, for the bias hypotheses.
        inlier = gnss.robust_inlier_probability(z[chosen], log_sigma, cfg.outlier_prob,
                                                cfg.outlier_range_m, post_log_w[chosen])
        result = self._finish(epoch, check, priors, post_log_w, chosen, total,
                              (prep, inlier, evidence, clock_w))
        if fusion is not None:
            result.camera_frame_ids = tuple(c.frame_id for c in camera)
            result.camera_alpha = fusion.alpha[:, chosen]
            result.camera_kl_nats = fusion.kl_nats[:, chosen]
            result.camera_excluded = bool(fusion.excluded[chosen])
        if lik.gamma is not None:
            result.gamma = lik.gamma[chosen]
        else:                                 # robust: inlier shares of the chosen set only
            result.gamma = gnss.robust_log_likelihood(
                z[chosen:chosen + 1], log_sigma, cfg.outlier_prob, cfg.outlier_range_m).gamma[0]
        result.n_satellites = int(prep.pr_m.shape[0])
        return result

    def _finish(self, epoch: GnssEpoch, check: gnss.GnssCheck, priors: np.ndarray,
                post_log_w: np.ndarray, chosen: int, total: np.ndarray,
                update: tuple) -> EpochResult:
        """Estimate, integrity risk and resampling, shared by every update path."""
        cfg = self.config
        m, n = post_log_w.shape
        pos = priors[..., POS]
        mean, cov = weighted_mean_cov(pos[chosen], post_log_w[chosen])
        risk, level = self._integrity(pos, post_log_w, chosen, mean, cov, epoch.stamp_ns,
                                      update)
        limit = float(cfg.alert_limits_m[0])
        if (self.acquired_stamp_ns is None and self._motion_unknown_s == 0.0
                and self.distance_since_init_m >= cfg.heading_acquisition_m):
            self.acquired_stamp_ns = epoch.stamp_ns
        settled_s = (-1.0 if self.acquired_stamp_ns is None
                     else (epoch.stamp_ns - self.acquired_stamp_ns) * 1e-9)
        if self._motion_unknown_s > 0.0:
            reason = (f'dead reckoning missing for {self._motion_unknown_s:.2f} s of this '
                      f'interval: motion unknown')
        elif settled_s < cfg.integrity_settling_s:
            reason = ('settling after the first fix or a lost heading (heading '
                      f'acquisition, then {cfg.integrity_settling_s:g} s)')
        elif not level <= limit:
            reason = f'protection level {level:.1f} m above the alert limit {limit:g} m'
        else:
            reason = ''
        ess = float(effective_sample_size(post_log_w[chosen]))
        particles, log_w = priors[chosen], post_log_w[chosen]
        acquired = self.distance_since_init_m >= cfg.heading_acquisition_m
        n_out = cfg.n_particles if acquired else n
        resampled = ess < cfg.resample_ess_fraction * n or n_out != n
        if resampled:
            idx = systematic_resample(log_w, self.rng)
            if n_out != n:   # end of heading acquisition: thin the set to its working size
                idx = idx[np.round(np.linspace(0, n - 1, n_out)).astype(int)]
            particles = particles[idx]
            log_w = np.full(n_out, -np.log(n_out))
        self.particles, self.log_w = particles, normalize_log_weights(log_w)
        self.posteriors, self.posterior_log_w = priors, post_log_w
        result = EpochResult(
            stamp_ns=epoch.stamp_ns, status=UPDATED, position_enu_m=mean, covariance_m2=cov,
            yaw_rad=self._circular_mean(priors[chosen, :, YAW], post_log_w[chosen]),
            chosen=chosen, total_log_lik=total, risk=risk, protection_level_m=level,
            integrity_ok=not reason, integrity_reason=reason,
            integrity_valid=self._motion_unknown_s == 0.0 and (
                settled_s >= cfg.integrity_settling_s),
            motion_unknown_s=self._motion_unknown_s,
            rejected=check.rejected, ess=ess, resampled=bool(resampled))
        self.last_result = result
        return result

    def _integrity(self, pos: np.ndarray, post_log_w: np.ndarray, chosen: int,
                   mean: np.ndarray, cov: np.ndarray, stamp_ns: int,
                   update: tuple) -> tuple[integrity.RiskBound, float]:
        """Risk bound at the alert limits and protection level over the M posteriors.

        Args:
            pos: (S, N, 3) particle positions of the motion samples [m].
            post_log_w: (S, N) their posterior log-weights.
            chosen: The chosen motion sample.
            mean: (3,) the estimate [m].
            cov: (3, 3) the chosen posterior's covariance [m^2].
            stamp_ns: Epoch time [ns].
            update: ``(prepared epoch, (k,) inlier probabilities, tempering exponent,
                (k,) clock weights)`` of the GNSS update.
        """
        cfg = self.config
        s, n = post_log_w.shape
        index = np.arange(cfg.n_posteriors) % s
        stride = max(n // cfg.n_particles, 1)
        if stride > 1:
            # Heading acquisition holds more particles than the working size; the bound
            # sees an evenly thinned set of the working size (the sets are in no order).
            pos, post_log_w = pos[:, ::stride], post_log_w[:, ::stride]
            post_log_w = post_log_w - logsumexp(post_log_w, axis=1, keepdims=True)
            prior_log_w = self.log_w[::stride] - logsumexp(self.log_w[::stride])
        else:
            prior_log_w = self.log_w
        prior_offsets = self.bias.offsets_m.copy()
        if cfg.bias_model == BIAS_NONE or update is None:
            offsets = prior_offsets
        else:
            prep, inlier, evidence, clock_w = update
            # The residuals at the estimate size the hypotheses; the update weighed each
            # satellite with tempering times inlier probability over its variance.
            at_estimate = gnss.clock_corrected_residuals(mean[None], prep, clock_w)[0]
            self.bias.observe_residuals(stamp_ns, at_estimate, inlier, 3 + prep.n_systems)
            weights = evidence * inlier / prep.sigma_m ** 2
            line = prep.sv_enu_m - mean
            line /= np.linalg.norm(line, axis=1, keepdims=True)
            _, prior_cov = weighted_mean_cov(pos[chosen], prior_log_w)
            offsets = self.bias.update(
                self.bias.biases_at(stamp_ns, prep.sv_key, prep.cn0_dbhz), line, weights,
                prep.sys_index, prep.n_systems, prior_cov, cov).copy()
        posteriors = integrity.PosteriorSet(pos, post_log_w, index, offsets,
                                            cfg.horizontal_risk)
        priors = integrity.PosteriorSet(pos, np.broadcast_to(prior_log_w, post_log_w.shape),
                                        index, prior_offsets, cfg.horizontal_risk)
        # KL(pi_t || pi_t-1) between Gaussian fits of the pooled posteriors and priors.
        kl = integrity.gaussian_kl(*posteriors.pooled_moments(), *priors.pooled_moments())
        limits = cfg.alert_limits_m
        dist_w = posteriors.distances(mean)
        risk = integrity.risk_bound(posteriors.hazard_mass(mean, limits, dist_w), kl,
                                    cfg.n_posteriors, cfg.risk_delta, cfg.inverse_bernoulli,
                                    limits)
        q_max = integrity.max_empirical_risk(cfg.target_risk, risk.epsilon,
                                             cfg.inverse_bernoulli)
        self.posterior_set = posteriors
        return risk, posteriors.protection_level(mean, q_max, dist_w)

    def _evidence_weight(self, dt_s: float) -> float:
        """Tempering exponent of this epoch's GNSS log-likelihood.

        Errors correlated over ``error_correlation_time_s`` are one piece of evidence per
        correlation time, not one per epoch.
        """
        cfg = self.config
        if cfg.error_correlation_time_s <= 0.0:
            return 1.0
        return min(1.0, max(dt_s, 1e-3) / cfg.error_correlation_time_s)

    @staticmethod
    def _circular_mean(yaw: np.ndarray, log_w: np.ndarray) -> float:
        w = np.exp(log_w)
        return float(np.arctan2(w @ np.sin(yaw), w @ np.cos(yaw)))
