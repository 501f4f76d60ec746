"""Integrity risk bound (paper §6, from Particle RAIM), protection level and reference risk.

``bound = R_M + D_Ber^-1(R_M, eps)`` with ``eps = (KL(pi_t || pi_t-1) + log((M+1)/delta)) / M``:
``R_M`` is the empirical risk over the M posteriors (the mass of each posterior beyond the
alert limit from the estimate), the KL divergence is between Gaussian approximations of the
posterior and the prior, and ``D_Ber^-1(q, eps)`` is the ``t`` with ``kl(q || q + t) = eps``.

Protection level. With ``R_M(r)`` the empirical risk at radius ``r``, the bound
``B(r) = R_M(r) + D_Ber^-1(R_M(r), eps)`` is non-increasing in ``r``: ``R_M(r)`` (a tail
mass) is, and ``q + D_Ber^-1(q, eps)`` grows with ``q`` (the upper confidence limit of a
larger empirical risk is larger). So ``B(r) <= target`` exactly when ``R_M(r) <= q_max``,
where ``q_max`` is the largest empirical risk whose bound is still the target
(:func:`max_empirical_risk`, one scalar bisection), and the protection level, the smallest
``r`` with ``B(r) <= target``, is the radius beyond which at most ``q_max`` of the pooled
posterior mass lies: a weighted quantile of the pooled distances
(:meth:`PosteriorSet.risk_and_level`: a weighted histogram of the M * N distances finds
the crossing, only the particles of that bin are sorted). With the exact
inverse ``q_max`` is 0 when ``eps >= -log(1 - target)`` (even an empirical risk of 0 has a
bound ``1 - exp(-eps)`` above the target): no radius certifies and the level is infinite.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Protocol

import numpy as np

from .kernels import posterior as posterior_kernels

# Inverses of the Bernoulli KL: the values of the ``inverse_bernoulli`` parameter, each
# the name of one :class:`InverseBernoulli` (``INVERSE_BERNOULLI``).
EXACT = 'exact'
APPROX = 'approx'


def bernoulli_kl(q: np.ndarray, p: np.ndarray) -> np.ndarray:
    """KL divergence between Bernoulli(q) and Bernoulli(p), elementwise [nats]."""
    q = np.asarray(q, dtype=float)
    p = np.clip(np.asarray(p, dtype=float), 1e-300, 1.0 - 1e-16)
    with np.errstate(divide='ignore', invalid='ignore'):
        a = np.where(q > 0.0, q * np.log(q / p), 0.0)
        b = np.where(q < 1.0, (1.0 - q) * np.log((1.0 - q) / (1.0 - p)), 0.0)
    return a + b


def inverse_bernoulli_exact(q, eps, iterations: int = 64) -> np.ndarray:
    """``t >= 0`` with ``kl(q || q + t) = eps``, by bisection on ``[q, 1]``.

    ``kl(q || p)`` increases with ``p`` on ``[q, 1)`` and diverges at 1, so the root is
    unique; 64 halvings reach double precision. A compiled scalar bisection per element
    (``core.kernels.posterior.bernoulli_gap``): the epoch's arrays hold 1-3 values.

    Args:
        q: Empirical risk(s) in [0, 1].
        eps: Divergence budget(s) >= 0 [nats].

    Returns:
        The gap(s) t, so that ``q + t`` is the upper confidence bound on the risk.
    """
    q, eps = np.asarray(q, dtype=float), np.asarray(eps, dtype=float)
    shape = q.shape if eps.ndim == 0 else np.broadcast_shapes(q.shape, eps.shape)
    out = np.empty(shape)
    posterior_kernels.bernoulli_gap(_flat(q, shape), _flat(eps, shape if eps.ndim else ()),
                                    int(iterations), out.reshape(-1))
    return out if shape else out[()]


def _flat(values: np.ndarray, shape: tuple) -> np.ndarray:
    """``values`` broadcast to ``shape`` as a writable contiguous 1-D array (a view when it
    already is one): one kernel signature for every caller."""
    if values.shape == shape and values.flags.c_contiguous and values.flags.writeable:
        return values.reshape(-1)
    return np.array(np.broadcast_to(values, shape)).reshape(-1)


def inverse_bernoulli_approx(q, eps) -> np.ndarray:
    """The paper's closed form ``sqrt(2 eps / (1/q + 1/(1-q)))`` = ``sqrt(2 eps q (1-q))``.

    It is the second-order expansion of the Bernoulli KL around q; it is exactly 0 at
    ``q = 0`` (and 1), so it adds no margin when no posterior mass is hazardous.
    """
    q = np.asarray(q, dtype=float)
    return np.sqrt(2.0 * np.asarray(eps, dtype=float) * q * (1.0 - q))


class InverseBernoulli(Protocol):
    """One way of inverting the Bernoulli KL: the bound's margin and its protection-level
    threshold (the values of the ``inverse_bernoulli`` parameter name them,
    ``INVERSE_BERNOULLI``)."""

    def gap(self, q, eps) -> np.ndarray:
        """``D_Ber^-1(q, eps)``: the margin added to the empirical risk(s) ``q``."""

    def max_empirical_risk(self, target: float, eps: float) -> float:
        """Largest ``q`` whose bound ``q + gap(q, eps)`` is at most ``target``
        (:func:`max_empirical_risk`), for ``eps >= 0``."""


@dataclass(frozen=True)
class ExactInverse:
    """The exact inverse, by bisection.

    Attributes:
        iterations: Halvings of the threshold's scalar bisection (60 reach double
            precision; the margin, :func:`inverse_bernoulli_exact`, always takes 64).
    """

    iterations: int = 60

    def gap(self, q, eps) -> np.ndarray:
        return inverse_bernoulli_exact(q, eps)

    def max_empirical_risk(self, target: float, eps: float) -> float:
        # The bound is at most the target exactly when kl(q || target) >= eps (see
        # max_empirical_risk), and kl(q || target) falls as q rises to the target.
        return float(posterior_kernels.max_empirical_risk(float(target), float(eps),
                                                          int(self.iterations)))


@dataclass(frozen=True)
class ApproxInverse:
    """The paper's closed form (:func:`inverse_bernoulli_approx`); reproduction only."""

    def gap(self, q, eps) -> np.ndarray:
        return inverse_bernoulli_approx(q, eps)

    def max_empirical_risk(self, target: float, eps: float) -> float:
        # q + sqrt(2 eps q (1 - q)) = t is (1 + 2 eps) q^2 - 2 (t + eps) q + t^2 = 0.
        t = target
        a, b = 1.0 + 2.0 * eps, t + eps
        return float(min(max((b - math.sqrt(max(b * b - a * t * t, 0.0))) / a, 0.0), t))


#: The inverse each value of the ``inverse_bernoulli`` parameter names.
INVERSE_BERNOULLI = {EXACT: ExactInverse(), APPROX: ApproxInverse()}
INVERSE_METHODS = tuple(INVERSE_BERNOULLI)


def inverse_method(method: str) -> InverseBernoulli:
    """The inverse named ``method`` ('exact' or 'approx').

    Raises:
        ValueError: An unknown name.
    """
    inverse = INVERSE_BERNOULLI.get(method)
    if inverse is None:
        raise ValueError(f'unknown inverse Bernoulli method {method!r}; use {INVERSE_METHODS}')
    return inverse


def inverse_bernoulli(q, eps, method: str = EXACT) -> np.ndarray:
    """``D_Ber^-1(q, eps)`` by the named method ('exact' or 'approx')."""
    return inverse_method(method).gap(q, eps)


def upper_risk(q, eps, method: str = EXACT) -> np.ndarray:
    """The bound ``q + D_Ber^-1(q, eps)`` for the given inverse, clipped to 1."""
    return np.minimum(np.asarray(q, dtype=float) + inverse_bernoulli(q, eps, method), 1.0)


def max_empirical_risk(target: float, eps: float, method: str = EXACT,
                       iterations: int = 60) -> float:
    """Largest empirical risk ``q`` whose bound ``q + D_Ber^-1(q, eps)`` is at most ``target``.

    Exact inverse: the bound of ``q`` is the ``p >= q`` with ``kl(q || p) = eps``, and
    ``kl(q || p)`` grows with ``p``, so the bound is at most ``target`` exactly when
    ``kl(q || target) >= eps``; ``kl(q || target)`` falls as ``q`` rises to ``target``, so
    ``q_max`` is the root of ``kl(q || target) = eps`` on ``[0, target]`` (scalar bisection,
    60 halvings reach double precision), or 0 when ``kl(0 || target) = -log(1 - target)``
    is already below ``eps``. Paper approximation: ``q + sqrt(2 eps q (1 - q)) = target``
    is a quadratic in ``q``; its smaller root.

    Args:
        target: Target risk in (0, 1).
        eps: Divergence budget [nats], >= 0.
        method: 'exact' or 'approx'.
        iterations: Bisection halvings of the exact inverse.

    Returns:
        ``q_max`` in [0, target]; 0 when even ``q = 0`` is bounded above the target.
    """
    inverse = inverse_method(method)
    if iterations != ExactInverse.iterations and isinstance(inverse, ExactInverse):
        inverse = ExactInverse(iterations)
    return inverse.max_empirical_risk(float(target), max(float(eps), 0.0))


def divergence_budget(kl_nats: float, n_posteriors: int, delta: float) -> float:
    """``eps = (KL + log((M + 1) / delta)) / M`` [nats] (paper §6)."""
    return (max(float(kl_nats), 0.0) + math.log((n_posteriors + 1) / delta)) / n_posteriors


def certifiable_target(n_posteriors: int, delta: float, kl_nats: float = 0.0) -> float:
    """Smallest target risk the exact bound can ever meet: ``1 - exp(-eps)`` (at R_M = 0)."""
    return float(1.0 - np.exp(-divergence_budget(kl_nats, n_posteriors, delta)))


def gaussian_kl(mean0: np.ndarray, cov0: np.ndarray, mean1: np.ndarray, cov1: np.ndarray,
                floor_m2: float = 1e-2) -> float:
    """KL(N0 || N1) between two d-dimensional Gaussians [nats].

    A diagonal floor keeps collapsed particle sets (after resampling) from giving a
    singular covariance.
    """
    d = mean0.shape[0]
    c0 = cov0 + floor_m2 * np.eye(d)
    c1 = cov1 + floor_m2 * np.eye(d)
    c1_inv = np.linalg.inv(c1)
    diff = mean1 - mean0
    _, logdet0 = np.linalg.slogdet(c0)
    _, logdet1 = np.linalg.slogdet(c1)
    return float(0.5 * (np.trace(c1_inv @ c0) + diff @ c1_inv @ diff - d + logdet1 - logdet0))


def hazard_mass(positions_m: np.ndarray, log_w: np.ndarray, centre_m: np.ndarray,
                alert_limits_m: np.ndarray, horizontal: bool = True) -> np.ndarray:
    """Mean over M sets of the weighted mass at or beyond each alert limit from a centre.

    With the estimate as centre this is the empirical risk ``R_M``; with the true position it
    is the reference risk ``E_{x~pi} P(||x - x*|| >= r)`` (evaluation only).

    Args:
        positions_m: (M, N, 3) particle positions [m].
        log_w: (M, N) normalised log-weights.
        centre_m: (3,) centre [m].
        alert_limits_m: (A,) alert limits [m].
        horizontal: Measure horizontal (east-north) distance; else 3D.

    Returns:
        (A,) risks in [0, 1].
    """
    dims = 2 if horizontal else 3
    diff = positions_m[..., :dims] - centre_m[:dims]
    dist = np.sqrt((diff * diff).sum(-1))
    w = np.exp(log_w)
    limits = np.atleast_1d(np.asarray(alert_limits_m, dtype=float))
    # One weighted count per limit; A is small (1-3), so no sort is needed.
    risks = np.stack([(w * (dist >= limit)).sum(axis=1) for limit in limits], axis=1)
    return np.clip(risks.mean(axis=0), 0.0, 1.0)


@dataclass(frozen=True)
class RiskBound:
    """Integrity risk of one epoch for each alert limit.

    Attributes:
        alert_limits_m: (A,) alert limits [m].
        empirical_risk: (A,) R_M.
        divergence_risk: (A,) D_Ber^-1(R_M, eps).
        risk_bound: (A,) empirical + divergence, clipped to 1.
        kl_nats: KL divergence between posterior and prior approximations.
        epsilon: The divergence budget eps.
    """

    alert_limits_m: np.ndarray
    empirical_risk: np.ndarray
    divergence_risk: np.ndarray
    risk_bound: np.ndarray
    kl_nats: float
    epsilon: float


def risk_bound(empirical: np.ndarray, kl_nats: float, n_posteriors: int, delta: float,
               method: str = EXACT, alert_limits_m: np.ndarray | None = None) -> RiskBound:
    """PAC-Bayes bound on the integrity risk (paper eq. for R(pi^t)).

    Args:
        empirical: (A,) empirical risks R_M.
        kl_nats: KL(pi_t || pi_t-1) >= 0.
        n_posteriors: M, the number of posteriors behind the empirical risk.
        delta: Confidence parameter in (0, 1].
        method: 'exact' (bisection) or 'approx' (the paper's closed form).
        alert_limits_m: (A,) limits, carried along for reporting.
    """
    empirical = np.asarray(empirical, dtype=float)
    eps = divergence_budget(kl_nats, n_posteriors, delta)
    divergence = inverse_bernoulli(empirical, eps, method)
    limits = np.full(empirical.shape, np.nan) if alert_limits_m is None else np.asarray(
        alert_limits_m, dtype=float)
    return RiskBound(alert_limits_m=limits, empirical_risk=empirical,
                     divergence_risk=divergence,
                     risk_bound=np.minimum(empirical + divergence, 1.0), kl_nats=kl_nats,
                     epsilon=float(eps))


def _vector3(value) -> np.ndarray:
    """A (3,) contiguous float64 copy or view (one kernel signature for every caller)."""
    return np.ascontiguousarray(np.asarray(value, dtype=float).reshape(-1)[:3])


@dataclass(frozen=True)
class PosteriorSet:
    """The M posteriors of one epoch, as the risk bound sees them.

    Posterior ``j`` is the particle set of motion sample ``motion_index[j]`` with its
    weights, displaced by ``-offsets_m[j]``: the error its bias hypothesis would have put
    into the estimate (``core.bias``), so the set says where the true position may lie
    relative to the estimate. Without bias hypotheses every offset is zero and each
    posterior has its own motion sample (the paper's construction). Positions are shared
    across posteriors of the same motion sample, so the M * N particles are never copied.

    Attributes:
        positions_m: (S, N, 3) particle positions of the S motion samples [m].
        log_w: (S, N) normalised log-weights, or (1, N): one row for every sample (the
            priors').
        motion_index: (M,) motion sample of each posterior.
        offsets_m: (M, 3) estimate error of each posterior's hypothesis [m].
        horizontal: Measure horizontal (east-north) distance; else 3D.
    """

    positions_m: np.ndarray
    log_w: np.ndarray
    motion_index: np.ndarray
    offsets_m: np.ndarray
    horizontal: bool = True

    @property
    def n_posteriors(self) -> int:
        return int(self.motion_index.shape[0])

    @cached_property
    def weights(self) -> np.ndarray:
        """Linear weights ``exp(log_w)``: (S, N), or (1, N) when every sample has the
        same row (``log_w`` one row, or broadcast from one, as the priors are)."""
        log_w = np.asarray(self.log_w, dtype=float)
        if log_w.shape[0] > 1 and log_w.strides[0] == 0:
            log_w = log_w[:1]
        if not log_w.flags.writeable:
            log_w = log_w.copy()          # a read-only view would be another signature
        out = np.empty(log_w.shape)
        posterior_kernels.exp_weights(log_w, out)
        return out

    def _xyz(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """East, north, up as (S, N) strided views: one kernel signature whatever the
        layout of ``positions_m``."""
        pos = self.positions_m
        return pos[..., 0], pos[..., 1], pos[..., 2]

    def _index(self) -> np.ndarray:
        return np.asarray(self.motion_index, dtype=np.int64)

    def _offsets(self) -> np.ndarray:
        return np.ascontiguousarray(self.offsets_m, dtype=float)

    def _dims(self) -> int:
        return 2 if self.horizontal else 3

    def distances(self, centre_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distances (M, N) of every posterior's particles from ``centre_m`` and their
        weights (M, N), each row summing to one.

        Particles of posterior j sit at ``x - o_j``: with ``r = x - centre`` the distance
        is ``|r - o_j|`` (horizontal or 3D), the arithmetic of :meth:`risk_and_level`.
        """
        out = np.empty((self.n_posteriors, self.positions_m.shape[1]))
        posterior_kernels.distances(*self._xyz(), self._index(), self._offsets(),
                                    _vector3(centre_m), self._dims(), out)
        w = self.weights
        return out, (w[self.motion_index] if w.shape[0] > 1
                     else np.repeat(w, self.n_posteriors, axis=0))

    def risk_and_level(self, centre_m: np.ndarray, radii_m, q_max: float
                       ) -> tuple[np.ndarray, float]:
        """Hazard masses at ``radii_m`` and the protection level for ``q_max``, in one
        compiled pass over the M * N posterior particles.

        Args:
            centre_m: (3,) the estimate (or, for the reference risk, the truth) [m].
            radii_m: (A,) alert radii [m].
            q_max: Largest admissible empirical risk (:func:`max_empirical_risk`).

        Returns:
            ``(masses, level)``: (A,) the mean over the posteriors of the mass at or beyond
            each radius (the empirical risk ``R_M``), and the smallest ``v`` in
            ``{0} ∪ {distances}`` with at most ``q_max`` of the pooled mass strictly beyond
            it [m]; inf when ``q_max`` is 0 (no radius can be certified).
        """
        radii = np.ascontiguousarray(radii_m, dtype=float).reshape(-1)
        masses = np.empty(radii.shape[0])
        want = bool(q_max > 0.0)
        level = posterior_kernels.hazard_and_level(
            *self._xyz(), self.weights, self._index(), self._offsets(),
            _vector3(centre_m), self._dims(), radii,
            float(q_max) * self.n_posteriors if want else 0.0, want, masses)
        return masses, float(level)

    def hazard_mass(self, centre_m: np.ndarray, radii_m, dist_w: tuple | None = None
                    ) -> np.ndarray:
        """Mean over the M posteriors of the mass at or beyond each radius, (A,).

        With the estimate as centre this is the empirical risk ``R_M``; with the true
        position it is the reference risk (evaluation only). ``dist_w``: the result of
        :meth:`distances` for this centre, when already at hand.
        """
        if dist_w is None:
            return self.risk_and_level(centre_m, radii_m, 0.0)[0]
        dist, w = dist_w
        radii = np.atleast_1d(np.asarray(radii_m, dtype=float))
        masses = np.array([(w * (dist >= r)).sum() for r in radii]) / dist.shape[0]
        return np.clip(masses, 0.0, 1.0)

    def protection_level(self, centre_m: np.ndarray, q_max: float,
                         dist_w: tuple | None = None) -> float:
        """Smallest radius around ``centre_m`` with at most ``q_max`` pooled mass beyond it.

        The level is the smallest ``v`` in ``{0} ∪ {distances}`` whose pooled mass
        strictly beyond ``v`` is at most ``q_max``: a value, so tied distances (frequent
        after resampling) give the same level in any order.

        Args:
            centre_m: (3,) the estimate [m].
            q_max: Largest admissible empirical risk (:func:`max_empirical_risk`).
            dist_w: The result of :meth:`distances` for this centre, when at hand.

        Returns:
            The radius [m]; ``inf`` when ``q_max`` is 0, i.e. when no radius can be
            certified.
        """
        if not q_max > 0.0:
            return float('inf')
        if dist_w is None:
            return self.risk_and_level(centre_m, np.zeros(0), q_max)[1]
        dist, w = (np.ascontiguousarray(a, dtype=float) for a in dist_w)
        return float(posterior_kernels.tail_level(
            dist, w, np.arange(dist.shape[0], dtype=np.int64), float(q_max) * dist.shape[0],
            -1.0))

    def pooled_moments(self) -> tuple[np.ndarray, np.ndarray]:
        """Mean (3,) and covariance (3, 3) of the pooled (equal-share) mixture of the M
        posteriors, from the per-sample moments (one compiled pass, no M * N copy)."""
        mean, cov, _, _, _ = posterior_kernels.pooled_moments(
            *self._xyz(), self.weights, self._index(), self._offsets(), self.weights,
            self._index(), self._offsets(), False, 0.0)
        return mean, cov

    def divergence_from(self, priors: 'PosteriorSet', floor_m2: float = 1e-2) -> float:
        """KL(N_post || N_prior) [nats] between Gaussian fits of the pooled mixtures of
        these posteriors and of ``priors`` (:func:`gaussian_kl` with ``floor_m2``).

        When ``priors`` holds the same particles (other weights and offsets), both sets of
        moments come from one compiled pass.
        """
        if priors.positions_m is not self.positions_m:
            return gaussian_kl(*self.pooled_moments(), *priors.pooled_moments(), floor_m2)
        *_, kl = posterior_kernels.pooled_moments(
            *self._xyz(), self.weights, self._index(), self._offsets(), priors.weights,
            priors._index(), priors._offsets(), True, float(floor_m2))
        return float(kl)
