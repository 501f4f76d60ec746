"""Receiver clock and GNSS likelihoods per particle (paper §3), fused in one pass.

For every particle of every motion sample: ranges to the k satellites, residuals, the
particle's own per-constellation clock (inlier-weighted mean of its residuals), normalised
residuals ``z`` and the log-likelihood, added to the prior log-weight (the joint), then the
log-sum-exp of each set. Nothing of size S x N x k is ever stored: particles go through in
blocks of ``BLOCK`` whose residuals (k x BLOCK) stay in the first-level cache, and each
inner loop runs over the particles of a block, which the compiler turns into vector
instructions (ranges, clocks, normalised residuals).

Ranges are taken directly as ``|s - p|`` in float64: the rounding of a 2e7 m range is
4e-9 m. The per-satellite exponentials, which dominate the kernels, are
``elementary.exp`` (vectorised with the rest of a block's loop, within 2 ulp of libm's).
"""
from __future__ import annotations

import math

import numpy as np

from . import contracted_kernel, elementary, inline_kernel, kernel

#: Particles per block (see the module docstring).
BLOCK = 64
LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)


@inline_kernel
def _block_residuals(points, start, m, sv, pr, sys_index, clock_w, n_systems, xyz, r, clock):
    """Clock-corrected residuals ``r[j, b]`` of the points ``start .. start + m`` of
    ``points`` (P, >= 3): each point's own per-constellation clock (``clock`` scratch,
    (n_systems, BLOCK)) removed [m].

    The block's coordinates are first copied into the contiguous rows of ``xyz`` (3,
    BLOCK): the loop over satellites then reads unit-stride vectors (the rows of
    ``points`` hold 4 or more values, a strided gather that keeps the loop slow)."""
    k = pr.shape[0]
    px, py, pz = xyz[0], xyz[1], xyz[2]
    for b in range(m):
        px[b] = points[start + b, 0]
        py[b] = points[start + b, 1]
        pz[b] = points[start + b, 2]
    for c in range(n_systems):
        clock_c = clock[c]
        for b in range(m):
            clock_c[b] = 0.0
    for j in range(k):
        sx, sy, sz, p, w = sv[j, 0], sv[j, 1], sv[j, 2], pr[j], clock_w[j]
        r_j, clock_c = r[j], clock[sys_index[j]]
        for b in range(m):
            dx = sx - px[b]
            dy = sy - py[b]
            dz = sz - pz[b]
            rj = p - math.sqrt(dx * dx + dy * dy + dz * dz)
            r_j[b] = rj
            clock_c[b] += w * rj
    for j in range(k):
        r_j, clock_c = r[j], clock[sys_index[j]]
        for b in range(m):
            r_j[b] -= clock_c[b]


@inline_kernel
def _fold_logs(prod, log_sum, m):
    """Add the log of each particle's running product of densities to its sum and start
    the product again (one log per group of satellites; a float32 product's log is taken
    in float64, which adds no error to the product's own rounding). ``elementary.log``,
    not libm's: a call per particle kept this loop scalar and took a third of the
    likelihood's time."""
    for b in range(m):
        log_sum[b] += elementary.log(np.float64(prod[b]))
        prod[b] = 1.0


#: ``log`` of a wide component at or below this is absent (``core.gnss.ABSENT_LOG``): its
#: part beyond the flat top is not computed.
_WIDE_ABSENT_LOG = -700.0


@inline_kernel
def _wide_constants(log_scale, wide_log_scale):
    """Per satellite, ``e^(wl - ls)`` and ``e^wl`` of :func:`_robust_densities` (0 for an
    absent wide component), once per kernel call: (k,), (k,)."""
    k = log_scale.shape[0]
    ratio = np.zeros(k)
    plateau = np.zeros(k)
    for j in range(k):
        if wide_log_scale[j] > _WIDE_ABSENT_LOG:
            ratio[j] = math.exp(wide_log_scale[j] - log_scale[j])
            plateau[j] = math.exp(wide_log_scale[j])
    return ratio, plateau


@inline_kernel
def _robust_densities(r_j, m, ls, isg, fl, wl, ratio, plateau, hi, dens, cores):
    """Each particle's density of one satellite under the robust model, for residuals
    ``r_j`` (float64): ``core + wide + floor`` into ``dens``, the core into ``cores``.

    The wide component is flat from 0 to ``hi`` and falls off on both sides like the core
    (``core.gnss.robust_terms``). Below 0 it is the core times ``ratio = e^(wl - ls)``, on
    the flat top the constant ``plateau = e^wl`` (:func:`_wide_constants`, 0 when
    absent): one exponential per particle and satellite, not two. Only a residual beyond
    the flat top needs its own, and a block computes it only when one of its residuals
    lies there (a satellite delayed beyond its component's top)."""
    above = False
    for b in range(m):
        e = r_j[b]
        z = e * isg
        core = elementary.exp(ls - 0.5 * z * z)
        wide = core * ratio if e < 0.0 else (plateau if e <= hi else 0.0)
        cores[b] = core
        dens[b] = core + wide + fl
        above |= e > hi
    if above and plateau > 0.0:
        for b in range(m):
            e = r_j[b]
            t = (e - hi) * isg
            tail = elementary.exp(wl - 0.5 * t * t)
            dens[b] += tail if e > hi else 0.0


@inline_kernel
def _robust_densities32(r_j, clock_c, m, ls, isg, fl, wl, ratio, plateau, hi, dens, cores,
                        want_cores):
    """:func:`_robust_densities` in float32, for residuals ``r_j - clock_c``; the core
    into ``cores`` only when ``want_cores`` (a constant of the caller: the branch is
    compiled away)."""
    half = np.float32(0.5)
    zero = np.float32(0.0)
    above = False
    for b in range(m):
        e = r_j[b] - clock_c[b]
        z = e * isg
        core = elementary.exp32(ls - half * z * z)
        wide = core * ratio if e < zero else (plateau if e <= hi else zero)
        dens[b] = core + wide + fl
        if want_cores:
            cores[b] = core
        above |= e > hi
    if above and plateau > zero:
        for b in range(m):
            e = r_j[b] - clock_c[b]
            t = (e - hi) * isg
            tail = elementary.exp32(wl - half * t * t)
            dens[b] += tail if e > hi else zero


@inline_kernel
def _single_constants(unit, base, half_inv_range, clock_w, inv_sigma, log_scale, floor,
                      wide_log_scale, wide_high):
    """The float32 kernels' per-satellite constants: the views' and the robust model's
    arrays rounded to float32 (the wide component's two constants computed in float64
    first, :func:`_wide_constants`)."""
    f32 = np.float32
    ratio, plateau = _wide_constants(log_scale, wide_log_scale)
    return (unit.astype(f32), base.astype(f32), half_inv_range.astype(f32),
            clock_w.astype(f32), inv_sigma.astype(f32), log_scale.astype(f32),
            floor.astype(f32), np.maximum(wide_log_scale, -1000.0).astype(f32),
            wide_high.astype(f32), ratio.astype(f32), plateau.astype(f32))


@inline_kernel
def _relative_residuals32(points, start, m, cx, cy, cz, limit, unit32, base32, half32,
                          clock_w32, clock_w, g, sv, pr, sys_index, n_systems, dx32, dy32,
                          dz32, q32, r, clock, exact_xyz, exact_r, exact_clock):
    """Float32 residuals ``r[j, b]`` of the points ``start .. start + m`` of ``points``
    relative to the centre ``(cx, cy, cz)`` (:func:`robust_joint_single` says how), and
    each point's clock per constellation in ``clock`` (float32, (n_systems, BLOCK)): the
    residual the densities take is ``r[j] - clock[sys_index[j]]``. A block with a point
    whose squared offset exceeds ``limit`` takes the exact float64 residuals, their clock
    already removed (``clock`` zero). ``unit32`` (k, 3), ``base32``, ``half32``,
    ``clock_w32`` (k,): one view's float32 constants; ``clock_w`` (k,) its float64 clock
    weights; ``dx32 .. q32`` (BLOCK,) float32 (offsets east, north, up and ``|d|^2``)
    and ``exact_*`` float64 scratch (rows of scratch arrays are taken once by the
    caller: a view made per block costs as much as a tenth of the block's arithmetic)."""
    k = pr.shape[0]
    f32 = np.float32
    zero = f32(0.0)
    for b in range(m):
        dx = points[start + b, 0] - cx
        dy = points[start + b, 1] - cy
        dz = points[start + b, 2] - cz
        dx32[b] = f32(dx)
        dy32[b] = f32(dy)
        dz32[b] = f32(dz)
        q32[b] = f32(dx * dx + dy * dy + dz * dz)
    far = False
    for b in range(m):
        far |= q32[b] > limit
    for c in range(n_systems):
        clock_c = clock[c]
        for b in range(m):
            clock_c[b] = zero
    if far:
        # Residuals r - clock in float64, the clock already removed.
        _block_residuals(points, start, m, sv, pr, sys_index, clock_w[g], n_systems,
                         exact_xyz, exact_r, exact_clock)
        for j in range(k):
            for b in range(m):
                r[j, b] = f32(exact_r[j, b])
    else:
        for j in range(k):
            ux, uy, uz = unit32[g, j, 0], unit32[g, j, 1], unit32[g, j, 2]
            p, h, w = base32[g, j], half32[g, j], clock_w32[g, j]
            r_j, clock_c = r[j], clock[sys_index[j]]
            for b in range(m):
                a = ux * dx32[b] + uy * dy32[b] + uz * dz32[b]
                rj = p + a - (q32[b] - a * a) * h
                r_j[b] = rj
                clock_c[b] += w * rj


@kernel
def _log_sum_exp(values):
    """``log sum exp(values)`` of a (N,) array, shifted by its maximum.

    Written for speed (once per set, over N values): the maximum in four partial results
    (``elementary.largest``); the exponentials a block at a time into a buffer (a loop
    that only stores vectorises, with ``elementary.exp`` in it, where libm's exp would be
    a call per element); each block summed in four partial sums."""
    n = values.shape[0]
    top = elementary.largest(values, -np.inf)
    if not top > -np.inf:
        return top
    buffer = np.empty(BLOCK)
    acc = 0.0
    for start in range(0, n, BLOCK):
        m = min(BLOCK, n - start)
        for b in range(m):
            buffer[b] = elementary.exp(values[start + b] - top)
        s0 = s1 = s2 = s3 = 0.0
        quad = m - m % 4
        for b in range(0, quad, 4):
            s0 += buffer[b]
            s1 += buffer[b + 1]
            s2 += buffer[b + 2]
            s3 += buffer[b + 3]
        for b in range(quad, m):
            s0 += buffer[b]
        acc += (s0 + s1) + (s2 + s3)
    return top + math.log(acc)


@contracted_kernel
def residuals_of_points(points, sv, pr, sys_index, clock_w, n_systems):
    """Clock-corrected residuals (P, k) of (P, >= 3) points [m]."""
    n = points.shape[0]
    k = pr.shape[0]
    out = np.empty((n, k))
    r = np.empty((k, BLOCK))
    xyz = np.empty((3, BLOCK))
    clock = np.empty((max(n_systems, 1), BLOCK))
    for start in range(0, n, BLOCK):
        m = min(BLOCK, n - start)
        _block_residuals(points, start, m, sv, pr, sys_index, clock_w, n_systems, xyz, r,
                         clock)
        for b in range(m):
            for j in range(k):
                out[start + b, j] = r[j, b]
    return out


@contracted_kernel
def robust_joint(sets, sv, pr, inv_sigma, sys_index, clock_w, n_systems, log_scale, floor,
                 wide_log_scale, wide_high, group, tempering, prior_log_w, joint):
    """Joint log-weights under the robust likelihood, for S sets of N particles.

    ``log L = sum_k log(scale_k exp(-z_k^2 / 2) + wide_k exp(-w_k^2 / 2) + floor_k)``
    with ``z_k = e_k / sigma_k`` (the line-of-sight core),
    ``w_k = (min(e_k, 0) + max(e_k - hi_k, 0)) / sigma_k`` (the NLOS / multipath
    component of the learned error model, flat between 0 and ``hi_k``,
    ``core.gnss.robust_terms``; ``log wide_k`` at or below ``-700``: none) and a flat
    floor per satellite: one ``exp`` per satellite where the residual is not beyond the
    flat top (:func:`_robust_densities`), one ``log`` per ``group`` satellites (the
    product of that many densities stays within the floating-point range;
    ``core.gnss.robust_terms``).

    Args:
        sets: (S, N, >= 3) particle positions [m].
        sv: (k, 3) satellite positions, same frame [m].
        pr: (k,) pseudoranges [m].
        inv_sigma: (k,) inverse measurement standard deviations [1/m].
        sys_index: (k,) constellation of each satellite.
        clock_w: (G, k) clock weights, summing to one per constellation: one row for
            every set (G = 1) or a row per set (G = S: sets weighed about places of
            their own, as the consistency test's two in one call).
        n_systems: Number of constellations.
        log_scale: (k,) log of each satellite's Gaussian scale (above).
        floor: (k,) outlier floor of each satellite (above).
        wide_log_scale: (k,) log of each satellite's wide component scale ``wide_k``.
        wide_high: (k,) the top of its flat part [m].
        group: Satellites per log.
        tempering: Tempering exponent of the log-likelihood.
        prior_log_w: (N,) prior log-weights.
        joint: (S, N) written: ``prior_log_w + tempering * log L``.

    Returns:
        (S,) log-sum-exp of each set's joint.
    """
    s_count, n = sets.shape[0], sets.shape[1]
    k = pr.shape[0]
    r = np.empty((k, BLOCK))
    xyz = np.empty((3, BLOCK))
    clock = np.empty((max(n_systems, 1), BLOCK))
    prod = np.empty(BLOCK)
    dens = np.empty(BLOCK)
    cores = np.empty(BLOCK)
    ratio, plateau = _wide_constants(log_scale, wide_log_scale)
    log_sum = np.empty(BLOCK)
    total = np.empty(s_count)
    shared = clock_w.shape[0] == 1
    for s in range(s_count):
        points = sets[s]
        clock_ws = clock_w[0] if shared else clock_w[s]
        for start in range(0, n, BLOCK):
            m = min(BLOCK, n - start)
            _block_residuals(points, start, m, sv, pr, sys_index, clock_ws, n_systems, xyz,
                             r, clock)
            for b in range(m):
                prod[b] = 1.0
                log_sum[b] = 0.0
            count = 0
            for j in range(k):
                _robust_densities(r[j], m, log_scale[j], inv_sigma[j], floor[j],
                                  wide_log_scale[j], ratio[j], plateau[j], wide_high[j],
                                  dens, cores)
                for b in range(m):
                    prod[b] *= dens[b]
                count += 1
                if count == group:
                    _fold_logs(prod, log_sum, m)
                    count = 0
            if count > 0:
                _fold_logs(prod, log_sum, m)
            for b in range(m):
                joint[s, start + b] = prior_log_w[start + b] + tempering * log_sum[b]
        total[s] = _log_sum_exp(joint[s])
    return total


@contracted_kernel
def robust_joint_single(sets, centre, unit, base, half_inv_range, max_offset_m, sv, pr,
                        inv_sigma, sys_index, clock_w, n_systems, log_scale, floor,
                        wide_log_scale, wide_high, group, tempering, prior_log_w, joint):
    """:func:`robust_joint` with the per-satellite arithmetic in float32 (twice the SIMD
    lanes), on coordinates relative to a ``centre`` near the cloud.

    Absolute ranges cannot be float32 (their spacing at 2e7 m is 2 m). Relative to the
    centre ``c`` a point is ``c + d``, and with ``e = s - c``, ``rho0 = |e|``,
    ``u = e / rho0``, ``a = u . d``: ``|s - c - d| = rho0 - a + (|d|^2 - a^2) / (2 rho0)``
    up to ``|d|^3 / (2 rho0^2)``. The caller passes ``base = pr - rho0 - clock0`` per
    satellite in float64 (``clock0`` a common clock per constellation: the particle's
    own clock removes it again, and what stays in float32 is tens of metres), ``unit``
    (u) and ``half_inv_range`` (1 / (2 rho0)); ``max_offset_m`` bounds ``|d|`` where the
    expansion and the float32 offsets are exact enough (``core.gnss``). A block with a
    particle farther out takes the exact float64 residuals (:func:`_block_residuals`).

    Args:
        sets, sv, pr, inv_sigma, sys_index, clock_w, n_systems, log_scale, floor,
            wide_log_scale, wide_high, tempering, prior_log_w, joint: As
            :func:`robust_joint` (``floor`` and the densities within the float32 range,
            ``group`` for it).
        centre: (G, 3) the centre c [m], one for every set or each set's (as ``clock_w``).
        unit, base, half_inv_range: (G, k, 3), (G, k), (G, k) as above.
        max_offset_m: (G,) largest ``|d|`` of the float32 path [m].

    Returns:
        (S,) log-sum-exp of each set's joint.
    """
    s_count, n = sets.shape[0], sets.shape[1]
    k = pr.shape[0]
    f32 = np.float32
    (unit32, base32, half32, clock_w32, inv_sigma32, log_scale32, floor32, wide_log32,
     wide_high32, wide_ratio32, plateau32) = _single_constants(
        unit, base, half_inv_range, clock_w, inv_sigma, log_scale, floor, wide_log_scale,
        wide_high)
    one = f32(1.0)
    r = np.empty((k, BLOCK), dtype=f32)
    clock = np.empty((max(n_systems, 1), BLOCK), dtype=f32)
    d = np.empty((4, BLOCK), dtype=f32)            # offsets east, north, up; |d|^2
    prod = np.empty(BLOCK, dtype=f32)
    dens = np.empty(BLOCK, dtype=f32)
    log_sum = np.empty(BLOCK)
    exact_xyz = np.empty((3, BLOCK))
    exact_r = np.empty((k, BLOCK))
    exact_clock = np.empty((max(n_systems, 1), BLOCK))
    total = np.empty(s_count)
    dx32, dy32, dz32, q32 = d[0], d[1], d[2], d[3]
    for s in range(s_count):
        points = sets[s]
        g = 0 if centre.shape[0] == 1 else s
        cx, cy, cz = centre[g, 0], centre[g, 1], centre[g, 2]
        limit = f32(max_offset_m[g] * max_offset_m[g])
        for start in range(0, n, BLOCK):
            m = min(BLOCK, n - start)
            _relative_residuals32(points, start, m, cx, cy, cz, limit, unit32, base32, half32,
                                  clock_w32, clock_w, g, sv, pr, sys_index, n_systems, dx32,
                                  dy32, dz32, q32, r, clock, exact_xyz, exact_r, exact_clock)
            for b in range(m):
                prod[b] = one
                log_sum[b] = 0.0
            count = 0
            for j in range(k):
                _robust_densities32(r[j], clock[sys_index[j]], m, log_scale32[j],
                                    inv_sigma32[j], floor32[j], wide_log32[j],
                                    wide_ratio32[j], plateau32[j], wide_high32[j], dens,
                                    dens, False)
                for b in range(m):
                    prod[b] *= dens[b]
                count += 1
                if count == group:
                    _fold_logs(prod, log_sum, m)
                    count = 0
            if count > 0:
                _fold_logs(prod, log_sum, m)
            for b in range(m):
                joint[s, start + b] = prior_log_w[start + b] + tempering * log_sum[b]
        total[s] = _log_sum_exp(joint[s])
    return total


@contracted_kernel
def particle_raim_joint(sets, sv, pr, inv_sigma, sys_index, clock_w, n_systems,
                        dirichlet_alpha, tempering, prior_log_w, joint, gamma):
    """Joint log-weights under the Particle RAIM mixture, weights by one EM step.

    E-step: each particle votes for satellite k with ``exp(-z_k^2 / 2)`` normalised over
    the satellites; M-step: ``gamma_k = (sum_p w_p v_pk + alpha - 1) / (1 + k (alpha - 1))``
    per set; then ``log L = log sum_k gamma_k N(e_k; 0, sigma_k)``. Two passes over the
    particles (the second recomputes the residuals rather than storing S x N x k).

    Args:
        sets, sv, pr, inv_sigma, sys_index, clock_w, n_systems, tempering, prior_log_w,
            joint: As :func:`robust_joint` (``clock_w`` one row or a row per set).
        dirichlet_alpha: Dirichlet concentration of the pooling.
        gamma: (S, k) written: the mixture weights of each set.

    Returns:
        (S,) log-sum-exp of each set's joint.
    """
    s_count, n = sets.shape[0], sets.shape[1]
    k = pr.shape[0]
    r = np.empty((k, BLOCK))
    xyz = np.empty((3, BLOCK))
    clock = np.empty((max(n_systems, 1), BLOCK))
    a_max = np.empty(BLOCK)
    acc = np.empty(BLOCK)
    total = np.empty(s_count)
    norm = 1.0 + k * (dirichlet_alpha - 1.0)
    shared = clock_w.shape[0] == 1
    for s in range(s_count):
        points = sets[s]
        clock_ws = clock_w[0] if shared else clock_w[s]
        for j in range(k):
            gamma[s, j] = 0.0
        for second in range(2):
            for start in range(0, n, BLOCK):
                m = min(BLOCK, n - start)
                _block_residuals(points, start, m, sv, pr, sys_index, clock_ws, n_systems,
                                 xyz, r, clock)
                # a = -z^2 / 2 in place; the largest per particle is the shift.
                for b in range(m):
                    a_max[b] = -np.inf
                    acc[b] = 0.0
                for j in range(k):
                    isg = inv_sigma[j]
                    for b in range(m):
                        zj = r[j, b] * isg
                        r[j, b] = -0.5 * zj * zj
                        a_max[b] = max(a_max[b], r[j, b])
                if second == 0:
                    # E-step votes, pooled by prior weight.
                    for j in range(k):
                        for b in range(m):
                            r[j, b] = elementary.exp(r[j, b] - a_max[b])
                            acc[b] += r[j, b]
                    for b in range(m):
                        acc[b] = math.exp(prior_log_w[start + b]) / acc[b]
                    for j in range(k):
                        g = 0.0
                        for b in range(m):
                            g += acc[b] * r[j, b]
                        gamma[s, j] += g
                else:
                    for j in range(k):
                        scale = gamma[s, j] * inv_sigma[j]
                        for b in range(m):
                            acc[b] += scale * elementary.exp(r[j, b] - a_max[b])
                    for b in range(m):
                        joint[s, start + b] = prior_log_w[start + b] + tempering * (
                            a_max[b] + math.log(acc[b]) - LOG_SQRT_2PI)
            if second == 0:
                for j in range(k):
                    gamma[s, j] = (gamma[s, j] + dirichlet_alpha - 1.0) / norm
        total[s] = _log_sum_exp(joint[s])
    return total


@kernel
def clock_inlier_weights(residual_m, sigma_m, sys_index, n_systems, spread_m, iterations):
    """Robust per-constellation clock at one point; returns (k,) satellite weights.

    For each constellation every satellite's residual is a clock candidate; the one with
    the most support under a Gaussian kernel wins, then ``iterations`` mean-shift steps
    refine it (a Welsch M-estimator). The kernel width is the measurement noise widened by
    the reference point's position uncertainty ``spread_m``. Weights sum to one within a
    constellation.
    """
    k = residual_m.shape[0]
    width = np.empty(k)
    for j in range(k):
        width[j] = math.sqrt(sigma_m[j] * sigma_m[j] + spread_m * spread_m)
    weights = np.zeros(k)
    for c in range(n_systems):
        best, best_support = -1, -1.0
        for a in range(k):
            if sys_index[a] != c:
                continue
            support = 0.0
            for b in range(k):
                if sys_index[b] == c:
                    u = (residual_m[a] - residual_m[b]) / width[b]
                    support += math.exp(-0.5 * u * u)
            if support > best_support:
                best, best_support = a, support
        if best < 0:
            continue
        clock = residual_m[best]
        for step in range(iterations + 1):
            num = 0.0
            den = 0.0
            for j in range(k):
                if sys_index[j] == c:
                    u = (residual_m[j] - clock) / width[j]
                    w = math.exp(-0.5 * u * u) / (width[j] * width[j])
                    weights[j] = w
                    num += w * residual_m[j]
                    den += w
            if step < iterations:
                clock = num / den
            else:
                for j in range(k):
                    if sys_index[j] == c:
                        weights[j] /= den
    return weights


@kernel
def clock_weights_at(sv_enu, pr, centre, sigma, sys_index, n_systems, spread_m, iterations):
    """:func:`clock_inlier_weights` of the residuals ``pr - |sv_enu - centre|`` (k,) at a
    point (``core.gnss.clock_weights``), each range numpy's ``sqrt(add.reduce(d * d,
    axis=1))``: the squares summed left to right. An epoch asks at three points; the
    residuals were five numpy calls before the kernel, more than their arithmetic."""
    k = pr.shape[0]
    residual = np.empty(k)
    for j in range(k):
        dx = sv_enu[j, 0] - centre[0]
        dy = sv_enu[j, 1] - centre[1]
        dz = sv_enu[j, 2] - centre[2]
        residual[j] = pr[j] - math.sqrt((dx * dx + dy * dy) + dz * dz)
    return clock_inlier_weights(residual, sigma, sys_index, n_systems, spread_m, iterations)


@kernel
def relative_views(sets, sv, pr, sys_index, n_systems, clock_w):
    """The float32 likelihood's views of an epoch (``core.gnss.relative_geometry``): from
    the centre of every 32nd particle of all (S, N, >= 3) sets (``clock_w`` (1, k)), or of
    each set alone (``clock_w`` (S, k), a row per set).

    numpy's arithmetic, operation for operation (the centre a sum in particle order, the
    squared range as numpy's ``einsum`` adds it: east and up first).

    Returns:
        ``(centre (G, 3), unit (G, k, 3), base (G, k), half_inv_range (G, k), closest
        (G,) range from the centre to the nearest satellite, finite)``: ``finite`` False
        when a centre is not finite (then the other values of that view are undefined).
    """
    n_sets, n = sets.shape[0], sets.shape[1]
    views = clock_w.shape[0]
    step = max(1, n // 32)
    k = sv.shape[0]
    centre = np.zeros((views, 3))
    unit = np.empty((views, k, 3))
    base = np.empty((views, k))
    half_inv_range = np.empty((views, k))
    closest = np.full(views, np.inf)
    clock0 = np.empty(n_systems)
    for g in range(views):
        first, last = (0, n_sets) if views == 1 else (g, g + 1)
        count = 0
        for s in range(first, last):
            for i in range(0, n, step):
                for a in range(3):
                    centre[g, a] += sets[s, i, a]
                count += 1
        for a in range(3):
            centre[g, a] = centre[g, a] / count
            if not np.isfinite(centre[g, a]):
                return centre, unit, base, half_inv_range, closest, False
        clock0[:] = 0.0
        for j in range(k):
            o0, o1, o2 = sv[j, 0] - centre[g, 0], sv[j, 1] - centre[g, 1], sv[j, 2] - centre[g, 2]
            rho = math.sqrt((o0 * o0 + o2 * o2) + o1 * o1)
            unit[g, j, 0] = o0 / rho
            unit[g, j, 1] = o1 / rho
            unit[g, j, 2] = o2 / rho
            base[g, j] = pr[j] - rho
            half_inv_range[g, j] = 0.5 / rho
            closest[g] = min(closest[g], rho)
            clock0[sys_index[j]] += clock_w[g, j] * base[g, j]
        for j in range(k):
            base[g, j] = base[g, j] - clock0[sys_index[j]]
    return centre, unit, base, half_inv_range, closest, True


@kernel
def constellation_index(system):
    """Index 0..S-1 of each satellite's constellation among those with at least two
    satellites, in increasing system order, -1 for a constellation of one; and S."""
    k = system.shape[0]
    index = np.full(k, -1, dtype=np.int64)
    order = np.argsort(system, kind='mergesort')
    n_systems = 0
    a = 0
    while a < k:
        b = a
        while b + 1 < k and system[order[b + 1]] == system[order[a]]:
            b += 1
        if b > a:
            for c in range(a, b + 1):
                index[order[c]] = n_systems
            n_systems += 1
        a = b + 1
    return index, n_systems


@inline_kernel
def _log_add_exp(a, b):
    """``log(e^a + e^b)`` (``np.logaddexp``), -inf for two -inf."""
    high = max(a, b)
    if high == -np.inf:
        return high
    return high + math.log1p(math.exp(-abs(a - b)))


@kernel
def learned_robust_terms(sigma, wide_share, wide_mean, wide_sd, fault_share, outlier_range_m,
                         log_scale, floor, wide_log_scale, wide_high):
    """The robust density's per-satellite terms under the learned mixture
    (``core.gnss.robust_terms`` says what they are), written into the last four (k,)
    arrays; returns the largest ``|log|`` of a single density (its largest value or its
    floor). A dozen numpy calls on a dozen values each cost more than their arithmetic."""
    log_floor = math.log(fault_share / outlier_range_m) if fault_share > 0.0 else -np.inf
    per_term = 1e-3
    for j in range(sigma.shape[0]):
        floor[j] = fault_share / outlier_range_m
        # Flat part plus the two half-Gaussian ends carry the component's weight.
        wide_high[j] = wide_mean[j] + 2.0 * wide_sd[j]
        wide_log_scale[j] = (math.log(wide_share[j])
                             - math.log(wide_high[j] + math.sqrt(2.0 * math.pi) * sigma[j]))
        log_scale[j] = (math.log(1.0 - wide_share[j] - fault_share) - math.log(sigma[j])
                        - LOG_SQRT_2PI)
        # Every density lies between its floor and the sum of its scales and its floor.
        largest = _log_add_exp(_log_add_exp(log_scale[j], wide_log_scale[j]), log_floor)
        per_term = max(per_term, abs(log_floor), abs(largest))
    return per_term
