"""Independent reference implementations the tests hold the package's code against.

The plain numpy forms of the epoch's per-particle work (the package runs compiled kernels,
``core.kernels``) are here: written for clarity, with the same arithmetic the kernels fuse.
"""
from dataclasses import dataclass

import numpy as np

from gnsscam_ros.core.gnss import LOG_SQRT_2PI, PreparedEpoch
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


# --------------------------------------------------------- motion (core.kernels.motion)
def propagate(particles: np.ndarray, distance_m: np.ndarray, dyaw_rad: np.ndarray,
              dup_m: float, pos_var_m2: np.ndarray, yaw_var_rad2: float,
              rng: np.random.Generator) -> np.ndarray:
    """(M, N, 4): the (N, 4) set moved by each of M motion samples along the mid-interval
    heading, with per-particle process noise (float32 standard normal draws)."""
    m, n = distance_m.shape[0], particles.shape[0]
    noise = rng.standard_normal((m, n, STATE_DIM), dtype=np.float32)
    cos_n, sin_n = np.cos(particles[:, YAW]), np.sin(particles[:, YAW])
    half = 0.5 * dyaw_rad
    step_c = (distance_m * np.cos(half))[:, None]
    step_s = (distance_m * np.sin(half))[:, None]
    out = np.empty((m, n, STATE_DIM))
    out[..., 0] = particles[None, :, 0] + step_c * cos_n - step_s * sin_n
    out[..., 1] = particles[None, :, 1] + step_c * sin_n + step_s * cos_n
    out[..., 2] = particles[None, :, 2] + dup_m
    out[..., :3] += np.sqrt(pos_var_m2) * noise[..., :3]
    out[..., YAW] = particles[None, :, YAW] + dyaw_rad[:, None] + np.sqrt(
        yaw_var_rad2) * noise[..., YAW]
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
