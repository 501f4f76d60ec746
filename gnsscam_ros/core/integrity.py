"""Integrity risk bound (paper §6, from Particle RAIM), reference risk and the flag.

``bound = R_M + D_Ber^-1(R_M, eps)`` with ``eps = (KL(pi_t || pi_t-1) + log((M+1)/delta)) / M``:
``R_M`` is the empirical risk over the M posteriors (the mass of each posterior beyond the
alert limit from the estimate), the KL divergence is between Gaussian approximations of the
posterior and the prior, and ``D_Ber^-1(q, eps)`` is the ``t`` with ``kl(q || q + t) = eps``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

EXACT = 'exact'
APPROX = 'approx'
INVERSE_METHODS = (EXACT, APPROX)


def bernoulli_kl(q: np.ndarray, p: np.ndarray) -> np.ndarray:
    """KL divergence between Bernoulli(q) and Bernoulli(p), elementwise [nats]."""
    q = np.asarray(q, dtype=float)
    p = np.clip(np.asarray(p, dtype=float), 1e-300, 1.0 - 1e-16)
    with np.errstate(divide='ignore', invalid='ignore'):
        a = np.where(q > 0.0, q * np.log(q / p), 0.0)
        b = np.where(q < 1.0, (1.0 - q) * np.log((1.0 - q) / (1.0 - p)), 0.0)
    return a + b


def inverse_bernoulli_exact(q, eps, iterations: int = 64) -> np.ndarray:
    """``t >= 0`` with ``kl(q || q + t) = eps``, by bisection on ``[q, 1]`` (vectorised).

    ``kl(q || p)`` increases with ``p`` on ``[q, 1)`` and diverges at 1, so the root is
    unique; 64 halvings reach double precision.

    Args:
        q: Empirical risk(s) in [0, 1].
        eps: Divergence budget(s) >= 0 [nats].

    Returns:
        The gap(s) t, so that ``q + t`` is the upper confidence bound on the risk.
    """
    q, eps = np.broadcast_arrays(np.asarray(q, dtype=float), np.asarray(eps, dtype=float))
    lo = q.copy()
    hi = np.ones_like(q)
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        above = bernoulli_kl(q, mid) > eps
        hi = np.where(above, mid, hi)
        lo = np.where(above, lo, mid)
    return 0.5 * (lo + hi) - q


def inverse_bernoulli_approx(q, eps) -> np.ndarray:
    """The paper's closed form ``sqrt(2 eps / (1/q + 1/(1-q)))`` = ``sqrt(2 eps q (1-q))``.

    It is the second-order expansion of the Bernoulli KL around q; it is exactly 0 at
    ``q = 0`` (and 1), so it adds no margin when no posterior mass is hazardous.
    """
    q = np.asarray(q, dtype=float)
    return np.sqrt(2.0 * np.asarray(eps, dtype=float) * q * (1.0 - q))


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
        n_posteriors: M, the number of motion samples.
        delta: Confidence parameter in (0, 1].
        method: 'exact' (bisection) or 'approx' (the paper's closed form).
        alert_limits_m: (A,) limits, carried along for reporting.
    """
    if method not in INVERSE_METHODS:
        raise ValueError(f'unknown inverse Bernoulli method {method!r}; use {INVERSE_METHODS}')
    empirical = np.asarray(empirical, dtype=float)
    eps = (max(kl_nats, 0.0) + np.log((n_posteriors + 1) / delta)) / n_posteriors
    if method == EXACT:
        divergence = inverse_bernoulli_exact(empirical, eps)
    else:
        divergence = inverse_bernoulli_approx(empirical, eps)
    limits = np.full(empirical.shape, np.nan) if alert_limits_m is None else np.asarray(
        alert_limits_m, dtype=float)
    return RiskBound(alert_limits_m=limits, empirical_risk=empirical,
                     divergence_risk=divergence,
                     risk_bound=np.minimum(empirical + divergence, 1.0), kl_nats=kl_nats,
                     epsilon=float(eps))
