"""Independent reference implementations the tests hold the package's code against."""
import math

import numpy as np

from gnsscam_ros.core.particles import MotionIncrement
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
    from scipy.special import logsumexp

    from gnsscam_ros.core.fusion import FusionResult
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
def inverse_bernoulli_exact(q, eps, iterations: int = 64) -> np.ndarray:
    """``t >= 0`` with ``kl(q || q + t) = eps``: vectorised bisection on ``[q, 1]``."""
    from gnsscam_ros.core.integrity import bernoulli_kl
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


def integrity_epoch(posteriors, priors, mean: np.ndarray, limits: np.ndarray,
                    target: float = 0.1, delta: float = 0.1):
    """The risk bound and level of an epoch as ``ParticleFilter._integrity`` computed them
    before the kernels: pooled moments twice, Gaussian KL, float32 distances, hazard mass,
    vectorised inverse Bernoulli, scalar threshold, partitioned level."""
    from gnsscam_ros.core import integrity
    post, prior = NumpyPosteriorSet(posteriors), NumpyPosteriorSet(priors)
    kl = integrity.gaussian_kl(*post.pooled_moments(), *prior.pooled_moments())
    m = posteriors.n_posteriors
    dist_w = post.distances(mean)
    empirical = post.hazard_mass(mean, limits, dist_w)
    eps = integrity.divergence_budget(kl, m, delta)
    bound = np.minimum(empirical + inverse_bernoulli_exact(empirical, eps), 1.0)
    q_max = max_empirical_risk_exact(target, eps)
    return bound, post.protection_level(mean, q_max, dist_w)
