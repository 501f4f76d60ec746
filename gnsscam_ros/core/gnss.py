"""GNSS module: receiver clock handling and the Particle RAIM likelihood; the measurement
checks (:mod:`.gnss_checks`, re-exported here).

Paper §3 (Particle RAIM): the likelihood of a particle is a Gaussian mixture over the
satellites, ``sum_k gamma_k N(pr_k | range_k + clock, sigma_k^2)``, with the mixture weights
``gamma`` from one EM step: per-particle votes by squared-normal voting on the normalised
residuals, normalised per particle and pooled across particles by MAP with a Dirichlet
prior. Everything is computed in log space with a max shift (log-sum-exp).

The receiver clock is estimated online: per constellation, a robust mode of
the residuals at the prior's centre picks the consistent satellites, then every particle
gets its own clock as the inlier-weighted mean of its residuals. This profiles the clock out
per particle (it is strongly correlated with height).

The per-particle work (ranges, clocks, likelihoods) runs in the compiled kernels of
``core.kernels.gnss``; this module prepares their inputs and holds the model objects.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from .error_model import AdaptiveErrorModel
from .frames import LocalFrame, sagnac_corrected
# The checks need no kernel: gnss_node imports them alone (no numba).
from .gnss_checks import (MAX_PSEUDORANGE_M, MAX_SATELLITE_RADIUS_M,  # noqa: F401
                          MAX_EPOCH_SATELLITES, MAX_VARIANCE_M2, GnssCheck, check_epoch,
                          epoch_problem, kept_satellites, satellite_key)
from .kernels import gnss as gnss_kernels
from .kernels import inliers as inlier_kernels
from .types import GnssEpoch

LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)

# Likelihoods of the GNSS update: the values of the ``likelihood`` parameter, each the
# name of one :class:`Likelihood` (``LIKELIHOOD_MODELS``).
PARTICLE_RAIM = 'particle_raim'    # the paper's mixture over satellites, weights by EM
ROBUST = 'robust'                  # Gaussian with a uniform outlier floor per satellite


@dataclass(frozen=True)
class PreparedEpoch:
    """Satellites of one epoch in the map frame, ready for per-particle evaluation.

    Attributes:
        sv_enu_m: (k, 3) Earth-rotation corrected satellite positions in ENU [m].
        pr_m: (k,) pseudoranges [m].
        sigma_m: (k,) measurement standard deviations [m].
        sys_index: (k,) constellation index 0..S-1 (one clock each).
        n_systems: Number of distinct constellations S.
        sv_key: (k,) ``system * 1000 + sv_id``, one key per satellite across epochs.
        cn0_dbhz: (k,) carrier-to-noise density ratios [dB-Hz] (NaN when unknown).
        wide_share: (k,) weight of the NLOS / multipath component of each satellite's
            learned error mixture (None: no such component, the stated model).
        wide_mean_m: (k,) its mean [m] (None as above).
        wide_sd_m: (k,) its standard deviation [m] (None as above).
    """

    sv_enu_m: np.ndarray
    pr_m: np.ndarray
    sigma_m: np.ndarray
    sys_index: np.ndarray
    n_systems: int
    sv_key: np.ndarray
    cn0_dbhz: np.ndarray
    wide_share: np.ndarray | None = None
    wide_mean_m: np.ndarray | None = None
    wide_sd_m: np.ndarray | None = None
    # Per-satellite terms derived from the fields above, computed once per epoch however
    # many likelihood calls need them (:func:`robust_terms`). The arrays are never
    # written to after construction, so what is derived from them stays valid.
    _derived: dict = field(default_factory=dict, init=False, repr=False, compare=False)


@dataclass(frozen=True)
class RobustTerms:
    """Per-satellite terms of the robust density as the kernels take them (see
    :func:`robust_terms`): ``log_scale``, ``floor``, ``wide_log_scale``, ``wide_high``
    (k,) and ``group`` (satellites per log)."""

    log_scale: np.ndarray
    floor: np.ndarray
    wide_log_scale: np.ndarray
    wide_high: np.ndarray
    group: int

    @property
    def arrays(self) -> tuple:
        """The arrays in the kernels' argument order."""
        return (self.log_scale, self.floor, self.wide_log_scale, self.wide_high)


#: Share of the flat floor under the learned mixture: what neither the line-of-sight
#: core nor the NLOS component explains (faults of hundreds of metres) costs at most
#: ``log(FAULT_SHARE / outlier_range_m)`` per satellite.
FAULT_SHARE = 0.01
#: ``log`` of a component that is absent: ``elementary.exp`` gives exactly 0 for it.
ABSENT_LOG = -1000.0


def prepare_epoch(epoch: GnssEpoch, frame: LocalFrame, rx_enu_m: np.ndarray,
                  measurement_var_m2: float, use_reported_variance: bool,
                  error_model: AdaptiveErrorModel | None = None) -> PreparedEpoch:
    """Correct Earth rotation, move satellites to ENU and drop single-satellite systems.

    A constellation seen through one satellite only fixes its own clock: its residual is
    zero for every particle, so it carries no position information and would flatten the
    mixture. It is dropped here.

    Args:
        epoch: Validated epoch (see :func:`check_epoch`).
        frame: The map frame.
        rx_enu_m: (3,) approximate receiver position for the signal flight time [m].
        measurement_var_m2: Default pseudorange variance [m^2].
        use_reported_variance: Use the larger of the default and the epoch's own variances.
        error_model: The learned error model: it gives every satellite its core spread
            and outlier part from its signal class, and the two arguments above are not
            used (None: the stated variances and the likelihood's constants).
    """
    sys_index, n_systems = gnss_kernels.constellation_index(
        np.asarray(epoch.system, dtype=np.int64))
    multi = sys_index >= 0
    rx_ecef = frame.enu_to_ecef(rx_enu_m)
    sv_ecef = sagnac_corrected(epoch.sv_pos_ecef_m[multi], rx_ecef)
    cn0 = np.asarray(epoch.cn0_dbhz[multi], dtype=float)
    share = mean = spread = None
    if error_model is not None:
        sigma, share, mean, spread = error_model.satellite_model(cn0)
    else:
        var = np.full(int(multi.sum()), float(measurement_var_m2))
        if use_reported_variance:
            var = np.maximum(var, epoch.var_m2[multi])
        sigma = np.sqrt(var)
    return PreparedEpoch(sv_enu_m=frame.ecef_to_enu(sv_ecef), pr_m=epoch.pr_m[multi].copy(),
                         sigma_m=sigma, sys_index=sys_index[multi],
                         n_systems=int(n_systems), sv_key=satellite_key(epoch, 1000)[multi],
                         cn0_dbhz=cn0, wide_share=share, wide_mean_m=mean,
                         wide_sd_m=spread)


def clock_weights(prep: PreparedEpoch, centre_m: np.ndarray, spread_m: float,
                  iterations: int = 3) -> np.ndarray:
    """Robust per-constellation clock at the prior's centre; returns satellite weights.

    For each constellation, every satellite's residual at ``centre_m`` is a clock
    candidate; the one with the most support under a Gaussian kernel wins, then a few
    mean-shift steps refine it (a Welsch M-estimator). The kernel width is the measurement
    noise widened by how far the centre may be from the particles (``spread_m``), so that
    geometry alone does not turn healthy satellites into outliers.

    Args:
        prep: The prepared epoch.
        centre_m: (3,) reference point, map frame [m].
        spread_m: Position uncertainty of the reference point [m].
        iterations: Mean-shift refinement steps.

    Returns:
        (k,) non-negative weights; within a constellation they sum to one.
    """
    # The residuals at the point inside the kernel (five numpy calls less, three times an
    # epoch).
    return gnss_kernels.clock_weights_at(
        prep.sv_enu_m, prep.pr_m, np.ascontiguousarray(centre_m, dtype=float).reshape(3),
        prep.sigma_m, prep.sys_index, prep.n_systems, float(spread_m), iterations)


def clock_corrected_residuals(positions_m: np.ndarray, prep: PreparedEpoch,
                              clock_weights: np.ndarray) -> np.ndarray:
    """Residuals (P, k) at (P, >= 3) positions after removing each position's own
    per-constellation clock (the inlier-weighted mean of its residuals) [m]."""
    return gnss_kernels.residuals_of_points(np.ascontiguousarray(positions_m, dtype=float),
                                            prep.sv_enu_m, prep.pr_m, prep.sys_index,
                                            clock_weights, prep.n_systems)


def robust_terms(prep: PreparedEpoch, outlier_prob: float, outlier_range_m: float,
                 log_range: float = 690.0) -> RobustTerms:
    """The robust model's per-satellite density as the kernels take it.

    ``scale_k exp(-z_k^2 / 2) + wide_k exp(-w_k^2 / 2) + floor_k``. With the learned error
    mixture (``prep.wide_share`` set): the core ``(1 - pi_k - FAULT_SHARE) N(0, s0_k)``;
    the NLOS / multipath component of weight ``pi_k``, flat over the delays it produces
    (``0 .. mu_k + 2 s1_k``: a reflection only ever delays a signal, by any amount, so
    within that range it pulls the position nowhere) and falling off beyond it like the
    core, with the core's sigma (a large *negative* residual is no reflection: the
    asymmetry that tells a wrong position from NLOS; the kernels take its fall below 0 as
    the core's own, ``core.kernels.gnss._robust_densities``); and ``FAULT_SHARE`` flat
    over ``outlier_range_m``. With the stated model: ``(1 - eps) N(0, sigma_k)`` and
    ``eps`` over ``outlier_range_m``.
    ``group`` is the number of densities whose product stays within ``exp(+-log_range)``
    (the kernel takes one log per group; 690: float64, 87: float32); 0 when a single
    density may already lie outside it (a zero floor).
    """
    key = (float(outlier_prob), float(outlier_range_m))
    terms = prep._derived.get(key + (log_range,))
    if terms is None:
        derived = prep._derived.get(key)
        if derived is None:
            derived = prep._derived[key] = _robust_arrays(prep, *key)
        *arrays, per_term = derived
        group = int(log_range / per_term) if np.isfinite(per_term) else 0
        terms = prep._derived[key + (log_range,)] = RobustTerms(*arrays, group)
    return terms


def _robust_arrays(prep: PreparedEpoch, outlier_prob: float, outlier_range_m: float
                   ) -> tuple:
    """:func:`robust_terms`' arrays and the largest ``|log|`` of a single density."""
    k = prep.pr_m.shape[0]
    if prep.wide_share is not None:
        arrays = tuple(np.empty(k) for _ in range(4))
        per_term = gnss_kernels.learned_robust_terms(
            prep.sigma_m, np.asarray(prep.wide_share, dtype=float),
            np.asarray(prep.wide_mean_m, dtype=float), np.asarray(prep.wide_sd_m, dtype=float),
            FAULT_SHARE, float(outlier_range_m), *arrays)
        return (*arrays, per_term)
    core = np.full(k, 1.0 - outlier_prob)
    wide_log = np.full(k, ABSENT_LOG)
    high = np.zeros(k)
    log_scale = np.log(core) - np.log(prep.sigma_m) - LOG_SQRT_2PI
    floor = np.full(k, outlier_prob / outlier_range_m)
    # Every density lies between its floor and the sum of its scales and its floor.
    with np.errstate(divide='ignore'):                  # no floor: log 0 = -inf
        log_floor = np.log(floor)
    log_largest = np.logaddexp(np.logaddexp(log_scale, wide_log), log_floor)
    per_term = max(float(np.abs(log_floor).max(initial=0.0)),
                   float(np.abs(log_largest).max(initial=0.0)), 1e-3)
    return log_scale, floor, wide_log, high, per_term


#: Largest distance of a particle from the cloud centre of the float32 likelihood [m]:
#: float32 offsets of up to 1 km are exact to 6e-5 m (a particle farther out takes the
#: exact float64 residuals, :func:`core.kernels.gnss.robust_joint_single`).
SINGLE_MAX_OFFSET_M = 1000.0
#: Largest error of the second-order range expansion the float32 likelihood allows [m]
#: (``|d|^3 / (2 rho0^2)``: at 2e7 m, offsets up to 2 km).
SINGLE_EXPANSION_TOLERANCE_M = 1e-5
#: Products of densities of the float32 likelihood stay within exp(+-87): normal float32
#: numbers (1.2e-38 = exp(-87.3) to 3.4e38 = exp(88.7)). Twelve satellites of the default
#: model (densities down to the floor 1e-3 = exp(-6.9)) make one product, so one log.
SINGLE_LOG_RANGE = 87.0


@dataclass(frozen=True)
class RelativeGeometry:
    """Satellites seen from centres near the particle cloud, for the float32 likelihood
    (:func:`core.kernels.gnss.robust_joint_single` says how they are used): G views, one
    of all sets or one per set.

    Attributes:
        centre_m: (G, 3) the centres [m].
        unit: (G, k, 3) unit vectors from a centre to the satellites.
        base_m: (G, k) pseudorange minus range from the centre minus a common clock per
            constellation [m].
        half_inv_range: (G, k) 1 / (2 range from the centre) [1/m].
        max_offset_m: (G,) farthest a particle may be from its centre on the float32
            path [m].
    """

    centre_m: np.ndarray
    unit: np.ndarray
    base_m: np.ndarray
    half_inv_range: np.ndarray
    max_offset_m: np.ndarray


def relative_geometry(sets: np.ndarray, prep: PreparedEpoch, clock_weights: np.ndarray
                      ) -> RelativeGeometry | None:
    """The float32 likelihood's view of an epoch from the centre of (S, N, >= 3) sets with
    (k,) or (1, k) clock weights, or its S views, one from each set's centre with its own
    clock weights ((S, k)); None where float32 would not be exact enough (a centre that is
    not finite). A common clock per constellation (the clock weights sum to one in each)
    is taken out of the base: every particle's own clock removes it again, and it keeps
    the float32 residuals small."""
    clock_w = np.ascontiguousarray(clock_weights, dtype=float).reshape(-1, prep.pr_m.shape[0])
    centre, unit, base, half_inv_range, closest, finite = gnss_kernels.relative_views(
        sets, prep.sv_enu_m, prep.pr_m, prep.sys_index, prep.n_systems, clock_w)
    if not finite:
        return None
    # numpy's cbrt, not the kernel's: the two differ in the last bit, and this bound
    # decides which particles take the float64 path.
    max_offset = [float(min(SINGLE_MAX_OFFSET_M,
                            np.cbrt(2.0 * SINGLE_EXPANSION_TOLERANCE_M * float(rho) ** 2)))
                  for rho in closest]
    return RelativeGeometry(centre_m=centre, unit=unit, base_m=base,
                            half_inv_range=half_inv_range, max_offset_m=np.array(max_offset))


def robust_inlier_shares(positions_m: np.ndarray, log_w: np.ndarray, prep: PreparedEpoch,
                         clock_weights: np.ndarray, outlier_prob: float,
                         outlier_range_m: float, geometry: RelativeGeometry | None = None,
                         view: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Posterior probability that each satellite is an inlier under the robust model, for
    one particle set (N, >= 3) with normalised log-weights (N,).

    With ``geometry`` (the views the float32 likelihood took, ``GnssLikelihood.geometry``;
    ``view``: the set's view, 0 when one is shared) the densities are those float32 ones
    (twice as fast at N = 10,000), else float64.

    Returns:
        ``(probability (k,), share (k,))``: the probabilities averaged under the weights
        (in [0, 1]; the bias hypotheses weigh satellites with them) and their plain
        average over the particles normalised to sum to one (the robust likelihood's
        mixture weights, reported with the epoch).
    """
    positions_m = np.ascontiguousarray(positions_m, dtype=float)
    log_w = np.ascontiguousarray(log_w, float)
    clock_weights = np.ascontiguousarray(clock_weights, dtype=float)
    terms = robust_terms(prep, outlier_prob, outlier_range_m)
    if geometry is not None:
        g = slice(view, view + 1) if geometry.centre_m.shape[0] > 1 else slice(0, 1)
        return inlier_kernels.robust_inlier_shares_single(
            positions_m, log_w, geometry.centre_m[g], geometry.unit[g], geometry.base_m[g],
            geometry.half_inv_range[g], geometry.max_offset_m[g], prep.sv_enu_m, prep.pr_m,
            1.0 / prep.sigma_m, prep.sys_index, clock_weights.reshape(1, -1),
            prep.n_systems, *terms.arrays)
    return inlier_kernels.robust_inlier_shares(
        positions_m, log_w, prep.sv_enu_m, prep.pr_m, 1.0 / prep.sigma_m, prep.sys_index,
        clock_weights, prep.n_systems, *terms.arrays)


@dataclass(frozen=True)
class GnssLikelihood:
    """The GNSS update of S particle sets.

    Attributes:
        joint: (S, N) joint log-weights: prior log-weight plus the tempered
            log-likelihood of each particle.
        total: (S,) log-sum-exp of each set's joint (its log marginal likelihood).
        gamma: (S, k) satellite mixture weights of each set (Particle RAIM; None for the
            robust likelihood, whose weights are those of the chosen set only).
        geometry: The views of the float32 likelihood, where it was taken (the inlier
            shares of a set are then taken alike, :func:`robust_inlier_shares`).
    """

    joint: np.ndarray
    total: np.ndarray
    gamma: np.ndarray | None = None
    geometry: RelativeGeometry | None = None


class Likelihood(Protocol):
    """A GNSS likelihood of the filter update, built once from the configuration
    (:func:`make_likelihood`)."""

    def joint(self, sets: np.ndarray, prep: PreparedEpoch, clock_weights: np.ndarray,
              tempering: float, prior_log_w: np.ndarray) -> GnssLikelihood:
        """Joint log-weights of the (S, N, >= 3) sets: ``prior_log_w`` (N,) plus
        ``tempering`` times each particle's log-likelihood, its clock profiled out.

        ``clock_weights``: (k,) for every set, or (S, k), a row per set: sets about
        places of their own in one call (the consistency test's cloud and the cloud
        moved onto the snapshot solution), each weighed as a call on it alone would."""

    def mixture_weights(self, lik: GnssLikelihood, chosen: int,
                        inlier_share: np.ndarray) -> np.ndarray:
        """The (k,) satellite weights of set ``chosen`` (reported with the epoch), from
        ``lik`` and the set's robust inlier share (:func:`robust_inlier_shares`)."""


def _sets(sets: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(sets, dtype=float)


def _clock_rows(clock_weights: np.ndarray) -> np.ndarray:
    """Clock weights as the kernels take them: (1, k) for every set or (S, k)."""
    rows = np.asarray(clock_weights)
    # np.atleast_2d's result without its dispatch.
    return np.ascontiguousarray(rows[None] if rows.ndim == 1 else rows, dtype=float)


@dataclass(frozen=True)
class ParticleRaimLikelihood:
    """The paper's mixture over satellites with weights from one EM step.

    ``sum_k gamma_k N(pr_k | range_k + clock, sigma_k^2)``; E-step: each particle votes for
    satellite k with ``exp(-z_k^2 / 2)`` normalised over the satellites (squared-normal
    voting); M-step: the votes pooled over the set by weight with a Dirichlet prior (MAP):
    ``gamma_k = (sum_p w_p v_pk + alpha - 1) / (1 + k (alpha - 1))``.

    Attributes:
        dirichlet_alpha: Dirichlet concentration (> 1 keeps every satellite possible).
    """

    dirichlet_alpha: float

    @classmethod
    def from_config(cls, config) -> 'ParticleRaimLikelihood':
        return cls(dirichlet_alpha=config.dirichlet_alpha)

    def joint(self, sets, prep, clock_weights, tempering, prior_log_w) -> GnssLikelihood:
        sets = _sets(sets)
        joint = np.empty(sets.shape[:2])
        gamma = np.empty((sets.shape[0], prep.pr_m.shape[0]))
        total = gnss_kernels.particle_raim_joint(
            sets, prep.sv_enu_m, prep.pr_m, 1.0 / prep.sigma_m, prep.sys_index,
            _clock_rows(clock_weights), prep.n_systems, float(self.dirichlet_alpha),
            float(tempering), np.ascontiguousarray(prior_log_w, dtype=float), joint, gamma)
        return GnssLikelihood(joint=joint, total=total, gamma=gamma)

    def mixture_weights(self, lik, chosen, inlier_share) -> np.ndarray:
        return lik.gamma[chosen]                 # the EM weights, computed for every set


@dataclass(frozen=True)
class RobustLikelihood:
    """Product over satellites of a Gaussian with a uniform outlier floor.

    ``log L = sum_k log((1 - eps) N(e_k; 0, sigma_k) + eps / range_out)``: every healthy
    satellite contributes information, while a faulty one costs at most a constant.

    Attributes:
        outlier_prob: Outlier probability eps.
        outlier_range_m: Width of the uniform outlier density [m].
    """

    outlier_prob: float
    outlier_range_m: float

    @classmethod
    def from_config(cls, config) -> 'RobustLikelihood':
        return cls(outlier_prob=config.outlier_prob, outlier_range_m=config.outlier_range_m)

    single_precision: bool = True

    def joint(self, sets, prep, clock_weights, tempering, prior_log_w) -> GnssLikelihood:
        """The joint in float32 (relative coordinates) where that is exact enough: densities
        within the float32 range and a finite cloud centre; else in float64."""
        sets = _sets(sets)
        clock_w = _clock_rows(clock_weights)
        joint = np.empty(sets.shape[:2])
        prior_log_w = np.ascontiguousarray(prior_log_w, dtype=float)
        inv_sigma = 1.0 / prep.sigma_m
        terms = robust_terms(prep, self.outlier_prob, self.outlier_range_m, SINGLE_LOG_RANGE)
        geometry = None
        if self.single_precision and terms.group >= 1:
            # One view for every set, or each set its own with its own clock weights.
            geometry = relative_geometry(sets, prep, clock_w)
        if geometry is not None:
            total = gnss_kernels.robust_joint_single(
                sets, geometry.centre_m, geometry.unit, geometry.base_m,
                geometry.half_inv_range, geometry.max_offset_m, prep.sv_enu_m, prep.pr_m,
                inv_sigma, prep.sys_index, clock_w, prep.n_systems, *terms.arrays,
                terms.group, float(tempering), prior_log_w, joint)
            return GnssLikelihood(joint=joint, total=total, geometry=geometry)
        terms = robust_terms(prep, self.outlier_prob, self.outlier_range_m)
        total = gnss_kernels.robust_joint(
            sets, prep.sv_enu_m, prep.pr_m, inv_sigma, prep.sys_index,
            clock_w, prep.n_systems, *terms.arrays, max(terms.group, 1),
            float(tempering), prior_log_w, joint)
        return GnssLikelihood(joint=joint, total=total)

    def mixture_weights(self, lik, chosen, inlier_share) -> np.ndarray:
        return inlier_share                      # the chosen set's inlier share


#: The likelihood of each value of the ``likelihood`` parameter.
LIKELIHOOD_MODELS = {PARTICLE_RAIM: ParticleRaimLikelihood, ROBUST: RobustLikelihood}
LIKELIHOODS = tuple(LIKELIHOOD_MODELS)


def make_likelihood(config) -> Likelihood:
    """The likelihood a configuration names (``config.likelihood``), with its parameters
    (any object with the parameter attributes: ``FilterConfig`` or its ``gnss`` part).

    Raises:
        ValueError: An unknown likelihood name.
    """
    model = LIKELIHOOD_MODELS.get(config.likelihood)
    if model is None:
        raise ValueError(f'likelihood must be one of {LIKELIHOODS}')
    return model.from_config(config)
