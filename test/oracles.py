"""Independent reference implementations the tests hold the package's code against.

The plain numpy forms of the epoch's per-particle work (the package runs compiled kernels,
``core.kernels``) are here: written for clarity, with the same arithmetic the kernels fuse.
"""
import math
from dataclasses import dataclass

import numpy as np
from scipy.special import logsumexp, rel_entr

from gnsscam_ros.core.fusion import FusionResult
from gnsscam_ros.core.bias import COV_FLOOR_M2, FORGET_AFTER_TAU
from gnsscam_ros.core.gnss import (LOG_SQRT_2PI, SINGLE_EXPANSION_TOLERANCE_M, SINGLE_MAX_OFFSET_M,
                                   PreparedEpoch)
from gnsscam_ros.core.particles import STATE_DIM, YAW, MotionIncrement
from gnsscam_ros.core.types import OdometrySeries


def integrate_odometry(odom: OdometrySeries, t0_ns: int, t1_ns: int) -> MotionIncrement:
    """Integrate speed and yaw rate over ``[t0_ns, t1_ns]`` (trapezoidal rule).

    Samples are linearly interpolated at the interval ends; outside the recorded span the
    nearest sample is held. Variances add up as for white noise on each sample period.

    Args:
        odom: Odometry series (stamps strictly increasing).
        t0_ns: Interval start [ns].
        t1_ns: Interval end [ns], not before ``t0_ns``.

    Returns:
        The motion increment (distance along the heading and heading change).
    """
    if t1_ns < t0_ns:
        raise ValueError(f'interval ends before it starts: {t0_ns} > {t1_ns}')
    dt_s = (t1_ns - t0_ns) * 1e-9
    if len(odom) == 0 or dt_s == 0.0:
        return MotionIncrement.stationary(dt_s)
    inside = (odom.stamp_ns > t0_ns) & (odom.stamp_ns < t1_ns)
    t = np.concatenate(([t0_ns], odom.stamp_ns[inside], [t1_ns])).astype(float) * 1e-9
    stamps_s = odom.stamp_ns.astype(float) * 1e-9
    speed = np.interp(t, stamps_s, odom.speed_mps)
    yaw_rate = np.interp(t, stamps_s, odom.yaw_rate_rps)
    steps = np.diff(t)
    distance = float(np.sum(0.5 * (speed[1:] + speed[:-1]) * steps))
    dyaw = float(np.sum(0.5 * (yaw_rate[1:] + yaw_rate[:-1]) * steps))
    speed_var = float(np.interp(t0_ns * 1e-9, stamps_s, odom.speed_var))
    yaw_var = float(np.interp(t0_ns * 1e-9, stamps_s, odom.yaw_rate_var))
    # Each sample's error persists for its own period: var = sigma^2 * sum(step^2)
    # (white noise per sample), an honest figure for the odometry's own quoted variances.
    sum_sq = float(np.sum(steps ** 2))
    return MotionIncrement(dt_s=dt_s, distance_m=distance, dyaw_rad=dyaw,
                           distance_var_m2=speed_var * sum_sq, dyaw_var_rad2=yaw_var * sum_sq)


# ------------------------------------------------------------- GNSS (core.kernels.gnss)
def ranges(positions_m: np.ndarray, sv_m: np.ndarray) -> np.ndarray:
    """Geometric ranges (P, k) from (P, 3) positions to (k, 3) satellites [m].

    Uses ``|s|^2 - 2 p.s + |p|^2`` (one matrix product); in a local frame |p| is small, so
    the rounding of |s|^2 ~ 4e14 m^2 costs under a micrometre of range.
    """
    sq = positions_m @ (-2.0 * sv_m.T)
    sq += (sv_m * sv_m).sum(1)
    sq += np.einsum('ij,ij->i', positions_m, positions_m)[:, None]
    return np.sqrt(sq, out=sq)


def snapshot_position(sv_enu_m: np.ndarray, pr_m: np.ndarray, sigma_m: np.ndarray,
                      sys_index: np.ndarray, n_systems: int, start_enu_m: np.ndarray,
                      plain_steps: int = 4, robust_steps: int = 5,
                      cauchy_scale: float = 2.0) -> np.ndarray | None:
    """The robust snapshot solution (``core.consistency.snapshot_position``) in numpy:
    ``plain_steps`` Gauss-Newton steps of weighted least squares, then ``robust_steps``
    of Cauchy IRLS, position and one clock per constellation, numpy's lstsq each step."""
    k = pr_m.shape[0]
    if k < 3 + n_systems + 1:
        return None
    if not (np.all(np.isfinite(start_enu_m)) and np.all(np.abs(start_enu_m) < 1e8)
            and np.all(np.isfinite(sv_enu_m)) and np.all(np.isfinite(pr_m))
            and np.all(np.isfinite(sigma_m)) and np.all(sigma_m > 0.0)):
        return None
    x = np.asarray(start_enu_m, dtype=float).copy()
    clock_cols = np.zeros((k, n_systems))
    clock_cols[np.arange(k), sys_index] = 1.0
    robust_w = np.ones(k)
    for step in range(plain_steps + robust_steps):
        offset = sv_enu_m - x
        rng = np.linalg.norm(offset, axis=1)
        jac = np.hstack([-offset / rng[:, None], clock_cols])
        resid = pr_m - rng
        w = robust_w / sigma_m
        a, b = jac * w[:, None], resid * w
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
            return None
        delta, *_ = np.linalg.lstsq(a, b, rcond=None)
        x = x + delta[:3]
        if step >= plain_steps - 1:
            post = (resid - jac @ delta) / (cauchy_scale * sigma_m)
            robust_w = 1.0 / np.sqrt(1.0 + post * post)
    return x if np.all(np.isfinite(x)) else None


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
class OracleLikelihood:
    """Per-particle GNSS log-likelihoods of M sets, with the EM mixture weights.

    Attributes:
        log_lik: (M, N) log-likelihood of each particle.
        gamma: (M, k) satellite mixture weights of each set.
    """

    log_lik: np.ndarray
    gamma: np.ndarray


def particle_raim_log_likelihood(z: np.ndarray, log_sigma: np.ndarray, prior_log_w: np.ndarray,
                                 dirichlet_alpha: float) -> OracleLikelihood:
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
    return OracleLikelihood(log_lik=log_lik, gamma=gamma)


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
                          outlier_range_m: float, inlier_share: bool = True) -> OracleLikelihood:
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
    return OracleLikelihood(log_lik=log_lik, gamma=gamma)


def mixture_densities(e: np.ndarray, core_sd: np.ndarray, wide_share: np.ndarray,
                      wide_mean: np.ndarray, wide_sd: np.ndarray, fault_share: float,
                      outlier_range_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The line-of-sight core and the whole density (..., k) of residuals e (..., k)
    under the learned error mixture, written from its definition (core.gnss.robust_terms):
    a core ``(1 - pi - eps) N(0, s0)``; an NLOS component of weight pi, flat over the
    delays ``[0, mu + 2 s1]`` with half-Gaussian ends of deviation s0 (total mass pi); a
    flat floor ``eps / range``."""
    core = ((1.0 - wide_share - fault_share) / (core_sd * np.sqrt(2.0 * np.pi))
            * np.exp(-0.5 * (e / core_sd) ** 2))
    top = wide_mean + 2.0 * wide_sd
    height = wide_share / (top + np.sqrt(2.0 * np.pi) * core_sd)
    below = np.where(e < 0.0, e, 0.0)
    above = np.where(e > top, e - top, 0.0)
    wide = height * np.exp(-0.5 * ((below + above) / core_sd) ** 2)
    return core, core + wide + fault_share / outlier_range_m


def mixture_log_likelihood(e: np.ndarray, core_sd: np.ndarray, wide_share: np.ndarray,
                           wide_mean: np.ndarray, wide_sd: np.ndarray, fault_share: float,
                           outlier_range_m: float) -> np.ndarray:
    """Log-likelihood (..., ) of residuals e (..., k) under the learned error mixture
    (:func:`mixture_densities`)."""
    return np.log(mixture_densities(e, core_sd, wide_share, wide_mean, wide_sd, fault_share,
                                    outlier_range_m)[1]).sum(axis=-1)


# ------------------------------------------- error model EM (core.kernels.mixture)
def em_step(r: np.ndarray, w: np.ndarray, cls: np.ndarray, n_classes: int,
            fit: tuple[np.ndarray, ...], prior: tuple[np.ndarray, ...],
            strength: float, min_core_sd_m: float) -> tuple[np.ndarray, ...]:
    """One MAP EM iteration of every class at once (``np.bincount`` over the classes):
    the numpy form ``core.kernels.mixture.em_fit`` replaced.

    Args:
        r: (n,) residuals [m]; w: (n,) their weights; cls: (n,) their classes.
        n_classes: Number of classes.
        fit: ``(s0, pi, mu, s1)`` per class, the current estimate.
        prior: ``(s0, pi, mu, s1)`` per class, the prior's centre.
        strength: Pseudo-samples of the prior.
        min_core_sd_m: Floor of s0 [m].
    """
    def normal_pdf_scale(sd):
        return 1.0 / (sd * np.sqrt(2.0 * np.pi))

    s0, pi, mu, s1 = (f[cls] for f in fit)
    # E-step: P(NLOS | r) = 1 / (1 + core / wide), the ratio from the log densities (it
    # stays finite where both densities underflow).
    log_ratio = (np.log((1.0 - pi) * normal_pdf_scale(s0))
                 - np.log(pi * normal_pdf_scale(s1))
                 - 0.5 * (r / s0) ** 2 + 0.5 * ((r - mu) / s1) ** 2)
    with np.errstate(over='ignore'):
        resp = 1.0 / (1.0 + np.exp(log_ratio))
    w1 = w * resp
    w0 = w - w1

    def total(values):
        return np.bincount(cls, weights=values, minlength=n_classes)

    p_s0, p_pi, p_mu, p_s1 = prior
    n0, n1 = total(w0), total(w1)
    a0, a1 = strength * (1.0 - p_pi), strength * p_pi
    new_pi = (n1 + a1) / (n0 + n1 + a0 + a1)
    new_mu = np.maximum((total(w1 * r) + a1 * p_mu) / (n1 + a1), 0.0)
    new_s0 = np.sqrt((total(w0 * r * r) + a0 * p_s0 ** 2) / (n0 + a0))
    dev = r - new_mu[cls]
    new_s1 = np.sqrt((total(w1 * dev * dev) + a1 * p_s1 ** 2) / (n1 + a1))
    new_s0 = np.maximum(new_s0, min_core_sd_m)
    new_s1 = np.maximum(new_s1, 2.0 * new_s0)
    return new_s0, new_pi, new_mu, new_s1


# --------------------------------------------------------- motion (core.kernels.motion)
def propagate(particles: np.ndarray, distance_m: np.ndarray, dyaw_rad: np.ndarray,
              dup_m: float, pos_var_m2: np.ndarray, yaw_var_rad2: float,
              noise: np.ndarray) -> np.ndarray:
    """(M, N, 4): the (N, 4) set moved by each of M motion samples along the mid-interval
    heading, with per-particle process noise (``noise``: (M, N, 4) float32 standard normal
    draws)."""
    m, n = distance_m.shape[0], particles.shape[0]
    cos_n, sin_n = np.cos(particles[:, YAW]), np.sin(particles[:, YAW])
    half = 0.5 * dyaw_rad
    step_c = (distance_m * np.cos(half))[:, None]
    step_s = (distance_m * np.sin(half))[:, None]
    out = np.empty((m, n, STATE_DIM))
    out[..., 0] = particles[None, :, 0] + step_c * cos_n - step_s * sin_n
    out[..., 1] = particles[None, :, 1] + step_c * sin_n + step_s * cos_n
    out[..., 2] = particles[None, :, 2] + dup_m
    out[..., :3] += np.sqrt(pos_var_m2) * noise[..., :3]
    # float64 noise, as the kernel computes: numpy < 2 would multiply the float32 draws by
    # the np.float64 scalar in float32 (value-based casting), numpy 2 in float64.
    out[..., YAW] = particles[None, :, YAW] + dyaw_rad[:, None] + np.sqrt(
        yaw_var_rad2) * noise[..., YAW].astype(np.float64)
    return out


def weighted_mean_cov(points: np.ndarray, log_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean (d,) and covariance (d, d) of (N, d) points, normalised log-weights."""
    w = np.exp(log_w)
    mean = w @ points
    centred = points - mean
    return mean, (centred * w[:, None]).T @ centred


def satellite_rejections(epoch, elevation_mask_deg: float = 0.0, cn0_mask_dbhz: float = 0.0,
                         max_radius_m: float = 1e8, max_pr_m: float = 1e8,
                         max_var_m2: float = 1e12) -> tuple[np.ndarray, dict]:
    """``(keep (k,), {reason: count})`` of the per-satellite checks of an epoch, in order:
    non-finite, non-positive, out of range, duplicated (system, sv_id), below a mask."""
    keep = np.ones(epoch.n_sv, dtype=bool)
    rejected: dict[str, int] = {}

    def drop(mask, reason):
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
        drop(finite & ((radius > max_radius_m) | (epoch.pr_m > max_pr_m)
                       | (epoch.var_m2 > max_var_m2)), 'out_of_range')
    key = epoch.system.astype(np.int64) * 100000 + epoch.sv_id.astype(np.int64)
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    drop(counts[inverse] > 1, 'duplicate')
    with np.errstate(invalid='ignore'):
        drop(epoch.elevation_deg < elevation_mask_deg, 'elevation_mask')
        drop(epoch.cn0_dbhz < cn0_mask_dbhz, 'cn0_mask')
    return keep, rejected


# ============================================================ camera fusion (paper §5)
# The numpy forms the compiled camera kernel replaced (``core.kernels.camera``).
def camera_log_q(positions_m: np.ndarray, match_enu_m: np.ndarray, temperature_m: float,
                 gate_m: float | None = None) -> np.ndarray:
    """Per-set log softmax of ``-distance / T`` over the particles, for one or K matches.

    The distance is Euclidean in 3D as in the paper.

    Args:
        positions_m: (M, N, 3) particle positions [m].
        match_enu_m: (3,) matched position at the epoch, or (K, 3) for K matches [m].
        temperature_m: Softmax temperature T [m].
        gate_m: Gate distance R [m]; None for the paper's plain softmax over particles.

    Returns:
        (M, N + 1) log Q with the "elsewhere" cell last, or (M, N) without a gate; with K
        matches a leading K axis. The cell weighs as much as N particles at the gate
        distance (logit ``-R / T + log N``).
    """
    pos = np.asarray(positions_m, dtype=float)[..., :3]
    match = np.asarray(match_enu_m, dtype=float)
    matches = match.reshape(-1, match.shape[-1])[:, :3]
    m, n = pos.shape[0], pos.shape[1]
    centre = pos[:, 0, :].mean(axis=0)
    flat = pos.reshape(-1, 3) - centre
    rel = matches - centre
    d2 = rel @ (-2.0 * flat.T)
    d2 += np.einsum('ij,ij->i', flat, flat)[None, :]
    d2 += np.einsum('ij,ij->i', rel, rel)[:, None]
    np.maximum(d2, 0.0, out=d2)
    logits = np.sqrt(d2, out=d2).reshape(len(matches), m, n)
    logits *= -1.0 / temperature_m
    if gate_m is not None:
        logits = np.concatenate(
            [logits, np.full(logits.shape[:-1] + (1,), -gate_m / temperature_m + np.log(n))],
            axis=-1)
    top = logits.max(axis=-1, keepdims=True)
    log_norm = top + np.log(np.exp(logits - top).sum(axis=-1, keepdims=True))
    logits -= log_norm
    return logits if match.ndim > 1 else logits[0]


def fuse_camera(log_p: np.ndarray, log_q: np.ndarray, kl_threshold_nats: float,
                elsewhere_prob: float | None = None):
    """Mixture-of-experts weights and the camera mixture for every posterior set.

    Args:
        log_p: (M, N) normalised log GNSS distribution over the particles of each set.
        log_q: (K, M, N) normalised log camera distributions, or (K, M, N + 1) with the
            "elsewhere" cell last (see :func:`camera_log_q`).
        kl_threshold_nats: Exclude the camera of a set when every KL(Q_j || P) exceeds it.
        elsewhere_prob: GNSS probability of the "elsewhere" cell (needed with that cell).

    Returns:
        ``core.fusion.FusionResult``; ``log_q_mix`` covers the N particles only.
    """
    n = log_p.shape[-1]
    if log_q.shape[-1] == n + 1:
        if elsewhere_prob is None:
            raise ValueError('log_q has an elsewhere cell: give elsewhere_prob')
        log_p = np.concatenate([log_p + np.log1p(-elsewhere_prob),
                                np.full(log_p.shape[:-1] + (1,), np.log(elsewhere_prob))],
                               axis=-1)
    elif log_q.shape[-1] != n:
        raise ValueError(f'log_q has {log_q.shape[-1]} cells for {n} particles')
    q = np.exp(log_q)
    kl = (q * (log_q - log_p[None])).sum(-1)
    k = -kl / q.sum(-1) - 1.0
    alpha = np.exp(k - logsumexp(k, axis=0, keepdims=True))
    mix = np.einsum('km,kmn->mn', alpha, q[..., :n])
    with np.errstate(divide='ignore'):
        log_q_mix = np.log(mix)
    tiny = mix < 1e-280
    if tiny.any():
        exact = logsumexp(log_q[..., :n] + np.log(np.maximum(alpha, 1e-300))[..., None],
                          axis=0)
        log_q_mix[tiny] = exact[tiny]
    excluded = kl.min(axis=0) > kl_threshold_nats
    log_q_mix[excluded] = 0.0
    return FusionResult(log_q_mix=log_q_mix, alpha=alpha, kl_nats=kl, excluded=excluded)


# ============================================================ integrity (paper §6)
# The numpy forms the compiled posterior kernels replaced (``core.kernels.posterior``).
def bernoulli_kl(q, p) -> np.ndarray:
    """``kl(q || p) = q log(q / p) + (1 - q) log((1 - q) / (1 - p))`` [nats], elementwise
    (scipy's relative entropy: 0 log 0 = 0, inf where p excludes what q allows)."""
    q, p = np.asarray(q, dtype=float), np.asarray(p, dtype=float)
    return rel_entr(q, p) + rel_entr(1.0 - q, 1.0 - p)


def _x_minus_log1p(x: np.ndarray) -> np.ndarray:
    """``x - log(1 + x)`` without cancellation for small ``|x|`` (its series there)."""
    x = np.asarray(x, dtype=float)
    small = np.abs(x) < 1e-3
    xs = np.where(small, x, 0.0)
    series = xs * xs * (0.5 - xs / 3.0 + xs * xs / 4.0 - xs ** 3 / 5.0)
    with np.errstate(divide='ignore'):
        direct = x - np.log1p(np.where(small, 0.0, x))
    return np.where(small, series, direct)


def bernoulli_kl_gap(q: float, t: float) -> float:
    """``kl(q || q + t)`` [nats], accurate also when ``t`` is far below ``q``: the linear
    terms of the two logarithms cancel exactly, leaving
    ``q g(t / q) + (1 - q) g(-t / (1 - q))`` with ``g(x) = x - log(1 + x)``."""
    if q == 0.0:
        return float(-np.log1p(-t))
    if q + t >= 1.0:
        return 0.0 if q == 1.0 else math.inf
    # q g(t / q) = t - q log((q + t) / q), by logarithms: t / q overflows for tiny q.
    first = (float(q * _x_minus_log1p(t / q)) if t < 1e-3 * q
             else t - q * (math.log(q + t) - math.log(q)))
    return first + float((1.0 - q) * _x_minus_log1p(-t / (1.0 - q)))


def inverse_bernoulli_exact(q, eps, iterations: int = 64) -> np.ndarray:
    """``t >= 0`` with ``kl(q || q + t) = eps``: vectorised bisection on ``[q, 1]``."""
    q, eps = np.broadcast_arrays(np.asarray(q, dtype=float), np.asarray(eps, dtype=float))
    lo = q.copy()
    hi = np.ones_like(q)
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        above = bernoulli_kl(q, mid) > eps
        hi = np.where(above, mid, hi)
        lo = np.where(above, lo, mid)
    return 0.5 * (lo + hi) - q


def posterior_distances(posteriors, centre_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M, N) distances of every posterior's particles from ``centre_m`` and their (M, N)
    weights, by the kernel's arithmetic: ``r = x - centre``, ``d = |r - offset_j|`` with
    the squares summed east, north (, up)."""
    dims = 2 if posteriors.horizontal else 3
    rel = posteriors.positions_m[..., :dims] - np.asarray(centre_m, dtype=float)[:dims]
    diff = rel[posteriors.motion_index] - posteriors.offsets_m[:, None, :dims]
    d2 = diff[..., 0] * diff[..., 0] + diff[..., 1] * diff[..., 1]
    if dims == 3:
        d2 = d2 + diff[..., 2] * diff[..., 2]
    return np.sqrt(d2), np.exp(posteriors.log_w[posteriors.motion_index])


def hazard_mass(dist: np.ndarray, w: np.ndarray, radii_m) -> np.ndarray:
    """Mean over the M posteriors of the mass at or beyond each radius, (A,)."""
    radii = np.atleast_1d(np.asarray(radii_m, dtype=float))
    masses = np.array([(w * (dist >= r)).sum() for r in radii]) / dist.shape[0]
    return np.clip(masses, 0.0, 1.0)


def protection_level(dist: np.ndarray, w: np.ndarray, q_max: float) -> float:
    """The smallest ``v`` in ``{0} ∪ {distances}`` whose pooled mass strictly beyond it is
    at most ``q_max`` (a full sort of the M * N distances; ties form one value)."""
    if not q_max > 0.0:
        return float('inf')
    d, w = dist.ravel(), w.ravel() / dist.shape[0]
    order = np.argsort(d, kind='stable')
    d, w = d[order], w[order]
    values, first = np.unique(d, return_index=True)
    group = np.add.reduceat(w, first)
    # beyond[i]: mass strictly beyond values[i]; candidate 0 has the mass of d > 0.
    beyond = np.concatenate((np.cumsum(group[::-1])[::-1][1:], [0.0]))
    ok = np.flatnonzero(beyond <= q_max)
    level = float(values[ok[0]])
    positive = group[values > 0.0].sum()
    return 0.0 if positive <= q_max else level


def pooled_moments(posteriors) -> tuple[np.ndarray, np.ndarray]:
    """Mean (3,) and covariance (3, 3) of the pooled (equal-share) mixture of the M
    posteriors, from the per-sample moments (einsums)."""
    w = np.exp(posteriors.log_w)
    pos = posteriors.positions_m[..., :3]
    means = np.einsum('sn,snd->sd', w, pos)
    centred = pos - means[:, None, :]
    covs = np.einsum('sn,snd,sne->sde', w, centred, centred)
    component_means = means[posteriors.motion_index] - posteriors.offsets_m
    mean = component_means.mean(axis=0)
    spread = component_means - mean
    cov = covs[posteriors.motion_index].mean(axis=0) + spread.T @ spread / len(spread)
    return mean, cov


class NumpyPosteriorSet:
    """The numpy ``PosteriorSet`` methods the kernels replaced, verbatim: float32
    distances by one small matrix product per motion sample, a partitioned sort for the
    protection level, einsum moments (``gnsscam_bench_kernels`` times them)."""

    def __init__(self, posteriors):
        self.positions_m = posteriors.positions_m
        self.log_w = np.asarray(posteriors.log_w)
        self.motion_index = posteriors.motion_index
        self.offsets_m = posteriors.offsets_m
        self.horizontal = posteriors.horizontal
        self.posteriors = posteriors

    def distances(self, centre_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distances (M, N) of every posterior's particles from ``centre_m`` and their
        weights (M, N), each row summing to one."""
        dims = 2 if self.horizontal else 3
        # Particles of posterior j sit at x - o_j, so with r = x - centre:
        # |r - o_j|^2 = |r|^2 - 2 r.o_j + |o_j|^2, one small matrix product per motion
        # sample instead of an (M, N, d) copy. Relative coordinates are small: single
        # precision is ample for the M * N result.
        rel = self.positions_m[..., :dims] - np.asarray(centre_m, dtype=float)[:dims]
        offsets = self.offsets_m[:, :dims]
        dist = np.empty((self.motion_index.shape[0], rel.shape[1]), dtype=np.float32)
        r2 = np.einsum('snd,snd->sn', rel, rel)
        o2 = np.einsum('md,md->m', offsets, offsets)
        for s in range(rel.shape[0]):
            rows = np.flatnonzero(self.motion_index == s)
            if rows.size:
                d2 = r2[s][None, :] - 2.0 * (offsets[rows] @ rel[s].T) + o2[rows][:, None]
                dist[rows] = np.sqrt(np.maximum(d2, 0.0))
        return dist, np.exp(self.log_w[self.motion_index])

    def hazard_mass(self, centre_m: np.ndarray, radii_m, dist_w: tuple | None = None
                    ) -> np.ndarray:
        """Mean over the M posteriors of the mass at or beyond each radius, (A,).

        With the estimate as centre this is the empirical risk ``R_M``; with the true
        position it is the reference risk (evaluation only). ``dist_w``: the result of
        :meth:`distances` for this centre, when already at hand.
        """
        dist, w = self.distances(centre_m) if dist_w is None else dist_w
        radii = np.atleast_1d(np.asarray(radii_m, dtype=float))
        # A is small (1-3): one weighted count per radius, no sort needed.
        masses = np.array([(w * (dist >= r)).sum() for r in radii]) / dist.shape[0]
        return np.clip(masses, 0.0, 1.0)

    def protection_level(self, centre_m: np.ndarray, q_max: float,
                         dist_w: tuple | None = None) -> float:
        """Smallest radius around ``centre_m`` with at most ``q_max`` pooled mass beyond it.

        Args:
            centre_m: (3,) the estimate [m].
            q_max: Largest admissible empirical risk (:func:`max_empirical_risk`).
            dist_w: The result of :meth:`distances` for this centre, when at hand.

        Returns:
            The radius [m]; ``inf`` when ``q_max`` is 0 and the posteriors do not all sit
            at the centre, i.e. when no radius can be certified.
        """
        if not q_max > 0.0:
            return float('inf')
        dist, w = self.distances(centre_m) if dist_w is None else dist_w
        dist, w = dist.ravel(), w.ravel() / dist.shape[0]
        # Only the far tail matters (q_max is a few per cent): partition off the farthest
        # candidates, check that they hold more than q_max, and sort just those.
        n = dist.shape[0]
        count = min(n, int(8 * q_max * n) + 256)
        while True:
            if count < n:
                part = np.argpartition(dist, n - count)[n - count:]
                d_tail, w_tail = dist[part], w[part]
                if w_tail.sum() <= q_max:     # too few (heavy weights in the tail): widen
                    count = min(n, 4 * count)
                    continue
            else:
                d_tail, w_tail = dist, w
            break
        order = np.argsort(d_tail)
        d, w = d_tail[order], w_tail[order]
        # tail[k] = mass at or beyond d[k]; R_M(r) for d[k-1] < r <= d[k] is tail[k]. The
        # level is the smallest d[k-1] whose strict tail (tail[k]) is within q_max.
        tail = np.cumsum(w[::-1])[::-1]
        k = int(np.searchsorted(-tail, -q_max, side='left'))
        return float(d[k - 1]) if k > 0 else 0.0

    def pooled_moments(self) -> tuple[np.ndarray, np.ndarray]:
        """Mean (3,) and covariance (3, 3) of the pooled (equal-share) mixture of the M
        posteriors, from the per-sample moments (no M * N copy)."""
        w = np.exp(self.log_w)
        means = np.einsum('sn,snd->sd', w, self.positions_m)
        centred = self.positions_m - means[:, None, :]
        covs = np.einsum('sn,snd,sne->sde', w, centred, centred)
        component_means = means[self.motion_index] - self.offsets_m
        mean = component_means.mean(axis=0)
        spread = component_means - mean
        cov = covs[self.motion_index].mean(axis=0) + spread.T @ spread / len(spread)
        return mean, cov


def _bernoulli_kl_scalar(q: float, p: float) -> float:
    out = q * math.log(q / p) if q > 0.0 else 0.0
    return out + ((1.0 - q) * math.log((1.0 - q) / (1.0 - p)) if q < 1.0 else 0.0)


def max_empirical_risk_exact(target: float, eps: float, iterations: int = 60) -> float:
    """The exact inverse's threshold by a Python scalar bisection."""
    if -math.log1p(-target) < eps:
        return 0.0
    lo, hi = 0.0, target
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        if _bernoulli_kl_scalar(mid, target) >= eps:
            lo = mid
        else:
            hi = mid
    return lo


def gaussian_kl(mean0, cov0, mean1, cov1, floor_m2: float = 1e-2) -> float:
    """KL(N0 || N1) [nats] = (tr(S1^-1 S0) + d^T S1^-1 d - k + log det S1 - log det S0) / 2,
    with the package's diagonal floor on both covariances; by Cholesky factors."""
    k = len(mean0)
    l0 = np.linalg.cholesky(np.asarray(cov0, float) + floor_m2 * np.eye(k))
    l1 = np.linalg.cholesky(np.asarray(cov1, float) + floor_m2 * np.eye(k))
    a = np.linalg.solve(l1, l0)                     # S1^-1 S0 has trace |L1^-1 L0|_F^2
    b = np.linalg.solve(l1, np.asarray(mean1, float) - mean0)
    log_det = 2.0 * (np.log(np.diag(l1)).sum() - np.log(np.diag(l0)).sum())
    return float(0.5 * ((a * a).sum() + b @ b - k + log_det))


def integrity_epoch(posteriors, priors, mean: np.ndarray, limits: np.ndarray,
                    target: float = 0.1, delta: float = 0.1):
    """The risk bound and level of an epoch as ``ParticleFilter._integrity`` computed them
    before the kernels: pooled moments twice, Gaussian KL, float32 distances, hazard mass,
    vectorised inverse Bernoulli, scalar threshold, partitioned level."""
    post, prior = NumpyPosteriorSet(posteriors), NumpyPosteriorSet(priors)
    kl = gaussian_kl(*post.pooled_moments(), *prior.pooled_moments())
    m = posteriors.n_posteriors
    dist_w = post.distances(mean)
    empirical = post.hazard_mass(mean, limits, dist_w)
    # The PAC-Bayes budget (paper §6): eps = (KL + log((M + 1) / delta)) / M.
    eps = (max(kl, 0.0) + math.log((m + 1) / delta)) / m
    bound = np.minimum(empirical + inverse_bernoulli_exact(empirical, eps), 1.0)
    q_max = max_empirical_risk_exact(target, eps)
    return bound, post.protection_level(mean, q_max, dist_w)


# ---------------------------------------------------- persistence (core.kernels.persistence)
def median_increment_m2(t: np.ndarray, d: np.ndarray, lag_s: float,
                        tolerance: float = 0.25) -> tuple[float, int]:
    """Median squared increment of the offsets ``d`` (n, 2) at times ``t`` (n,) about
    ``lag_s`` apart (each epoch with the nearer epoch around ``t - lag``, if earlier and
    within ``tolerance`` of the lag), and the pairs."""
    lag_ns = int(lag_s * 1e9)
    j = np.searchsorted(t, t - lag_ns)
    before = np.clip(j - 1, 0, t.shape[0] - 1)
    after = np.clip(j, 0, t.shape[0] - 1)
    target = t - lag_ns
    pick = np.where(np.abs(t[before] - target) < np.abs(t[after] - target), before, after)
    ok = ((np.abs(t[pick] - target) <= tolerance * lag_ns)
          & (pick < np.arange(t.shape[0])))
    if not ok.any():
        return float('nan'), 0
    with np.errstate(over='ignore', invalid='ignore'):
        step = d[ok] - d[pick[ok]]
        return float(np.median(np.sum(step * step, axis=1))), int(ok.sum())


# ------------------------------------- the error model's residuals (core.kernels.residuals)
def core_shares(r: np.ndarray, core_sd: np.ndarray, wide_share: np.ndarray,
                wide_mean: np.ndarray, wide_sd: np.ndarray) -> np.ndarray:
    """Each residual's probability of the line-of-sight core of its (k,) mixture."""
    def normal_pdf(x, mean, sd):
        z = (x - mean) / sd
        return np.exp(-0.5 * z * z) / (sd * np.sqrt(2.0 * np.pi))

    core = (1.0 - wide_share) * normal_pdf(r, 0.0, core_sd)
    return core / np.maximum(core + wide_share * normal_pdf(r, wide_mean, wide_sd), 1e-300)


class LaggedPairs:
    """The error model's residual pairs about ``lag_ns`` apart, from per-satellite lists:
    each satellite's stamp closest to one lag back (of two as close, the earlier) pairs
    if it is within half a lag of it; stamps older than two lags are forgotten."""

    def __init__(self, lag_ns: int):
        self.lag_ns = lag_ns
        self.history: dict[int, list[tuple[int, float]]] = {}

    def pairs(self, stamp_ns: int, keys: np.ndarray, values: np.ndarray) -> np.ndarray:
        """(p, 3) pairs of an epoch: value now, value then, their spacing [s]."""
        target, out = stamp_ns - self.lag_ns, []
        for key, value in zip(keys.tolist(), values.tolist()):
            rows = [row for row in self.history.get(key, [])
                    if row[0] >= stamp_ns - 2 * self.lag_ns]
            if rows:
                then, old = min(rows, key=lambda row: abs(row[0] - target))
                if abs(then - target) <= self.lag_ns // 2:
                    out.append((value, old, (stamp_ns - then) * 1e-9))
            self.history[key] = rows + [(stamp_ns, value)]
        return np.array(out).reshape(-1, 3)


# ---------------------------------------------------------------- bias hypotheses
def hidden_faults(biases: np.ndarray, core_sd: np.ndarray, leverage: np.ndarray,
                  core_sds: float, largest: np.ndarray) -> np.ndarray:
    """The biases (k, M) with each hypothesis's hidden fault (``core.bias``): satellite
    ``m mod k`` of hypothesis m by ``+-min(c s / sqrt(1 - h), largest)``, the sign
    alternating with each round over the satellites."""
    k, m = biases.shape
    sizes = np.minimum(core_sds * core_sd / np.sqrt(np.maximum(1.0 - leverage, 1e-12)),
                       largest)
    which = np.arange(m)
    sign = np.where((which // k) % 2 == 0, 1.0, -1.0)
    out = biases.copy()
    out[which % k, which] += sign * sizes[which % k]
    return out


class GaussMarkovBiases:
    """The hypotheses' per-satellite Gauss-Markov biases (``BiasHypotheses.biases_at``)
    as a dictionary of rows, numpy's arithmetic on the epoch's satellites at once."""

    def __init__(self, m: int, rng: np.random.Generator):
        self.m, self.rng, self.biases = m, rng, {}

    def step(self, stamp_ns: int, keys: np.ndarray, sigma: np.ndarray, tau: float
             ) -> np.ndarray:
        draws = self.rng.standard_normal((keys.shape[0], self.m))
        known = [self.biases.get(key) for key in keys.tolist()]
        seen = np.array([k is not None for k in known], dtype=bool)
        then = np.array([k[0] if k is not None else stamp_ns for k in known], dtype=np.int64)
        previous = np.array([k[1] if k is not None else np.zeros(self.m) for k in known])
        dt_s = (stamp_ns - then) * 1e-9
        phi = np.exp(-np.maximum(dt_s, 0.0) / tau) if tau > 0 else np.zeros_like(dt_s)
        phi = np.where(~seen, 0.0, np.where(dt_s <= 0.0, 1.0, phi))
        out = (phi[:, None] * previous.reshape(-1, self.m)
               + (np.sqrt(1.0 - phi * phi) * sigma)[:, None] * draws)
        for key, row in zip(keys.tolist(), out.copy()):
            self.biases[key] = (stamp_ns, row)
        horizon = stamp_ns - int(FORGET_AFTER_TAU * tau * 1e9)
        self.biases = {k: v for k, v in self.biases.items() if v[0] >= horizon}
        return out


def projected_weights(weights: np.ndarray, sys_index: np.ndarray, n_systems: int
                      ) -> np.ndarray:
    """``Wp = W - W S (S^T W S)^-1 S^T W``: the weight matrix with each constellation's
    clock profiled out (k, k), for diagonal ``W = diag(weights)``."""
    onehot = np.zeros((weights.shape[0], n_systems))
    onehot[np.arange(weights.shape[0]), sys_index] = 1.0
    ws = weights[:, None] * onehot                          # W S (k, S)
    per_system = np.maximum(np.bincount(sys_index, weights, minlength=n_systems),
                            1e-300)                      # diag(S^T W S)
    return np.diag(weights) - (ws / per_system) @ ws.T


def bias_leverages(line_of_sight: np.ndarray, weights: np.ndarray,
                   sys_index: np.ndarray, n_systems: int) -> np.ndarray:
    """Diagonal of the weighted least-squares hat matrix, position and one clock per
    constellation estimated: ``h_k``, the share of satellite k's own bias that the
    estimate absorbs, (k,) in [0, 1] (``core.bias.leverages``)."""
    k = line_of_sight.shape[0]
    onehot = np.zeros((k, n_systems))
    onehot[np.arange(k), sys_index] = 1.0
    design = np.hstack([-line_of_sight, onehot])
    cov = np.linalg.pinv(design.T @ (weights[:, None] * design))
    return np.clip(np.einsum('ij,jk,ik->i', design, cov, design) * weights, 0.0, 1.0)


def bias_beyond_cloud(offsets_m: np.ndarray, fault_offsets_m: np.ndarray,
                      cloud_cov_m2: np.ndarray, dims: int) -> np.ndarray:
    """``core.bias.beyond_cloud`` (numpy, BLAS products)."""
    offsets = np.asarray(offsets_m, dtype=float)
    faults = np.asarray(fault_offsets_m, dtype=float)
    gm = (offsets - faults)[:, :dims]
    moment = gm.T @ gm / max(gm.shape[0], 1)
    values, vectors = np.linalg.eigh(moment)
    if not values[-1] > 0.0:
        return offsets.copy()                       # no Gauss-Markov part to shrink
    # O^(-1/2) on the span of the offsets (a direction they never take stays at zero).
    floor = values[-1] * 1e-12
    inv_sqrt = (vectors * np.where(values > floor, 1.0 / np.sqrt(np.maximum(values, floor)),
                                   0.0)) @ vectors.T
    excess = _psd_part(moment - np.asarray(cloud_cov_m2, dtype=float)[:dims, :dims])
    ex_values, ex_vectors = np.linalg.eigh(excess)
    ex_sqrt = (ex_vectors * np.sqrt(np.maximum(ex_values, 0.0))) @ ex_vectors.T
    out = offsets.copy()
    out[:, :dims] = faults[:, :dims] + gm @ (ex_sqrt @ inv_sqrt).T
    return out


def _information(cov_m2: np.ndarray) -> np.ndarray:
    return np.linalg.inv(cov_m2 + COV_FLOOR_M2 * np.eye(cov_m2.shape[0]))


def _psd_part(matrix: np.ndarray) -> np.ndarray:
    values, vectors = np.linalg.eigh(0.5 * (matrix + matrix.T))
    return (vectors * np.maximum(values, 0.0)) @ vectors.T


def bias_update(offsets_m, fault_offsets_m, biases_m, line_of_sight, weights, sys_index,
                n_systems, prior_cov_m2, posterior_cov_m2, fault_biases_m=None):
    """``BiasHypotheses.update``'s offsets and fault offsets (numpy, BLAS products)."""
    prior_info = _information(prior_cov_m2)
    gained = _psd_part(_information(posterior_cov_m2) - prior_info)
    cov = np.linalg.inv(prior_info + gained)
    wp = projected_weights(weights, sys_index, n_systems)
    gain = -line_of_sight.T @ wp                        # G^T Wp, G = -line of sight
    offsets_m = (offsets_m @ prior_info + (gain @ biases_m).T) @ cov
    moved = fault_offsets_m @ prior_info
    if fault_biases_m is not None:
        moved = moved + (gain @ fault_biases_m).T
    fault_offsets_m = moved @ cov
    return offsets_m, fault_offsets_m


# ---------------------------------------------------------------- float32 likelihood views
def relative_geometry(sets: np.ndarray, prep: PreparedEpoch, clock_weights: np.ndarray):
    """One view of ``core.gnss.relative_geometry`` (numpy): ``(centre, unit, base,
    half_inv_range, max_offset)`` from the centre of every 32nd particle of the sets, or
    None for a centre that is not finite."""
    step = max(1, sets.shape[1] // 32)
    centre = sets[:, ::step, :3].reshape(-1, 3).mean(axis=0)
    if not np.all(np.isfinite(centre)):
        return None
    offset = prep.sv_enu_m - centre
    rho0 = np.sqrt(np.einsum('ij,ij->i', offset, offset))
    unit = offset / rho0[:, None]
    base = prep.pr_m - rho0
    clock0 = np.bincount(prep.sys_index, weights=clock_weights * base,
                         minlength=prep.n_systems)
    base = base - clock0[prep.sys_index]
    expansion = np.cbrt(2.0 * SINGLE_EXPANSION_TOLERANCE_M * float(rho0.min()) ** 2)
    return centre, unit, base, 0.5 / rho0, float(min(SINGLE_MAX_OFFSET_M, expansion))
