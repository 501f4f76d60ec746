"""Camera distributions and their mixture (paper §5), fused into one kernel per epoch.

For every posterior set s and camera match k the camera distribution over the set's N
particles (and the "elsewhere" cell) is the softmax of ``-distance / T``; its KL
divergence from the GNSS distribution gives the match's mixture weight, and the mixture
``Q* = sum_k alpha_k Q_k`` multiplies the GNSS likelihood (``core.fusion``). Per set:

1. the particles relative to a reference particle, once (unit-stride, small numbers);
2. per match, one pass for the distances and their minimum (the softmax shift), one pass
   for ``e = exp(logit - shift)`` (one exponential per match, set and particle, kept in a
   scratch buffer) and one for the sums ``sum e`` and ``sum e (logit - shift - log p)``:
   the normaliser and the KL divergence;
3. the mixture from the kept ``e`` and its logarithm; where it underflows (a particle far
   from every match) the exact log-sum-exp over the matches for those particles only.
"""
from __future__ import annotations

import math

import numpy as np

from . import kernel
from .elementary import exp

#: Below this the mixture is taken again by the exact log-sum-exp over the matches.
TINY_MIXTURE = 1e-280
#: Smallest mixture weight whose logarithm the exact fallback uses.
ALPHA_FLOOR = 1e-300


@kernel
def _match(px, py, pz, mx, my, mz, lp, inv_temperature, cell_logit, has_cell, dist, e):
    """One match against one set: ``e = exp(logit - top)`` over the particles (into
    ``e``) and ``(top, z_inside, a)`` with ``z_inside = sum e`` and
    ``a = sum e (logit - top - log p)``; ``top`` is the largest logit (cell included)."""
    n = px.shape[0]
    for i in range(n):
        dx, dy, dz = px[i] - mx, py[i] - my, pz[i] - mz
        dist[i] = math.sqrt(dx * dx + dy * dy + dz * dz)
    d_min = np.inf
    for i in range(n):
        d_min = min(d_min, dist[i])
    top = -d_min * inv_temperature
    if has_cell and cell_logit > top:
        top = cell_logit
    for i in range(n):
        e[i] = exp(-dist[i] * inv_temperature - top)
    # Four partial sums each: independent chains, deterministic order.
    z0 = z1 = z2 = z3 = 0.0
    a0 = a1 = a2 = a3 = 0.0
    stop = n - n % 4
    for i in range(0, stop, 4):
        z0 += e[i]
        z1 += e[i + 1]
        z2 += e[i + 2]
        z3 += e[i + 3]
        a0 += e[i] * (-dist[i] * inv_temperature - top - lp[i])
        a1 += e[i + 1] * (-dist[i + 1] * inv_temperature - top - lp[i + 1])
        a2 += e[i + 2] * (-dist[i + 2] * inv_temperature - top - lp[i + 2])
        a3 += e[i + 3] * (-dist[i + 3] * inv_temperature - top - lp[i + 3])
    for i in range(stop, n):
        z0 += e[i]
        a0 += e[i] * (-dist[i] * inv_temperature - top - lp[i])
    return top, (z0 + z1) + (z2 + z3), (a0 + a1) + (a2 + a3)


@kernel
def _mixture(e, scale, px, py, pz, rel_matches, inv_temperature, log_norm, log_alpha, out):
    """``out = log sum_k scale_k e_k`` (log Q*); where the sum underflows (below
    TINY_MIXTURE: a particle far from every match), the exact log-sum-exp over the
    matches of ``logit - log_norm_k + log_alpha_k`` for those particles only."""
    n_matches, n = e.shape
    for k in range(n_matches):
        c, ek = scale[k], e[k]
        if k == 0:
            for i in range(n):
                out[i] = c * ek[i]
        else:
            for i in range(n):
                out[i] += c * ek[i]
    terms = np.empty(n_matches)
    for i in range(n):
        mix = out[i]
        if mix >= TINY_MIXTURE:
            out[i] = math.log(mix)
            continue
        best = -np.inf
        for k in range(n_matches):
            dx = px[i] - rel_matches[k, 0]
            dy = py[i] - rel_matches[k, 1]
            dz = pz[i] - rel_matches[k, 2]
            terms[k] = (-math.sqrt(dx * dx + dy * dy + dz * dz) * inv_temperature
                        - log_norm[k] + log_alpha[k])
            best = max(best, terms[k])
        total = 0.0
        for k in range(n_matches):
            total += math.exp(terms[k] - best)
        out[i] = best + math.log(total)


@kernel
def fuse(x, y, z, matches, log_p, inv_temperature, cell_logit, log_inside, log_elsewhere,
         has_cell, kl_threshold, log_q_mix, alpha, kl, excluded):
    """Camera mixture of every posterior set, written into the output arrays.

    Args:
        x, y, z: (S, N) particle positions, east, north, up [m].
        matches: (K, 3) matched positions at the epoch [m].
        log_p: (S, N) normalised log GNSS distribution of each set.
        inv_temperature: 1 / T [1/m].
        cell_logit: Logit of the "elsewhere" cell, ``-R / T + log N``.
        log_inside: ``log(1 - elsewhere_prob)``, the GNSS log-mass of the particles.
        log_elsewhere: ``log(elsewhere_prob)``.
        has_cell: Whether the domain has the "elsewhere" cell (else a plain softmax; the
            three arguments before are then unused).
        kl_threshold: The camera of a set is excluded when every KL exceeds it [nats].
        log_q_mix: (S, N) output: log Q* (0 for an excluded set).
        alpha: (K, S) output: normalised mixture weights.
        kl: (K, S) output: KL(Q_k || P) [nats].
        excluded: (S,) output: the camera is excluded for that set.
    """
    n_sets, n = log_p.shape
    n_matches = matches.shape[0]
    px, py, pz, dist = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    e = np.empty((n_matches, n))
    log_norm, scale = np.empty(n_matches), np.empty(n_matches)
    weight, log_alpha = np.empty(n_matches), np.empty(n_matches)
    # Coordinates relative to a particle: small numbers, exact differences.
    ref = np.array([x[0, 0], y[0, 0], z[0, 0]])
    rel_matches = matches - ref
    log_z_inside = log_inside if has_cell else 0.0
    for s in range(n_sets):
        xs, ys, zs = x[s], y[s], z[s]
        for i in range(n):
            px[i] = xs[i] - ref[0]
            py[i] = ys[i] - ref[1]
            pz[i] = zs[i] - ref[2]
        kl_min = np.inf
        for k in range(n_matches):
            top, z_inside, a = _match(px, py, pz, rel_matches[k, 0], rel_matches[k, 1],
                                      rel_matches[k, 2], log_p[s], inv_temperature,
                                      cell_logit, has_cell, dist, e[k])
            e_cell = math.exp(cell_logit - top) if has_cell else 0.0
            total = z_inside + e_cell
            log_z = math.log(total)
            log_norm[k], scale[k] = top + log_z, 1.0 / total
            # KL(Q_k || P) = sum_i q_i (log q_i - log p_i), q_i = e_i / total, the cell's
            # term apart; alpha_k is the softmax of -KL_k - 1 (paper §5).
            div = a / total - (log_z + log_z_inside) * (z_inside / total)
            if has_cell:
                div += (e_cell / total) * (cell_logit - top - log_z - log_elsewhere)
            kl[k, s] = div
            weight[k] = -div - 1.0
            kl_min = min(kl_min, div)
        w_max = weight.max()
        for k in range(n_matches):
            weight[k] = math.exp(weight[k] - w_max)
        total = weight.sum()
        for k in range(n_matches):
            alpha[k, s] = weight[k] / total
            scale[k] *= alpha[k, s]
            log_alpha[k] = math.log(max(alpha[k, s], ALPHA_FLOOR))
        excluded[s] = kl_min > kl_threshold
        if excluded[s]:
            log_q_mix[s, :] = 0.0
        else:
            _mixture(e, scale, px, py, pz, rel_matches, inv_temperature, log_norm,
                     log_alpha, log_q_mix[s])


def warm_up() -> None:
    """Compile (or load from the disk cache) :func:`fuse` for the argument types of
    ``core.fusion.camera_fusion`` (coordinates as strided (S, N) views), on a tiny
    input."""
    positions = np.zeros((2, 4, 4))
    positions[:, :, 0] = np.arange(4.0)
    log_p = np.full((2, 4), -math.log(4.0))
    out = np.empty((2, 4)), np.empty((1, 2)), np.empty((1, 2)), np.empty(2, dtype=np.bool_)
    fuse(positions[..., 0], positions[..., 1], positions[..., 2], np.zeros((1, 3)), log_p,
         0.2, -4.0 + math.log(4.0), math.log1p(-1e-3), math.log(1e-3), True, 5.0, *out)
