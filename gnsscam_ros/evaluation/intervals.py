"""Confidence intervals of integrity rates: exact binomial and between-seed.

An integrity rate is a count ``k`` of epochs out of ``n`` (false alarms of the fault-free
epochs, missed identifications of the faulty ones, MI epochs of the updated ones, ...).

* **Clopper-Pearson** (:func:`clopper_pearson`): the exact binomial interval, from the
  beta distribution: ``lower = Beta(a/2; k, n - k + 1)``, ``upper = Beta(1 - a/2; k + 1,
  n - k)``, ``a = 1 - confidence`` (``lower = 0`` for ``k = 0``, ``upper = 1`` for
  ``k = n``). Its coverage is at least the confidence for *independent* epochs.
* **Between seeds** (:func:`between_seed_interval`): epochs of one drive are correlated
  (an NLOS episode or a fault lasts seconds, the filter carries its error from epoch to
  epoch), so ``n`` epochs carry less information than ``n`` independent trials and the
  Clopper-Pearson interval is too narrow. Drives of different seeds are independent:
  taking each seed as one cluster, the pooled rate ``p = sum k_s / sum n_s`` gets the
  cluster-robust (ratio estimator) variance
  ``v = S / (S - 1) * sum (k_s - p n_s)^2 / (sum n_s)^2`` over the ``S`` seeds, and the
  interval is Korn and Graubard's (1998) Clopper-Pearson interval on the effective sample
  size ``n_eff = p (1 - p) / v`` (at most ``n``; ``n`` when ``v = 0``), shrunk for the
  ``S - 1`` degrees of freedom: ``n* = n_eff (t_{n-1} / t_{S-1})^2`` with ``t`` the
  two-sided ``confidence`` quantiles of Student's t, ``k* = p n*``. The design effect
  ``n / n_eff`` says how many correlated epochs are worth one independent one. It needs
  two seeds or more, and becomes reliable with a handful.
* **Mean over seeds** (:func:`mean_interval`): a quantity measured once per seed (a
  run's RMSE) gets Student's t interval of its mean, ``mean +- t_{S-1} sd / sqrt(S)``.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import stats

#: Confidence of every interval the campaign reports.
CONFIDENCE = 0.95


def clopper_pearson(k: float, n: float, confidence: float = CONFIDENCE
                    ) -> tuple[float, float] | None:
    """Exact binomial (Clopper-Pearson) interval of ``k`` successes in ``n`` trials.

    Non-integer ``k`` and ``n`` are accepted (the beta quantiles are defined for them;
    :func:`between_seed_interval` uses effective counts).

    Args:
        k: Successes, ``0 <= k <= n``.
        n: Trials; 0 gives None (no interval).
        confidence: Two-sided confidence level in (0, 1).

    Returns:
        ``(lower, upper)`` or None when ``n == 0``.

    Raises:
        ValueError: ``k`` or ``n`` out of range, or a confidence outside (0, 1).
    """
    if not 0.0 < confidence < 1.0:
        raise ValueError(f'confidence must be in (0, 1), got {confidence!r}')
    if not (math.isfinite(k) and math.isfinite(n) and 0 <= k <= n):
        raise ValueError(f'need 0 <= k <= n, got k={k!r}, n={n!r}')
    if n == 0:
        return None
    alpha = 1.0 - confidence
    lower = 0.0 if k == 0 else float(stats.beta.ppf(alpha / 2, k, n - k + 1))
    upper = 1.0 if k == n else float(stats.beta.ppf(1 - alpha / 2, k + 1, n - k))
    return lower, upper


def rate_entry(k: int, n: int, confidence: float = CONFIDENCE) -> dict:
    """``{'rate', 'count', 'n', 'ci95'}`` of one count (rate and interval None for n = 0)."""
    ci = clopper_pearson(k, n, confidence)
    return {'rate': k / n if n else None, 'count': int(k), 'n': int(n),
            'ci95': list(ci) if ci is not None else None}


def between_seed_interval(counts: list[int], totals: list[int],
                          confidence: float = CONFIDENCE) -> dict | None:
    """Cluster-robust interval of a pooled rate with one cluster per seed (module doc).

    Args:
        counts: ``k_s`` per seed.
        totals: ``n_s`` per seed (seeds with ``n_s = 0`` carry no information and are
            left out).
        confidence: Two-sided confidence level.

    Returns:
        ``{'ci95', 'seeds', 'design_effect', 'effective_n', 'drive_rate_mean',
        'drive_rate_sd'}`` or None with fewer than two seeds with epochs.
    """
    k = np.asarray(counts, dtype=float)
    n = np.asarray(totals, dtype=float)
    keep = n > 0
    k, n = k[keep], n[keep]
    seeds = int(k.size)
    if seeds < 2:
        return None
    total = float(n.sum())
    p = float(k.sum()) / total
    variance = seeds / (seeds - 1) * float(np.sum((k - p * n) ** 2)) / total ** 2
    binomial = p * (1 - p) / total
    if variance > 0 and binomial > 0:
        n_eff = min(total, p * (1 - p) / variance)
    else:
        # All seeds at the same rate (e.g. none with a single event): no sign of
        # correlation in the data; the degrees of freedom below still widen the interval.
        n_eff = total
    t_ratio = (stats.t.ppf((1 + confidence) / 2, max(total - 1, 1))
               / stats.t.ppf((1 + confidence) / 2, seeds - 1))
    n_star = n_eff * float(t_ratio) ** 2
    ci = clopper_pearson(p * n_star, n_star, confidence)
    rates = k / n
    return {'ci95': list(ci), 'seeds': seeds,
            'design_effect': total / n_eff if n_eff > 0 else None,
            'effective_n': n_star,
            'drive_rate_mean': float(rates.mean()),
            'drive_rate_sd': float(rates.std(ddof=1))}


def epochs_needed(rate: float, upper_limit: float, confidence: float = CONFIDENCE,
                  design_effect: float = 1.0, max_epochs: int = 10 ** 9) -> int | None:
    """Epochs a campaign needs for the Clopper-Pearson upper bound of an observed ``rate``
    to fall below ``upper_limit`` (planning; ``design_effect`` > 1 for correlated epochs).

    Returns:
        The smallest such ``n`` (times the design effect, rounded up), or None when the
        rate is not below the limit or ``max_epochs`` do not suffice.
    """
    if not 0 <= rate < upper_limit <= 1:
        return None

    def upper(n: float) -> float:
        return clopper_pearson(rate * n, n, confidence)[1]

    hi = 1
    while upper(hi) >= upper_limit:
        hi *= 2
        if hi > max_epochs:
            return None
    lo = hi // 2
    while hi - lo > 1:                   # the upper bound falls with n at a fixed rate
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if upper(mid) < upper_limit else (mid, hi)
    return int(math.ceil(hi * design_effect))


def mean_interval(values, confidence: float = CONFIDENCE) -> dict | None:
    """Student's t interval of the mean of one value per seed (module docstring).

    Args:
        values: One finite value per seed.
        confidence: Two-sided confidence level.

    Returns:
        ``{'mean', 'sd', 'seeds', 'ci95'}`` (``ci95`` None with one seed), or None with no
        values.
    """
    v = np.asarray(list(values), dtype=float)
    if not v.size:
        return None
    mean = float(v.mean())
    if v.size < 2:
        return {'mean': mean, 'sd': None, 'seeds': 1, 'ci95': None}
    sd = float(v.std(ddof=1))
    half = float(stats.t.ppf((1 + confidence) / 2, v.size - 1)) * sd / math.sqrt(v.size)
    return {'mean': mean, 'sd': sd, 'seeds': int(v.size), 'ci95': [mean - half, mean + half]}
