"""Posterior inlier probabilities of the satellites under the robust model, for one
particle set (``core.gnss.robust_inlier_shares``): in float64, or in float32 on the
relative views the float32 joint took (``core.kernels.gnss.robust_joint_single``), with
the joint's residuals and densities (its helpers in ``core.kernels.gnss``).
"""
from __future__ import annotations

import numpy as np

from . import contracted_kernel, elementary, inline_kernel
from .gnss import (BLOCK, _block_residuals, _relative_residuals32, _robust_densities,
                   _robust_densities32, _single_constants, _wide_constants)


@inline_kernel
def _lane_totals(lanes_w, lanes_p):
    """The inlier kernels' ``(weighted, share)`` from their per-lane sums (k, BLOCK): the
    lanes added up, the share normalised to sum to one."""
    k = lanes_w.shape[0]
    weighted = np.zeros(k)
    share = np.zeros(k)
    for j in range(k):
        for b in range(BLOCK):
            weighted[j] += lanes_w[j, b]
            share[j] += lanes_p[j, b]
    total = share.sum()
    for j in range(k):
        share[j] /= total
    return weighted, share


@contracted_kernel
def robust_inlier_shares(points, log_w, sv, pr, inv_sigma, sys_index, clock_w, n_systems,
                         log_scale, floor, wide_log_scale, wide_high):
    """Per-satellite inlier probabilities of one set under the robust model.

    ``p_k = d_k / (d_k + v_k + floor_k)``, ``d_k = scale_k exp(-z_k^2 / 2)`` (the core)
    and ``v_k`` the wide component (``core.kernels.gnss.robust_joint``), per particle.

    Returns:
        ``(weighted (k,), share (k,))``: the average of ``p_k`` under ``log_w`` (what the
        bias hypotheses weigh each satellite with) and the plain average over the
        particles normalised to sum to one (the mixture weights reported per epoch).
    """
    n = points.shape[0]
    k = pr.shape[0]
    r = np.empty((k, BLOCK))
    xyz = np.empty((3, BLOCK))
    clock = np.empty((max(n_systems, 1), BLOCK))
    w = np.empty(BLOCK)
    dens = np.empty(BLOCK)
    cores = np.empty(BLOCK)
    ratio, plateau = _wide_constants(log_scale, wide_log_scale)
    # Sums per satellite and lane of a block, added up once at the end: a loop that adds
    # into one scalar stays scalar (each add waits for the previous one), this one
    # vectorises with the exponential in it.
    lanes_w = np.zeros((k, BLOCK))
    lanes_p = np.zeros((k, BLOCK))
    for start in range(0, n, BLOCK):
        m = min(BLOCK, n - start)
        _block_residuals(points, start, m, sv, pr, sys_index, clock_w, n_systems, xyz, r,
                         clock)
        for b in range(m):
            w[b] = elementary.exp(log_w[start + b])
        for j in range(k):
            sum_w, sum_p = lanes_w[j], lanes_p[j]
            _robust_densities(r[j], m, log_scale[j], inv_sigma[j], floor[j],
                              wide_log_scale[j], ratio[j], plateau[j], wide_high[j], dens,
                              cores)
            for b in range(m):
                p = cores[b] / dens[b]
                sum_w[b] += w[b] * p
                sum_p[b] += p
    return _lane_totals(lanes_w, lanes_p)


@contracted_kernel
def robust_inlier_shares_single(points, log_w, centre, unit, base, half_inv_range,
                                max_offset_m, sv, pr, inv_sigma, sys_index, clock_w,
                                n_systems, log_scale, floor, wide_log_scale, wide_high):
    """:func:`robust_inlier_shares` with the densities in float32 on the relative
    coordinates of :func:`robust_joint_single` (the same residuals and densities the
    joint took; the sums in float64).

    Args:
        points, log_w, sv, pr, inv_sigma, sys_index, n_systems, log_scale, floor,
            wide_log_scale, wide_high: As :func:`robust_inlier_shares`.
        centre, unit, base, half_inv_range, max_offset_m, clock_w: The view of the
            joint the set was weighed in, as :func:`robust_joint_single` takes it with
            G = 1: (1, 3), (1, k, 3), (1, k), (1, k), (1,), (1, k).
    """
    n = points.shape[0]
    k = pr.shape[0]
    f32 = np.float32
    (unit32, base32, half32, clock_w32, inv_sigma32, log_scale32, floor32, wide_log32,
     wide_high32, wide_ratio32, plateau32) = _single_constants(
        unit, base, half_inv_range, clock_w, inv_sigma, log_scale, floor, wide_log_scale,
        wide_high)
    r = np.empty((k, BLOCK), dtype=f32)
    clock = np.empty((max(n_systems, 1), BLOCK), dtype=f32)
    d = np.empty((4, BLOCK), dtype=f32)
    dens = np.empty(BLOCK, dtype=f32)
    cores = np.empty(BLOCK, dtype=f32)
    exact_xyz = np.empty((3, BLOCK))
    exact_r = np.empty((k, BLOCK))
    exact_clock = np.empty((max(n_systems, 1), BLOCK))
    w = np.empty(BLOCK)
    dx32, dy32, dz32, q32 = d[0], d[1], d[2], d[3]
    cx, cy, cz = centre[0, 0], centre[0, 1], centre[0, 2]
    limit = f32(max_offset_m[0] * max_offset_m[0])
    # Per satellite and lane, added up once at the end (as robust_inlier_shares).
    lanes_w = np.zeros((k, BLOCK))
    lanes_p = np.zeros((k, BLOCK))
    for start in range(0, n, BLOCK):
        m = min(BLOCK, n - start)
        _relative_residuals32(points, start, m, cx, cy, cz, limit, unit32, base32, half32,
                              clock_w32, clock_w, 0, sv, pr, sys_index, n_systems, dx32, dy32,
                              dz32, q32, r, clock, exact_xyz, exact_r, exact_clock)
        for b in range(m):
            w[b] = elementary.exp(log_w[start + b])
        for j in range(k):
            sum_w, sum_p = lanes_w[j], lanes_p[j]
            _robust_densities32(r[j], clock[sys_index[j]], m, log_scale32[j],
                                inv_sigma32[j], floor32[j], wide_log32[j], wide_ratio32[j],
                                plateau32[j], wide_high32[j], dens, cores, True)
            for b in range(m):
                p = np.float64(cores[b] / dens[b])
                sum_w[b] += w[b] * p
                sum_p[b] += p
    return _lane_totals(lanes_w, lanes_p)
