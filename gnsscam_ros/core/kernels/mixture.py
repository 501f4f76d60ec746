"""The error model's EM iterations (``core.error_model``) in one pass per iteration.

An epoch refits the mixture twice (pooled, then per signal class) over the window's
residuals, a few iterations each, so its cost grows with the window: some 4,500 residuals
at 5 Hz. Each iteration is one loop giving every residual its responsibility (one
exponential of the log density ratio: no divisions, no class sums, so it vectorises),
one loop folding them into the class sums, and the M-step per class. The epoch's two fits
and the class prior between them are one call (:func:`refit`), and how many residuals the
fit takes for line of sight is the E-step's responsibility summed (:func:`line_of_sight`).
"""
from __future__ import annotations

import math

import numpy as np

from . import inline_kernel, kernel
from .elementary import exp


@inline_kernel
def _class_constants(s0, pi, s1, inv0, inv1, log_ratio):
    """Per class ``1 / s0``, ``1 / s1`` and the log of the core's over the wide density
    apart from their exponents (+-inf where a weight is 0: the responsibility is then
    exactly 0 or 1)."""
    for c in range(s0.shape[0]):
        inv0[c] = 1.0 / s0[c]
        inv1[c] = 1.0 / s1[c]
        log_ratio[c] = math.log((1.0 - pi[c]) / pi[c]) + math.log(s1[c] * inv0[c])


@inline_kernel
def _wide_responsibility(r, inv0, inv1, mu, log_ratio):
    """P(NLOS | r) = 1 / (1 + core / wide), from the class constants of
    :func:`_class_constants`: the ratio stays finite where both densities underflow (a
    residual of kilometres is the wide component's, not a 0 / 0 that would hand it to
    the core)."""
    z0 = r * inv0
    z1 = (r - mu) * inv1
    return 1.0 / (1.0 + exp(log_ratio - 0.5 * (z0 * z0 - z1 * z1)))


@kernel
def em_fit(r, w, cls, n_classes, s0, pi, mu, s1, p_s0, p_pi, p_mu, p_s1, strength,
           min_core_sd_m, iterations):
    """``iterations`` MAP EM iterations of a two-component mixture per class,
    ``(1 - pi) N(r; 0, s0^2) + pi N(r; mu, s1^2)``, started from ``(s0, pi, mu, s1)``.

    The E-step gives each residual its probability of the wide component; the M-step
    takes each class's weighted moments plus conjugate pseudo-samples at the prior's
    centre (``strength * (1 - p_pi)`` core samples of variance ``p_s0^2``,
    ``strength * p_pi`` wide ones at ``p_mu`` with variance ``p_s1^2``), ``mu >= 0``,
    ``s0 >= min_core_sd_m`` and ``s1 >= 2 s0`` (the wide component stays the wide one).

    Args:
        r: (n,) residuals [m]; w: (n,) their weights; cls: (n,) their classes (int64).
        n_classes: Number of classes.
        s0, pi, mu, s1: (n_classes,) the starting fit.
        p_s0, p_pi, p_mu, p_s1: (n_classes,) the prior's centre.
        strength: Pseudo-samples of the prior.
        min_core_sd_m: Floor of s0 [m].
        iterations: EM iterations.

    Returns:
        The fit ``(s0, pi, mu, s1)``, new arrays (n_classes,).
    """
    n = r.shape[0]
    s0, pi, mu, s1 = s0.copy(), pi.copy(), mu.copy(), s1.copy()
    a0 = strength * (1.0 - p_pi)
    a1 = strength * p_pi
    inv0 = np.empty(n_classes)
    inv1 = np.empty(n_classes)
    log_ratio = np.empty(n_classes)
    # Per class: core and wide weights, the wide one's first and second moment, the core's
    # second moment.
    n0 = np.empty(n_classes)
    n1 = np.empty(n_classes)
    sum1_r = np.empty(n_classes)
    sum1_rr = np.empty(n_classes)
    sum0_rr = np.empty(n_classes)
    resp = np.empty(n)
    at_inv0 = np.empty(n)
    at_inv1 = np.empty(n)
    at_mu = np.empty(n)
    at_log_ratio = np.empty(n)
    for _ in range(iterations):
        _class_constants(s0, pi, s1, inv0, inv1, log_ratio)
        # E-step (_wide_responsibility). The class constants are gathered first: the loop
        # of exponentials then vectorises (with the gathers inside it did not, and took
        # 2.5 times as long).
        for i in range(n):
            c = cls[i]
            at_inv0[i] = inv0[c]
            at_inv1[i] = inv1[c]
            at_mu[i] = mu[c]
            at_log_ratio[i] = log_ratio[c]
        for i in range(n):
            resp[i] = _wide_responsibility(r[i], at_inv0[i], at_inv1[i], at_mu[i],
                                           at_log_ratio[i])
        n0[:] = 0.0
        n1[:] = 0.0
        sum1_r[:] = 0.0
        sum1_rr[:] = 0.0
        sum0_rr[:] = 0.0
        for i in range(n):
            c = cls[i]
            w1 = w[i] * resp[i]
            w0 = w[i] - w1
            rr = r[i] * r[i]
            n0[c] += w0
            n1[c] += w1
            sum1_r[c] += w1 * r[i]
            sum1_rr[c] += w1 * rr
            sum0_rr[c] += w0 * rr
        for c in range(n_classes):
            pi[c] = (n1[c] + a1[c]) / (n0[c] + n1[c] + a0[c] + a1[c])
            mu[c] = max((sum1_r[c] + a1[c] * p_mu[c]) / (n1[c] + a1[c]), 0.0)
            s0[c] = math.sqrt((sum0_rr[c] + a0[c] * p_s0[c] ** 2) / (n0[c] + a0[c]))
            # The wide spread about the new mean: sum w1 (r - mu)^2 from the moments (the
            # mean is of the order of the spread: no cancellation to speak of).
            dev = max(sum1_rr[c] - 2.0 * mu[c] * sum1_r[c] + mu[c] * mu[c] * n1[c], 0.0)
            s1[c] = math.sqrt((dev + a1[c] * p_s1[c] ** 2) / (n1[c] + a1[c]))
            s0[c] = max(s0[c], min_core_sd_m)
            s1[c] = max(s1[c], 2.0 * s0[c])
    return s0, pi, mu, s1


@kernel
def refit(r, w, cls, n_classes, pooled, pooled_prior, pooled_strength, fit, shape,
          class_strength, min_core_sd_m, iterations):
    """The error model's refit of an epoch (``core.error_model``) in one call: the
    pooled fit (:func:`em_fit` with every residual in one class, from ``pooled`` towards
    ``pooled_prior``), then the classes' (from ``fit``) towards their prior, the pooled
    fit's spreads shaped by ``shape`` about their sample-weighted mean (so that the shape
    moves spreads between classes only). The arithmetic between the two fits is numpy's
    on (n_classes,) arrays, element for element (a sum of a few values is a loop there
    too).

    Args:
        r: (n,) residuals [m]; w: (n,) their weights; cls: (n,) their classes (int64).
        n_classes: Number of classes.
        pooled, pooled_prior: ``(s0, pi, mu, s1)``, arrays (1,): the pooled fit and its
            prior's centre.
        pooled_strength, class_strength: Pseudo-samples of the two priors.
        fit: ``(s0, pi, mu, s1)``, arrays (n_classes,): the classes' fit.
        shape: (n_classes,) the priors' C/N0 shape of the class spreads.
        min_core_sd_m, iterations: As :func:`em_fit`.

    Returns:
        ``(pooled fit, class fit, counts)``: two ``(s0, pi, mu, s1)`` tuples and the
        residuals per class (float, (n_classes,)).
    """
    one = np.zeros(r.shape[0], dtype=np.int64)
    s0, pi, mu, s1 = em_fit(r, w, one, 1, pooled[0], pooled[1], pooled[2], pooled[3],
                            pooled_prior[0], pooled_prior[1], pooled_prior[2],
                            pooled_prior[3], pooled_strength, min_core_sd_m, iterations)
    counts = np.zeros(n_classes)
    for i in range(cls.shape[0]):
        counts[cls[i]] += 1.0
    weighted = 0.0
    total = 0.0
    for c in range(n_classes):
        weighted += counts[c] * shape[c]
        total += counts[c]
    mean_shape = weighted / max(total, 1.0)
    shaped = np.empty(n_classes)
    for c in range(n_classes):
        shaped[c] = shape[c] / mean_shape
    fitted = em_fit(r, w, cls, n_classes, fit[0], fit[1], fit[2], fit[3], s0[0] * shaped,
                    np.full(n_classes, pi[0]), np.full(n_classes, mu[0]), s1[0] * shaped,
                    class_strength, min_core_sd_m, iterations)
    return (s0, pi, mu, s1), fitted, counts


@kernel
def line_of_sight(r, cls, s0, pi, mu, s1):
    """How many of the residuals ``r`` (k,) of classes ``cls`` the fit ``(s0, pi, mu,
    s1)`` (per class) takes for line of sight: the sum of their probabilities of the core,
    ``1 - P(NLOS | r)`` as the EM's E-step gives it (``core.error_model``: the residuals'
    inflation)."""
    n_classes = s0.shape[0]
    inv0 = np.empty(n_classes)
    inv1 = np.empty(n_classes)
    log_ratio = np.empty(n_classes)
    _class_constants(s0, pi, s1, inv0, inv1, log_ratio)
    total = 0.0
    for i in range(r.shape[0]):
        c = cls[i]
        total += 1.0 - _wide_responsibility(r[i], inv0[c], inv1[c], mu[c], log_ratio[c])
    return total
