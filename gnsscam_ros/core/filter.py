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

from . import gnss, integrity
from .bias import (BIAS_CN0, BIAS_LEARNED, BIAS_MODELS, BIAS_NONE, BiasHypotheses,
                   beyond_cloud, hidden_fault_sizes, leverages, with_hidden_faults)
from .config import ERROR_ADAPTIVE, FilterConfig
from .consistency import (ConsistencyMonitor, ConsistencyState, MovedFrom,
                          snapshot_position)
from .error_model import AdaptiveErrorModel
from .fusion import MAX_CAMERA_MATCHES, CameraMeasurement, camera_fusion
from .frames import LocalFrame, row_norms
from .gnss import LIKELIHOODS, PARTICLE_RAIM, ROBUST
from .kernels import weights as weight_kernels
from .noise import ProcessNoise
from .particles import (POS, STATE_DIM, SYSTEMATIC, YAW, MotionIncrement,
                        motion_samples, normalize_log_weights, propagate, weighted_mean_cov)
from .persistence import SnapshotPersistence, persisting_worth, tempering_exponent
from .rng import spawn
from .snapshot import solve_snapshot
# Epoch outcomes (``core.types``, so that the verdict needs no filter to read them).
from .types import INVALID, PROPAGATED, REJECTED, UPDATED, WAITING, GnssEpoch

# Importable from here as before: the parameter names and values of the configuration
# (``core.config``), the likelihoods (``core.gnss``) and the bias models (``core.bias``).
__all__ = ['BIAS_CN0', 'BIAS_LEARNED', 'BIAS_MODELS', 'BIAS_NONE', 'HEADING_LOST_RAD',
           'INVALID', 'LIKELIHOODS', 'MAX_ORIGIN_DISTANCE_M', 'MAX_STATE_COORDINATE',
           'PARTICLE_RAIM', 'PROPAGATED', 'REINITIALISING', 'REJECTED', 'ROBUST', 'UPDATED',
           'WAITING', 'EpochResult', 'FilterConfig', 'ParticleFilter']

#: How the results and verdicts of a discarded state end.
REINITIALISING = 're-initialising from the next fix'
#: Largest magnitude of a particle coordinate in the map frame [m] and of its (unwrapped)
#: heading [rad]. The frame is only valid within MAX_ORIGIN_DISTANCE_M of its origin; a
#: particle 10,000 km away comes from arithmetic gone wrong (or days of unknown motion),
#: and its squares in the range arithmetic must stay far from overflow.
MAX_STATE_COORDINATE = 1e7
#: What a step may raise on input that slipped through the checks (overflow into NaN,
#: a singular matrix, an allocation that failed): the state is then discarded.
_NUMERICAL_FAILURES = (ArithmeticError, ValueError, MemoryError, np.linalg.LinAlgError)
#: Farthest a given map frame origin may be from the first fix [m]. The filter moves
#: particles in the frame's east-north plane and treats its up axis as vertical; 100 km
#: away they are ~1 degree off the local ones, 6,000 km away (an origin left at 0, 0)
#: meaningless, so such an origin is a configuration error, not a frame.
MAX_ORIGIN_DISTANCE_M = 100_000.0
#: Heading uncertainty accrued over a dead-reckoning gap beyond which the heading counts
#: as lost and is acquired again (distance ``heading_acquisition_m``) [rad].
HEADING_LOST_RAD = 0.5
#: Travel since the first fix up to which the vehicle counts as not having moved [m]: its
#: heading, unknown, does not matter yet (a static receiver never needs it).
STATIONARY_M = 0.5
#: Particles of a set that the statistics of its shape see (an even thinning of a larger
#: set, weights normalised again): the consistency test's log-likelihood ratio (both of
#: its hypotheses on the same particles; a second full evaluation would double the
#: likelihood's cost) and the Gaussian fits of the bound's KL divergence (their moments:
#: every particle cost 0.3 ms at N = 10,000 and moved no protection level by more than
#: 0.1 % on emulated and smartLoc drives; the level itself takes every particle).
SHAPE_PARTICLES = 1000


@dataclass
class EpochResult:
    """What one GNSS epoch produced.

    Attributes:
        stamp_ns: Epoch time [ns].
        status: 'updated', 'propagated', 'rejected', 'waiting' or 'invalid' (the step left
            the state non-finite or absurd; nothing of it is reported and the filter
            starts again from the next usable fix).
        reason: Why the epoch was not used for an update ('' when it was).
        position_enu_m: (3,) estimate in the map frame [m] (None while waiting).
        covariance_m2: (3, 3) covariance of the chosen motion sample's set [m^2].
        yaw_rad: Heading estimate [rad].
        chosen_sample: Index of the chosen motion sample (of the S, the one with the
            highest total log-likelihood: the estimate's set).
        total_log_lik: (S,) total log-likelihood of each motion sample.
        risk: Risk bound for ``config.alert_limits_m`` (None when not updated).
        protection_level_m: Horizontal (or 3D, see ``horizontal_risk``) protection level:
            the smallest radius around the estimate whose risk bound is at most the target
            [m]; inf when none is, None when not updated.
        settling_s: Time since the heading was acquired (or since the start of a
            vehicle seen not to move) [s]; -1 while it is not: integrity settles for
            ``integrity_settling_s`` from then (``core.verdict``).
        motion_unknown_s: Part of the interval without dead reckoning [s].
        n_satellites: Satellites used in the update.
        rejected: ``{reason: count}`` of satellites dropped by the checks.
        gamma: (k,) mixture weights of the chosen motion sample's set.
        ess: Effective sample size of the chosen motion sample's set before resampling.
        resampled: Whether the chosen motion sample's set was resampled.
        camera_frame_ids: Frame ids of the camera measurements offered this epoch.
        camera_alpha: (K,) mixture weights alpha*_j of the chosen motion sample's set.
        camera_kl_nats: (K,) KL(Q_j || P) of the chosen motion sample's set.
        camera_excluded: The camera disagreed with GNSS and was left out this epoch.
        consistency: The consistency test of the cloud against the measurements after
            this epoch (``core.consistency``).
        recovered: The filter recovered this epoch (part of the cloud moved onto the
            snapshot solution).
        recoveries: Recoveries since the filter was made.
        tempering: Exponent of this epoch's GNSS log-likelihood (what the epoch was worth
            against an independent one; NaN: no GNSS update).
        persistent_share: Share of the GNSS error taken to persist (``core.persistence``).
    """

    stamp_ns: int
    status: str
    reason: str = ''
    position_enu_m: np.ndarray | None = None
    covariance_m2: np.ndarray | None = None
    yaw_rad: float = float('nan')
    chosen_sample: int = -1
    total_log_lik: np.ndarray | None = None
    risk: integrity.RiskBound | None = None
    protection_level_m: float | None = None
    settling_s: float = -1.0
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
    consistency: ConsistencyState = field(default_factory=ConsistencyState)
    recovered: bool = False
    recoveries: int = 0
    tempering: float = float('nan')
    persistent_share: float = 1.0


class ParticleFilter:
    """Particle RAIM filter over (east, north, up, yaw) with integrity risk.

    Args:
        config: Parameters.
        frame: The map frame; None anchors it at the first robust fix.
        rng: Random generator (explicit, for reproducible runs).
    """

    def __init__(self, config: FilterConfig, frame: LocalFrame | None = None,
                 rng: np.random.Generator | None = None):
        self.config = config                            # builds self.likelihood
        self.frame = frame
        self.rng = rng if rng is not None else np.random.default_rng()
        # The process noise has a stream of its own, drawn an epoch ahead (core.noise).
        self.noise = ProcessNoise(spawn(self.rng, 1)[0])
        self.particles: np.ndarray | None = None        # (N, 4) chosen set
        self.log_w: np.ndarray | None = None            # (N,)
        # The S motion samples of the last epoch (each the previous set moved by one draw
        # of the motion) and their weights after it; not the M posteriors of the bound.
        self.sample_particles: np.ndarray | None = None  # (S, N, 4)
        self.sample_log_w: np.ndarray | None = None      # (S, N)
        # The M posteriors of the last update as the risk bound saw them.
        self.posterior_set: integrity.PosteriorSet | None = None
        self.bias = BiasHypotheses(config.bias, config.n_posteriors, self.rng)
        self.errors = AdaptiveErrorModel(config.error_window_s, config.error_correlation_time_s)
        self.consistency = ConsistencyMonitor(config.consistency_suspect_nats,
                                              config.consistency_recover_nats)
        self.persistence = SnapshotPersistence(config.error_window_s)
        self._consistency_state = ConsistencyState()
        self.last_stamp_ns: int | None = None
        self.distance_since_init_m = 0.0
        self.acquired_stamp_ns: int | None = None      # end of heading acquisition
        self._settled_stationary = False                # settling while not yet moved
        self._motion_seen = False                       # known motion since the start
        self._motion_unknown_s = 0.0                    # of the epoch being processed
        self.moved_from = MovedFrom()                    # the last recovery's origin
        self.last_result: EpochResult | None = None

    @property
    def config(self) -> FilterConfig:
        """The parameters in force; setting them builds the GNSS likelihood they name."""
        return self._config

    @config.setter
    def config(self, config: FilterConfig) -> None:
        self.likelihood: gnss.Likelihood = gnss.make_likelihood(config.gnss)
        self._config = config

    @property
    def initialised(self) -> bool:
        return self.particles is not None

    def reset(self) -> None:
        """Forget the particle state: the next usable fix initialises the filter as the
        first one did. The configuration, the map frame (its origin may have been
        published) and the time of the last epoch stay; the bias hypotheses start afresh.
        """
        self.particles = self.log_w = None
        self.sample_particles = self.sample_log_w = None
        self.posterior_set = None
        self.bias = BiasHypotheses(self.config.bias, self.config.n_posteriors, self.rng)
        self.errors = AdaptiveErrorModel(self.config.error_window_s,
                                         self.config.error_correlation_time_s)
        self.consistency.reset()
        self.persistence.reset()
        self.distance_since_init_m = 0.0
        self.acquired_stamp_ns = None
        self._settled_stationary = False
        self._motion_unknown_s = 0.0
        self.moved_from = MovedFrom()
        self.last_result = None

    def state_problem(self, result: EpochResult | None = None) -> str | None:
        """Why the state (and ``result``, the epoch just run) cannot be trusted, or None.

        Checked: particles finite and within ``MAX_STATE_COORDINATE``, weights a
        distribution (no NaN, no +inf, some finite), bias offsets finite; of the result,
        estimate, covariance and heading finite, risk bound in [0, 1], protection level not
        NaN (inf means none within reach). One compiled pass over the N particles.
        """
        if self.particles is None:
            return None
        if self.log_w is None:
            return 'particle weights are not a distribution'
        code = weight_kernels.set_problem(np.ascontiguousarray(self.particles, dtype=float),
                                          np.ascontiguousarray(self.log_w, dtype=float),
                                          MAX_STATE_COORDINATE)
        if code == 2:
            return f'particles beyond {MAX_STATE_COORDINATE:g} m of the map origin'
        if code:
            return weight_kernels.SET_PROBLEMS[code - 1]
        if not np.isfinite(self.bias.offsets_m).all():
            return 'non-finite bias offsets'
        if result is None or result.position_enu_m is None:
            return None
        if not (np.isfinite(result.position_enu_m).all()
                and np.isfinite(result.covariance_m2).all()
                and np.isfinite(result.yaw_rad)):
            return 'non-finite estimate'
        if result.risk is not None:
            bound = np.asarray(result.risk.risk_bound, dtype=float)
            if not ((bound >= 0.0) & (bound <= 1.0)).all():
                return 'risk bound outside [0, 1]'
        if result.protection_level_m is not None and np.isnan(result.protection_level_m):
            return 'protection level is NaN'
        return None

    def set_parameters(self, **changes) -> None:
        """Change parameters between epochs (validated; the old ones stay on error)."""
        new = replace(self.config, **changes)
        if (new.bias != self.config.bias
                or new.n_posteriors != self.config.n_posteriors):
            self.bias = BiasHypotheses(new.bias, new.n_posteriors, self.rng)
        if new.n_particles != self.config.n_particles and self.initialised:
            idx = SYSTEMATIC.resize(self.log_w, self.rng, new.n_particles)
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
                epoch (``fusion.match_at_epoch``), oldest first; None or empty for GNSS
                only. Only the newest ``MAX_CAMERA_MATCHES`` are fused.

        Returns:
            The epoch's result; bad input never raises, it is reported in the result. A
            step that fails numerically or leaves the state invalid (:meth:`state_problem`)
            returns ``INVALID``: the state is discarded (:meth:`reset`; the last epoch's
            time stays that of the last good one) and the next usable fix initialises the
            filter again, so no estimate of the broken state is ever returned or kept.
        """
        problem = gnss.epoch_problem(epoch)
        if problem:
            stamp = epoch.stamp_ns if isinstance(epoch.stamp_ns, (int, np.integer)) else -1
            return EpochResult(stamp_ns=stamp, status=REJECTED, reason=problem)
        last_good_ns = self.last_stamp_ns
        try:
            result = self._step(epoch, motion, camera)
        except _NUMERICAL_FAILURES as err:
            problem = f'{type(err).__name__}: {err}'
        else:
            problem = None if result.status == REJECTED else self.state_problem(result)
            if problem is None:
                return result
        self.reset()
        # Not the bad epoch's time: a far-future stamp must not block every later epoch.
        self.last_stamp_ns = last_good_ns
        return EpochResult(stamp_ns=int(epoch.stamp_ns), status=INVALID,
                           reason=f'filter state invalid ({problem}): {REINITIALISING}')

    def _step(self, epoch: GnssEpoch, motion: MotionIncrement | None,
              camera: list[CameraMeasurement] | None) -> EpochResult:
        cfg = self.config
        if self.last_stamp_ns is not None and epoch.stamp_ns <= self.last_stamp_ns:
            return EpochResult(stamp_ns=epoch.stamp_ns, status=REJECTED,
                               reason=f'time went backwards or repeated: {epoch.stamp_ns} '
                                      f'<= {self.last_stamp_ns} ns')
        check = gnss.check_epoch(epoch, cfg.min_satellites, cfg.elevation_mask_deg,
                                 cfg.cn0_mask_dbhz, cfg.satellite_limit)
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
                           cfg.motion.position_process_var_m2(dt_s, motion.distance_m)
                           + np.array([gap_m2, gap_m2, 0.0]),
                           cfg.yaw_propagation_var_rad2 * dt_s
                           + (cfg.max_yaw_rate_rps * motion.unknown_s) ** 2,
                           self.noise.take((distance.shape[0], self.particles.shape[0],
                                            STATE_DIM)))
        # The predicted motion of the estimate, for the dead-reckoned path the snapshot
        # solutions are compared with (core.persistence). A poisoned state gives NaN here,
        # which restarts the window; the filter discards that state itself.
        moved = weight_kernels.weighted_displacement(self.particles, priors[0], self.log_w)
        self.persistence.move(moved)
        self.moved_from.move(moved)
        self._motion_unknown_s = float(motion.unknown_s)
        if motion.unknown_s * cfg.max_yaw_rate_rps > HEADING_LOST_RAD:
            # Without dead reckoning the heading drifts by up to max_yaw_rate_rps: beyond
            # HEADING_LOST_RAD it is unknown, is acquired again, and integrity settles
            # again before it is certified. A shorter gap (a late or restarted dead
            # reckoner) costs only its own epoch (ERROR) and the spread it adds.
            self.acquired_stamp_ns = None
            self.distance_since_init_m = 0.0
            self._motion_seen = False
        self.last_stamp_ns = epoch.stamp_ns
        self.distance_since_init_m += abs(motion.distance_m)
        self._motion_seen |= motion.unknown_s == 0.0
        prep = None
        if check.usable:
            centre, cov = weighted_mean_cov(priors[0], self.log_w)
            prep = self._prepare(gnss.kept_satellites(epoch, check), centre)
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
        usable = epoch.subset(check.keep)
        # The learned model weighs the first fix (by C/N0), not the stated variances.
        sigma = (self.errors.total_sigma_m(usable.cn0_dbhz)
                 if cfg.error_model == ERROR_ADAPTIVE else None)
        try:
            fix = solve_snapshot(usable, measurement_var_m2=cfg.measurement_var_m2,
                                 sigma_m=sigma)
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
        self._motion_seen = False
        # Evaluate the first epoch's measurements on the fresh set.
        priors = np.repeat(self.particles[None], cfg.motion_sample_count, axis=0)
        self._motion_unknown_s = 0.0
        centre, cov = weighted_mean_cov(self.particles, self.log_w)
        prep = self._prepare(gnss.kept_satellites(epoch, check), centre)
        return self._update(epoch, check, priors, prep, centre, cov, dt_s=0.0)

    def _prepare(self, epoch: GnssEpoch, centre: np.ndarray) -> gnss.PreparedEpoch:
        """The epoch's satellites for the likelihood, with the error model in force."""
        cfg = self.config
        learned = self.errors if cfg.error_model == ERROR_ADAPTIVE else None
        return gnss.prepare_epoch(epoch, self.frame, centre, cfg.measurement_var_m2,
                                  cfg.use_reported_variance, learned)

    def _propagate_only(self, epoch: GnssEpoch, check: gnss.GnssCheck,
                        priors: np.ndarray) -> EpochResult:
        # No usable measurements: keep the measured-motion sample and report no integrity.
        self.particles = priors[0]
        self.sample_particles = priors
        self.sample_log_w = np.broadcast_to(self.log_w, priors.shape[:2]).copy()
        mean, cov, yaw, _ = weight_kernels.set_summary(self.particles, self.log_w)
        result = EpochResult(stamp_ns=epoch.stamp_ns, status=PROPAGATED, reason=check.reason,
                             position_enu_m=mean, covariance_m2=cov, yaw_rad=float(yaw),
                             chosen_sample=0, rejected=check.rejected,
                             motion_unknown_s=self._motion_unknown_s)
        self.last_result = result
        return result

    def _update(self, epoch: GnssEpoch, check: gnss.GnssCheck, priors: np.ndarray,
                prep: gnss.PreparedEpoch, centre: np.ndarray, cov: np.ndarray,
                dt_s: float, camera: list[CameraMeasurement] | None = None) -> EpochResult:
        cfg = self.config
        # Receiver clock: robust inlier weights at the prior's centre, then per particle
        # (profiled out inside the likelihood kernel).
        spread_m = min(float(np.sqrt(max(np.trace(cov), 0.0))), cfg.clock_kernel_max_m)
        clock_w = gnss.clock_weights(prep, centre, spread_m)
        persisting = persisting_worth(dt_s, cfg.error_correlation_time_s)
        tempering = tempering_exponent(self.persistence.persistent_share, persisting)
        lik = self.likelihood.joint(priors, prep, clock_w, tempering, self.log_w)
        joint, total = lik.joint, lik.total
        self._consistency_state = self._snapshot_step(epoch.stamp_ns, priors[0], prep,
                                                      centre, spread_m, clock_w, tempering,
                                                      float(total[0]), persisting)
        fusion = None
        if camera and cfg.use_camera:
            # The cost is images x samples x particles: a bounded number of images.
            camera = camera[-MAX_CAMERA_MATCHES:]
            # Camera and GNSS distributions share the domain: the particles of each set.
            log_p = joint - total[:, None]
            fusion = camera_fusion(priors, np.array([c.position_enu_m[:3] for c in camera]),
                                   log_p, cfg.camera_temperature_m, cfg.camera_gate_m,
                                   cfg.camera_kl_threshold_nats, cfg.camera_elsewhere_prob)
            total = weight_kernels.add_and_sum_rows(joint, fusion.log_q_mix)
        post_log_w = joint
        post_log_w -= total[:, None]
        chosen = int(np.argmax(total))
        # The chosen set's inlier probability of each satellite, for the bias hypotheses
        # (over every particle: they carry it from epoch to epoch, and from SHAPE_PARTICLES
        # single GLONASS-only levels moved by up to 16 %), and its inlier share (reported).
        inlier, share = gnss.robust_inlier_shares(priors[chosen], post_log_w[chosen], prep,
                                                  clock_w, cfg.outlier_prob,
                                                  cfg.outlier_range_m, lik.geometry, chosen)
        result = self._finish(epoch, check, priors, post_log_w, chosen, total,
                              (prep, inlier, tempering, clock_w))
        result.tempering = tempering
        result.persistent_share = self.persistence.persistent_share
        if fusion is not None:
            result.camera_frame_ids = tuple(c.frame_id for c in camera)
            result.camera_alpha = fusion.alpha[:, chosen]
            result.camera_kl_nats = fusion.kl_nats[:, chosen]
            result.camera_excluded = bool(fusion.excluded[chosen])
        result.gamma = self.likelihood.mixture_weights(lik, chosen, share)
        result.n_satellites = int(prep.pr_m.shape[0])
        return result

    def _snapshot_step(self, stamp_ns: int, cloud: np.ndarray, prep: gnss.PreparedEpoch,
                       centre: np.ndarray, spread_m: float, clock_w: np.ndarray,
                       tempering: float, cloud_total: float, persisting: float
                       ) -> ConsistencyState:
        """What the epoch's own robust snapshot solution tells: its residuals teach the
        error model (``core.error_model``; the snapshot depends on this epoch alone, so
        a filter locked onto a wrong place cannot teach the model that place), and the
        cloud moved onto it is the alternative of the consistency test
        (``core.consistency``; ``clock_w``: the update's clock weights)."""
        cfg = self.config
        adaptive = cfg.error_model == ERROR_ADAPTIVE
        sigma = self.errors.total_sigma_m(prep.cn0_dbhz) if adaptive else prep.sigma_m
        snap = snapshot_position(prep.sv_enu_m, prep.pr_m, sigma, prep.sys_index,
                                 prep.n_systems, centre)
        if snap is None:
            return self.consistency.observe(stamp_ns, float('nan'))
        self.persistence.observe(stamp_ns, snap[:2])
        if adaptive:
            at_snap = gnss.clock_weights(prep, snap, cfg.clock_kernel_max_m)
            residual = gnss.clock_corrected_residuals(snap[None], prep, at_snap)[0]
            self.errors.observe(stamp_ns, residual, prep.cn0_dbhz, 3 + prep.n_systems,
                                prep.sv_key)
        shift = np.zeros(cloud.shape[1])
        shift[:2] = snap[:2] - centre[:2]
        log_w = self.log_w
        at_moved = gnss.clock_weights(prep, centre + shift[:3], spread_m)
        if cloud.shape[0] > SHAPE_PARTICLES:
            # Thinned cloud and moved cloud in one call, each with its own clock weights.
            thin = SYSTEMATIC.thin(cloud.shape[0], SHAPE_PARTICLES)
            cloud, log_w = cloud[thin], normalize_log_weights(log_w[thin])
            cloud_total, moved_total = (float(t) for t in self.likelihood.joint(
                np.stack((cloud, cloud + shift)), prep, np.stack((clock_w, at_moved)),
                tempering, log_w).total)
        else:                                   # the update weighed the cloud itself
            moved_total = float(self.likelihood.joint((cloud + shift)[None], prep, at_moved,
                                                      tempering, log_w).total[0])
        # The test weighs the epoch as if all of its error persisted: a snapshot solution
        # pulled off by an NLOS episode stays off for as long as the episode, and must not
        # outweigh the cloud sooner because the rest of the error is white. The ratio of
        # two likelihoods tempered alike scales with the exponent.
        return self.consistency.observe(
            stamp_ns, (moved_total - cloud_total) * (persisting / tempering), persisting,
            shift[:2])

    def _recover(self, stamp_ns: int) -> None:
        """Move a share of the cloud by the smoothed separation onto the snapshot
        solutions (its shape kept), so that the likelihood decides between the two places
        from now on."""
        shift = self._consistency_state.shift_m
        n = self.particles.shape[0]
        moved = self.rng.choice(n, size=max(1, int(self.config.recovery_share * n)),
                                replace=False)
        self.particles = self.particles.copy()
        self.particles[moved, :2] += shift
        if self.acquired_stamp_ns is not None:
            self.acquired_stamp_ns = stamp_ns               # settle again before OK

    def _finish(self, epoch: GnssEpoch, check: gnss.GnssCheck, priors: np.ndarray,
                post_log_w: np.ndarray, chosen: int, total: np.ndarray,
                update: tuple) -> EpochResult:
        """Estimate, integrity risk and resampling, shared by every update path."""
        cfg = self.config
        m, n = post_log_w.shape
        mean, cov, yaw, ess = weight_kernels.set_summary(priors[chosen], post_log_w[chosen])
        risk, level = self._integrity(priors, post_log_w, chosen, mean, cov, epoch.stamp_ns,
                                      update)
        # The heading matters once the vehicle moves: settling starts when it is acquired,
        # or at once while the vehicle has not moved (and again from acquisition if it
        # starts to move before that).
        acquiring = self.distance_since_init_m < cfg.heading_acquisition_m
        # Stationary: seen not to move (a fresh start has seen no motion at all yet).
        stationary = self._motion_seen and self.distance_since_init_m <= STATIONARY_M
        if self._settled_stationary and not stationary and acquiring:
            self.acquired_stamp_ns = None
        if (self.acquired_stamp_ns is None and self._motion_unknown_s == 0.0
                and (not acquiring or stationary)):
            self.acquired_stamp_ns = epoch.stamp_ns
        self._settled_stationary = stationary and self.acquired_stamp_ns is not None
        settled_s = (-1.0 if self.acquired_stamp_ns is None
                     else (epoch.stamp_ns - self.acquired_stamp_ns) * 1e-9)
        consistency = self._consistency_state
        if (consistency.inconsistent or consistency.recover) and not (
                consistency.separation_m > level):
            # The alternative is within the level the cloud claims: covered either way, no
            # alarm and nothing to recover to (a consistent cloud's statistic drifts up).
            consistency = consistency.withdrawn()
        # The estimate may be the wrong one of two places: while the test says so, and
        # until integrity has settled (the cloud has not yet shown that it is consistent;
        # the verdict is not OK then either), the level covers the other.
        unsettled = settled_s < cfg.integrity_settling_s
        own_level = level
        if (consistency.inconsistent or unsettled) and np.isfinite(consistency.separation_m):
            level = max(level, consistency.separation_m)
        # After a recovery, until integrity has settled again, the place it left too.
        level = self.moved_from.cover(mean, level, unsettled)
        particles, log_w = priors[chosen], post_log_w[chosen]
        acquired = self.distance_since_init_m >= cfg.heading_acquisition_m
        n_out = cfg.n_particles if acquired else n
        resampled = ess < cfg.resample_ess_fraction * n or n_out != n
        if resampled:
            # At the end of heading acquisition n_out is the working size: the set thins.
            particles = particles[SYSTEMATIC.resample(log_w, self.rng, n_out)]
            log_w = np.full(n_out, -np.log(n_out))
        self.particles, self.log_w = particles, normalize_log_weights(log_w)
        if consistency.recover:
            self.consistency.recovered()
            self.moved_from.start(mean, own_level)
            self._recover(epoch.stamp_ns)
        self.sample_particles, self.sample_log_w = priors, post_log_w
        result = EpochResult(
            stamp_ns=epoch.stamp_ns, status=UPDATED, position_enu_m=mean, covariance_m2=cov,
            yaw_rad=float(yaw),
            chosen_sample=chosen, total_log_lik=total, risk=risk, protection_level_m=level,
            settling_s=settled_s, motion_unknown_s=self._motion_unknown_s,
            rejected=check.rejected, ess=float(ess), resampled=bool(resampled),
            consistency=consistency, recovered=consistency.recover,
            recoveries=self.consistency.recoveries)
        self.last_result = result
        return result

    def _integrity(self, sets: np.ndarray, post_log_w: np.ndarray, chosen: int,
                   mean: np.ndarray, cov: np.ndarray, stamp_ns: int,
                   update: tuple) -> tuple[integrity.RiskBound, float]:
        """Risk bound at the alert limits and protection level over the M posteriors.

        Args:
            sets: (S, N, 4) particles of the motion samples.
            post_log_w: (S, N) their posterior log-weights.
            chosen: The chosen motion sample.
            mean: (3,) the estimate [m].
            cov: (3, 3) the chosen motion sample's covariance [m^2].
            stamp_ns: Epoch time [ns].
            update: ``(prepared epoch, (k,) inlier probabilities, tempering exponent,
                (k,) clock weights)`` of the GNSS update.
        """
        cfg = self.config
        s, n = post_log_w.shape
        index = np.arange(cfg.n_posteriors) % s
        thin = SYSTEMATIC.thin(n, cfg.n_particles)
        if thin.step > 1:
            # Heading acquisition holds more particles than the working size; the bound
            # sees an evenly thinned set of about the working size.
            sets, post_log_w = sets[:, thin], post_log_w[:, thin]
            post_log_w = normalize_log_weights(post_log_w)
            prior_log_w = normalize_log_weights(self.log_w[thin])
        else:
            prior_log_w = self.log_w
        prior_offsets = self.bias.offsets_m.copy()
        prep, inlier, tempering, clock_w = update
        if cfg.bias_model == BIAS_NONE:
            offsets = prior_offsets
        else:
            # The 'learned' hypotheses take the persisting part of an inlier's error (the
            # core of its class times the square root of the persisting share: the white
            # part is averaged by the filter and is in the cloud's own spread) and how
            # long it persists from the error model; the residuals at the estimate size
            # the 'cn0' ones. The update weighed each satellite with tempering times inlier
            # probability over its variance.
            sigma = tau = learned = None
            if cfg.bias_model == BIAS_LEARNED:
                learned = self.errors.satellite_model(prep.cn0_dbhz)
                sigma = learned[0] * np.sqrt(self.persistence.persistent_share)
                tau = self.errors.correlation_time_s
            else:
                at_estimate = gnss.clock_corrected_residuals(mean[None], prep, clock_w)[0]
                self.bias.observe_residuals(stamp_ns, at_estimate, inlier,
                                            3 + prep.n_systems)
            weights = tempering * inlier / prep.sigma_m ** 2
            line = prep.sv_enu_m - mean
            line /= row_norms(line)[:, None]
            # The whole rows: a kernel that reads three columns needs no copy of them.
            _, prior_cov = weighted_mean_cov(sets[chosen], prior_log_w)
            biases = self.bias.biases_at(stamp_ns, prep.sv_key, prep.cn0_dbhz, sigma, tau)
            if cfg.bias_model == BIAS_LEARNED and cfg.hidden_fault_core_sds > 0.0:
                # Plus one satellite's unseen bias per hypothesis (core.bias), at most the
                # reach of its class's wide component (mean + 3 sd): the largest error the
                # learned model gives any weight to.
                core, _, wide_mean, wide_sd = learned
                gauss_markov = biases
                biases = with_hidden_faults(biases, hidden_fault_sizes(
                    core, leverages(line, weights, prep.sys_index, prep.n_systems),
                    cfg.hidden_fault_core_sds, np.abs(wide_mean) + 3.0 * wide_sd))
                faults = biases - gauss_markov
            else:
                faults = None
            prior_faults = self.bias.fault_offsets_m.copy()
            offsets = self.bias.update(
                biases, line, weights,
                prep.sys_index, prep.n_systems, prior_cov, cov, faults).copy()
            if cfg.bias_beyond_cloud and self.errors.correlation_measured:
                # Only what the sets' spreads do not already hold (core.bias.beyond_cloud).
                # That they hold the persisting errors rests on how long those persist:
                # unmeasured (sparse epochs, a stated error model), every offset counts.
                dims = 2 if cfg.horizontal_risk else 3
                offsets = beyond_cloud(offsets, self.bias.fault_offsets_m, cov, dims)
                prior_offsets = beyond_cloud(prior_offsets, prior_faults, prior_cov, dims)
        pos = sets[..., POS]
        posteriors = integrity.PosteriorSet(pos, post_log_w, index, offsets,
                                            cfg.horizontal_risk)
        # KL(pi_t || pi_t-1) between Gaussian fits of the pooled posteriors and priors (their
        # moments from an even thinning of each set, SHAPE_PARTICLES); it sets q_max, so
        # the empirical risk and the level, over every particle, come from one pass.
        fit_thin = SYSTEMATIC.thin(post_log_w.shape[1], SHAPE_PARTICLES)
        fit_log_w, fit_prior_log_w = post_log_w[:, fit_thin], prior_log_w[fit_thin]
        if fit_thin.step > 1:
            fit_log_w = normalize_log_weights(fit_log_w)
            fit_prior_log_w = normalize_log_weights(fit_prior_log_w)
        fits = integrity.PosteriorSet(pos[:, fit_thin], fit_log_w, index, offsets,
                                      cfg.horizontal_risk)
        # One row of the priors' weights for all (np.broadcast_to cost 12 us at N = 120).
        kl = fits.divergence_from(integrity.PosteriorSet(
            fits.positions_m, fit_prior_log_w[None], index, prior_offsets,
            cfg.horizontal_risk))
        eps = integrity.divergence_budget(kl, cfg.n_posteriors, cfg.risk_delta)
        q_max = integrity.max_empirical_risk(cfg.target_risk, eps, cfg.inverse_bernoulli)
        limits = cfg.alert_limits_m
        empirical, level = posteriors.risk_and_level(mean, limits, q_max)
        risk = integrity.risk_bound(empirical, kl, cfg.n_posteriors, cfg.risk_delta,
                                    cfg.inverse_bernoulli, limits)
        self.posterior_set = posteriors
        return risk, level
