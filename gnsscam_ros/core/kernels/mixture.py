"""The error model's EM iterations (``core.error_model``) in one pass per iteration.

An epoch refits the mixture twice (pooled, then per signal class) over the window's
residuals, a few iterations each; in numpy every iteration was some twenty small array
operations (densities, responsibilities, seven weighted sums per class), about half a
millisecond an epoch. Same arithmetic here: the responsibilities and the class sums in
one loop over the residuals, then the M-step per class.
"""
from __future__ import annotations

import math

import numpy as np

from . import kernel

_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)


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
    n0 = np.empty(n_classes)
    n1 = np.empty(n_classes)
    sum1_r = np.empty(n_classes)
    sum0_rr = np.empty(n_classes)
    resp = np.empty(n)
    for _ in range(iterations):
        n0[:] = 0.0
        n1[:] = 0.0
        sum1_r[:] = 0.0
        sum0_rr[:] = 0.0
        for i in range(n):
            c = cls[i]
            z0 = r[i] / s0[c]
            z1 = (r[i] - mu[c]) / s1[c]
            core = (1.0 - pi[c]) * (math.exp(-0.5 * z0 * z0) * _INV_SQRT_2PI / s0[c])
            wide = pi[c] * (math.exp(-0.5 * z1 * z1) * _INV_SQRT_2PI / s1[c])
            resp[i] = wide / max(core + wide, 1e-300)     # P(NLOS | r)
            w1 = w[i] * resp[i]
            w0 = w[i] - w1
            n0[c] += w0
            n1[c] += w1
            sum1_r[c] += w1 * r[i]
            sum0_rr[c] += w0 * r[i] * r[i]
        new_mu = np.empty(n_classes)
        for c in range(n_classes):
            pi[c] = (n1[c] + a1[c]) / (n0[c] + n1[c] + a0[c] + a1[c])
            new_mu[c] = max((sum1_r[c] + a1[c] * p_mu[c]) / (n1[c] + a1[c]), 0.0)
            s0[c] = math.sqrt((sum0_rr[c] + a0[c] * p_s0[c] ** 2) / (n0[c] + a0[c]))
        # The wide spread about the new mean.
        dev_sum = np.zeros(n_classes)
        for i in range(n):
            c = cls[i]
            dev = r[i] - new_mu[c]
            dev_sum[c] += w[i] * resp[i] * dev * dev
        for c in range(n_classes):
            mu[c] = new_mu[c]
            s1[c] = math.sqrt((dev_sum[c] + a1[c] * p_s1[c] ** 2) / (n1[c] + a1[c]))
            s0[c] = max(s0[c], min_core_sd_m)
            s1[c] = max(s1[c], 2.0 * s0[c])
    return s0, pi, mu, s1
