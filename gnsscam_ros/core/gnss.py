"""GNSS module: measurement checks, receiver clock handling and the Particle RAIM likelihood.

Paper §3 (Particle RAIM): the likelihood of a particle is a Gaussian mixture over the
satellites, ``sum_k gamma_k N(pr_k | range_k + clock, sigma_k^2)``, with the mixture weights
``gamma`` from one EM step: per-particle votes by squared-normal voting on the normalised
residuals, normalised per particle and pooled across particles by MAP with a Dirichlet
prior. Everything is computed in log space with a max shift (log-sum-exp).

The receiver clock is estimated online: per constellation, a robust mode of
the residuals at the prior's centre picks the consistent satellites, then every particle
gets its own clock as the inlier-weighted mean of its residuals. This profiles the clock out
per particle (it is strongly correlated with height) at the cost of one small matrix product.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from .frames import LocalFrame, sagnac_corrected
from .types import GnssEpoch

LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)

# Likelihoods of the GNSS update: the values of the ``likelihood`` parameter, each the
# name of one :class:`Likelihood` (``LIKELIHOOD_MODELS``).
PARTICLE_RAIM = 'particle_raim'    # the paper's mixture over satellites, weights by EM
ROBUST = 'robust'                  # Gaussian with a uniform outlier floor per satellite


#: Most satellites one epoch uses. The update's arrays are particles x motion samples x
#: satellites, so the satellite count sets what one epoch costs (memory and time; a
#: configuration whose sizes would exceed the memory budget of ``core.config`` with this
#: many uses fewer, ``FilterConfig.satellite_limit``); an epoch with more usable
#: satellites keeps the strongest by C/N0 (unknown C/N0 last, then the order received).
#: A receiver tracking GPS, GLONASS, Galileo, BeiDou and QZSS sees 40-60 satellites under
#: open sky (one row each: rows of the same satellite are duplicates), so 64 drops nothing
#: real, and 64 well-spread satellites fix the position as well as more would.
MAX_SATELLITES = 64
#: Farthest a satellite may be from the Earth's centre [m]: GNSS orbits reach 42,164 km
#: (geostationary); beyond twice that a position is corrupt, and its square (in the range
#: arithmetic) must stay far from overflow.
MAX_SATELLITE_RADIUS_M = 1e8
#: Longest pseudorange taken [m]: geometric ranges are below 4e7 m, receiver clock offsets
#: are steered within a millisecond (3e5 m).
MAX_PSEUDORANGE_M = 1e8
#: Largest pseudorange variance taken [m^2] (a standard deviation of 1,000 km carries no
#: position information, and its inverse must not underflow in the update weights).
MAX_VARIANCE_M2 = 1e12


def epoch_problem(epoch: GnssEpoch) -> str | None:
    """Why an epoch cannot be checked at all (None when its arrays fit together): an
    integer stamp and one row per satellite in every array. Values are checked per
    satellite by :func:`check_epoch`."""
    if not isinstance(epoch.stamp_ns, (int, np.integer)) or isinstance(epoch.stamp_ns, bool):
        return f'stamp must be an integer number of nanoseconds, got {epoch.stamp_ns!r}'
    try:
        k = int(np.shape(epoch.pr_m)[0]) if np.ndim(epoch.pr_m) == 1 else -1
        shapes_ok = (k >= 0 and np.shape(epoch.sv_pos_ecef_m) == (k, 3)
                     and all(np.shape(getattr(epoch, name)) == (k,)
                             for name in ('var_m2', 'sv_id', 'system', 'elevation_deg',
                                          'cn0_dbhz')))
    except TypeError:
        shapes_ok = False
    if not shapes_ok:
        return 'the arrays of the epoch do not hold one row per satellite'
    return None


@dataclass(frozen=True)
class GnssCheck:
    """Outcome of validating one epoch.

    Attributes:
        keep: (k,) mask of the satellites that passed every check.
        rejected: ``{reason: count}`` for the satellites that did not.
        usable: Whether enough satellites remain for a position update.
        reason: Why the epoch is unusable ('' when usable).
    """

    keep: np.ndarray
    rejected: dict = field(default_factory=dict)
    usable: bool = True
    reason: str = ''


def check_epoch(epoch: GnssEpoch, min_satellites: int = 4, elevation_mask_deg: float = 0.0,
                cn0_mask_dbhz: float = 0.0, max_satellites: int = MAX_SATELLITES) -> GnssCheck:
    """Validate an epoch: non-finite or implausible values, duplicates, masks, satellite
    count.

    Satellites with a NaN elevation or C/N0 are kept (unknown is not below the mask).
    Duplicated (system, sv_id) pairs are all dropped: there is no telling which is right.
    Positions, pseudoranges and variances beyond ``MAX_SATELLITE_RADIUS_M``,
    ``MAX_PSEUDORANGE_M`` and ``MAX_VARIANCE_M2`` are dropped ('out_of_range'); of more
    than ``max_satellites`` (at most ``MAX_SATELLITES``) remaining, the strongest by C/N0
    are kept ('satellite_limit').
    """
    k = epoch.n_sv
    keep = np.ones(k, dtype=bool)
    rejected: dict[str, int] = {}

    def drop(mask: np.ndarray, reason: str) -> None:
        nonlocal keep
        hit = mask & keep
        if hit.any():
            rejected[reason] = rejected.get(reason, 0) + int(hit.sum())
            keep &= ~hit

    finite = (np.isfinite(epoch.pr_m) & np.all(np.isfinite(epoch.sv_pos_ecef_m), axis=1)
              & np.isfinite(epoch.var_m2))
    drop(~finite, 'non_finite')
    drop(finite & ((epoch.pr_m <= 0.0) | (epoch.var_m2 <= 0.0)), 'non_positive')
    with np.errstate(over='ignore', invalid='ignore'):
        radius = np.sqrt(np.einsum('ij,ij->i', epoch.sv_pos_ecef_m, epoch.sv_pos_ecef_m))
        drop(finite & ((radius > MAX_SATELLITE_RADIUS_M) | (epoch.pr_m > MAX_PSEUDORANGE_M)
                       | (epoch.var_m2 > MAX_VARIANCE_M2)), 'out_of_range')
    key = epoch.system.astype(np.int64) * 100000 + epoch.sv_id.astype(np.int64)
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    drop(counts[inverse] > 1, 'duplicate')
    with np.errstate(invalid='ignore'):
        drop(epoch.elevation_deg < elevation_mask_deg, 'elevation_mask')
        drop(epoch.cn0_dbhz < cn0_mask_dbhz, 'cn0_mask')
    n_keep = int(keep.sum())
    limit = min(int(max_satellites), MAX_SATELLITES)
    if n_keep > limit:
        # Strongest first; unknown (NaN) or absurd (infinite) C/N0 sorts last, equal ones
        # keep their order.
        cn0 = np.where(np.isfinite(epoch.cn0_dbhz), epoch.cn0_dbhz, -np.inf)
        order = np.flatnonzero(keep)[np.argsort(-cn0[keep], kind='stable')]
        over = np.zeros(k, dtype=bool)
        over[order[limit:]] = True
        drop(over, 'satellite_limit')
        n_keep = limit
    if n_keep < min_satellites:
        return GnssCheck(keep, rejected, False,
                         f'{n_keep} usable satellites, at least {min_satellites} needed')
    return GnssCheck(keep, rejected)


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
    """

    sv_enu_m: np.ndarray
    pr_m: np.ndarray
    sigma_m: np.ndarray
    sys_index: np.ndarray
    n_systems: int
    sv_key: np.ndarray
    cn0_dbhz: np.ndarray


def prepare_epoch(epoch: GnssEpoch, frame: LocalFrame, rx_enu_m: np.ndarray,
                  measurement_var_m2: float, use_reported_variance: bool) -> PreparedEpoch:
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
    """
    systems, sys_index, counts = np.unique(epoch.system, return_inverse=True,
                                           return_counts=True)
    multi = counts[sys_index] >= 2
    rx_ecef = frame.enu_to_ecef(rx_enu_m)
    sv_ecef = sagnac_corrected(epoch.sv_pos_ecef_m[multi], rx_ecef)
    var = np.full(int(multi.sum()), float(measurement_var_m2))
    if use_reported_variance:
        var = np.maximum(var, epoch.var_m2[multi])
    _, sys_index = np.unique(epoch.system[multi], return_inverse=True)
    return PreparedEpoch(sv_enu_m=frame.ecef_to_enu(sv_ecef), pr_m=epoch.pr_m[multi].copy(),
                         sigma_m=np.sqrt(var), sys_index=sys_index,
                         n_systems=int(sys_index.max()) + 1 if sys_index.size else 0,
                         sv_key=(epoch.system[multi].astype(np.int64) * 1000
                                 + epoch.sv_id[multi].astype(np.int64)),
                         cn0_dbhz=np.asarray(epoch.cn0_dbhz[multi], dtype=float))


def ranges(positions_m: np.ndarray, sv_m: np.ndarray) -> np.ndarray:
    """Geometric ranges (P, k) from (P, 3) positions to (k, 3) satellites [m].

    Uses ``|s|^2 - 2 p.s + |p|^2`` (one matrix product); in a local frame |p| is small, so
    the rounding of |s|^2 ~ 4e14 m^2 costs under a micrometre of range.
    """
    sq = positions_m @ (-2.0 * sv_m.T)
    sq += (sv_m * sv_m).sum(1)
    sq += np.einsum('ij,ij->i', positions_m, positions_m)[:, None]
    return np.sqrt(sq, out=sq)


def clock_inlier_weights(residual_m: np.ndarray, sigma_m: np.ndarray, sys_index: np.ndarray,
                         n_systems: int, spread_m: float, iterations: int = 3) -> np.ndarray:
    """Robust per-constellation clock at one reference point; returns satellite weights.

    For each constellation, every satellite's residual is a clock candidate; the one with
    the most support under a Gaussian kernel wins, then a few mean-shift steps refine it
    (a Welsch M-estimator). The kernel width is the measurement noise widened by how far
    the reference point may be from the particles (``spread_m``), so that geometry alone
    does not turn healthy satellites into outliers.

    Args:
        residual_m: (k,) pseudorange minus range at the reference point [m].
        sigma_m: (k,) measurement standard deviations [m].
        sys_index: (k,) constellation index.
        n_systems: Number of constellations.
        spread_m: Position uncertainty of the reference point [m].
        iterations: Mean-shift refinement steps.

    Returns:
        (k,) non-negative weights; within a constellation they sum to one.
    """
    width = np.sqrt(sigma_m ** 2 + spread_m ** 2)
    weights = np.zeros_like(residual_m)
    for s in range(n_systems):
        idx = np.flatnonzero(sys_index == s)
        r, h = residual_m[idx], width[idx]
        support = np.exp(-0.5 * ((r[None, :] - r[:, None]) / h[None, :]) ** 2).sum(1)
        clock = r[np.argmax(support)]
        for _ in range(iterations):
            w = np.exp(-0.5 * ((r - clock) / h) ** 2) / h ** 2
            clock = float(w @ r / w.sum())
        w = np.exp(-0.5 * ((r - clock) / h) ** 2) / h ** 2
        weights[idx] = w / w.sum()
    return weights


def clock_corrected_residuals(positions_m: np.ndarray, prep: PreparedEpoch,
                              clock_weights: np.ndarray) -> np.ndarray:
    """Residuals (P, k) after removing each particle's own per-constellation clock [m]."""
    residual = ranges(positions_m, prep.sv_enu_m)
    np.subtract(prep.pr_m, residual, out=residual)
    onehot = np.zeros((prep.pr_m.shape[0], prep.n_systems))
    onehot[np.arange(prep.pr_m.shape[0]), prep.sys_index] = clock_weights
    clock = residual @ onehot                       # (P, S): inlier-weighted mean residual
    residual -= clock[:, prep.sys_index]
    return residual


@dataclass(frozen=True)
class GnssLikelihood:
    """Per-particle GNSS log-likelihoods of M sets, with the EM mixture weights.

    Attributes:
        log_lik: (M, N) log-likelihood of each particle.
        gamma: (M, k) satellite mixture weights of each set.
    """

    log_lik: np.ndarray
    gamma: np.ndarray


def particle_raim_log_likelihood(z: np.ndarray, log_sigma: np.ndarray, prior_log_w: np.ndarray,
                                 dirichlet_alpha: float) -> GnssLikelihood:
    """The Particle RAIM mixture likelihood with weights from one EM step.

    Args:
        z: (M, N, k) normalised residuals ``e / sigma``.
        log_sigma: (k,) log standard deviations.
        prior_log_w: (N,) or (M, N) normalised prior log-weights (for MAP pooling).
        dirichlet_alpha: Dirichlet concentration (> 1 keeps every satellite possible).

    Returns:
        Log-likelihoods (M, N) and mixture weights gamma (M, k).
    """
    # E-step, squared-normal voting: a particle votes for satellite k with exp(-z^2/2),
    # normalised over satellites (a softmax, computed once with a max shift).
    a = -0.5 * z * z
    a_max = a.max(axis=-1, keepdims=True)
    e = np.exp(a - a_max)
    e_sum = e.sum(axis=-1, keepdims=True)
    votes = e / e_sum
    # M-step, MAP pooling: gamma_k = (sum_p w_p v_pk + alpha - 1) / (1 + k (alpha - 1)).
    w = np.exp(np.broadcast_to(prior_log_w, z.shape[:2]))
    pooled = np.einsum('mn,mnk->mk', w, votes)
    k = z.shape[-1]
    gamma = (pooled + dirichlet_alpha - 1.0) / (1.0 + k * (dirichlet_alpha - 1.0))
    # log sum_k gamma_k N(e_k; 0, sigma_k) = a_max + log sum_k gamma_k/sigma_k exp(a - a_max)
    scale = gamma * np.exp(-log_sigma)[None, :]
    log_lik = a_max[..., 0] + np.log(np.einsum('mnk,mk->mn', e, scale)) - LOG_SQRT_2PI
    return GnssLikelihood(log_lik=log_lik, gamma=gamma)


def robust_inlier_probability(z: np.ndarray, log_sigma: np.ndarray, outlier_prob: float,
                              outlier_range_m: float, log_w: np.ndarray) -> np.ndarray:
    """Posterior probability that each satellite is an inlier, under the robust model,
    averaged over one weighted particle set.

    Args:
        z: (N, k) normalised residuals of the set.
        log_sigma: (k,) log standard deviations.
        outlier_prob: Outlier probability eps.
        outlier_range_m: Width of the uniform outlier density [m].
        log_w: (N,) normalised log-weights.

    Returns:
        (k,) probabilities in [0, 1].
    """
    dens = np.exp(-0.5 * z * z) * ((1.0 - outlier_prob) * np.exp(-log_sigma - LOG_SQRT_2PI))
    inlier = dens / (dens + outlier_prob / outlier_range_m)
    return np.exp(log_w) @ inlier


def robust_log_likelihood(z: np.ndarray, log_sigma: np.ndarray, outlier_prob: float,
                          outlier_range_m: float, inlier_share: bool = True) -> GnssLikelihood:
    """Product over satellites of a Gaussian with a uniform outlier floor.

    ``log L = sum_k log((1 - eps) N(e_k; 0, sigma_k) + eps / range_out)``: every healthy
    satellite contributes evidence (the mixture over satellites lets the best-fitting one
    dominate), while a faulty one costs at most a constant. The floor keeps the sum away
    from zero, so the per-satellite term is evaluated directly (one exp, one log) without a
    log-sum-exp shift: an underflowing Gaussian simply leaves the floor.

    Args:
        z: (M, N, k) normalised residuals.
        log_sigma: (k,) log standard deviations.
        outlier_prob: Outlier probability eps.
        outlier_range_m: Width of the uniform outlier density [m].
        inlier_share: Also return the per-satellite inlier share (costs one more pass; the
            filter asks for it on the chosen set only).

    Returns:
        Log-likelihoods (M, N) and, as ``gamma``, the posterior inlier probability per
        satellite (M, k) averaged over particles and normalised (None when not asked for).
    """
    dens = np.square(z)
    dens *= -0.5
    np.exp(dens, out=dens)
    dens *= (1.0 - outlier_prob) * np.exp(-log_sigma - LOG_SQRT_2PI)
    floor = outlier_prob / outlier_range_m
    gamma = None
    if inlier_share:
        inlier = (dens / (dens + floor)).mean(axis=1)
        gamma = inlier / inlier.sum(axis=-1, keepdims=True)
    dens += floor
    log_lik = np.log(dens, out=dens).sum(axis=-1)
    return GnssLikelihood(log_lik=log_lik, gamma=gamma)


class Likelihood(Protocol):
    """A GNSS likelihood of the filter update, built once from the configuration
    (:func:`make_likelihood`)."""

    def log_likelihood(self, z: np.ndarray, log_sigma: np.ndarray, prior_log_w: np.ndarray
                       ) -> GnssLikelihood:
        """Per-particle log-likelihoods (M, N) of the normalised residuals ``z`` (M, N, k),
        with ``log_sigma`` (k,) and the prior log-weights (N,) or (M, N)."""

    def mixture_weights(self, lik: GnssLikelihood, z: np.ndarray, log_sigma: np.ndarray,
                        chosen: int) -> np.ndarray:
        """The (k,) satellite weights of set ``chosen`` (reported with the epoch), from
        the result ``lik`` of :meth:`log_likelihood` on the same input."""


@dataclass(frozen=True)
class ParticleRaimLikelihood:
    """The paper's mixture over satellites (:func:`particle_raim_log_likelihood`).

    Attributes:
        dirichlet_alpha: Dirichlet concentration of the EM pooling.
    """

    dirichlet_alpha: float

    @classmethod
    def from_config(cls, config) -> 'ParticleRaimLikelihood':
        return cls(dirichlet_alpha=config.dirichlet_alpha)

    def log_likelihood(self, z, log_sigma, prior_log_w) -> GnssLikelihood:
        return particle_raim_log_likelihood(z, log_sigma, prior_log_w, self.dirichlet_alpha)

    def mixture_weights(self, lik, z, log_sigma, chosen) -> np.ndarray:
        return lik.gamma[chosen]                 # the EM weights, computed for every set


@dataclass(frozen=True)
class RobustLikelihood:
    """Gaussian with a uniform outlier floor per satellite (:func:`robust_log_likelihood`).

    Attributes:
        outlier_prob: Outlier probability eps.
        outlier_range_m: Width of the uniform outlier density [m].
    """

    outlier_prob: float
    outlier_range_m: float

    @classmethod
    def from_config(cls, config) -> 'RobustLikelihood':
        return cls(outlier_prob=config.outlier_prob, outlier_range_m=config.outlier_range_m)

    def log_likelihood(self, z, log_sigma, prior_log_w) -> GnssLikelihood:
        # The inlier shares cost one more pass over all M * N particles: only the chosen
        # set's are reported (mixture_weights).
        return robust_log_likelihood(z, log_sigma, self.outlier_prob, self.outlier_range_m,
                                     inlier_share=False)

    def mixture_weights(self, lik, z, log_sigma, chosen) -> np.ndarray:
        return robust_log_likelihood(z[chosen:chosen + 1], log_sigma, self.outlier_prob,
                                     self.outlier_range_m).gamma[0]


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
