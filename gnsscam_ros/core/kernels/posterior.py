"""Posterior statistics of the integrity risk (paper §6): moments, hazard mass, level.

The M posteriors of an epoch share the particles of S motion samples: posterior j is the
sample ``index[j]`` displaced by ``-offsets[j]`` (``core.integrity.PosteriorSet``). Weight
arrays are (S, N), or (1, N) when every sample has the same weights (the priors).

* :func:`pooled_moments` -- mean and covariance of the pooled mixture of the posteriors
  and, in the same pass, of the priors (same positions, prior weights), one pass per
  sample about a reference particle (relative coordinates: no cancellation), and their
  Gaussian KL divergence.
* :func:`hazard_and_level` -- the distances of all M * N posterior particles from the
  estimate (kept in a buffer), the hazard masses at the alert radii and the protection
  level: the smallest value in ``{0} ∪ {distances}`` with pooled mass strictly beyond it
  at most ``q_max``. A weighted histogram finds the bin where the tail mass crosses
  ``q_max`` (refined while that bin holds many particles), and only that bin is sorted;
  ties (frequent after resampling) form one value, so the level does not depend on their
  order.
* :func:`bernoulli_gap` and :func:`max_empirical_risk` -- the exact inverse of the
  Bernoulli KL by scalar bisection (the per-epoch arrays hold 1-3 values).
"""
from __future__ import annotations

import math

import numpy as np

from . import inline_kernel, kernel
from .elementary import exp, largest

#: Bins of the tail-mass histogram of the protection level.
LEVEL_BINS = 2048
#: (row, column) of the packed symmetric 3 x 3 entries (xx, xy, xz, yy, yz, zz).
_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
#: The crossing bin is sorted once it holds at most this many particles (else it is
#: split into LEVEL_BINS bins again).
LEVEL_SORT_MAX = 2048
#: Distances per block of the crossing bin's gather (:func:`_gather_bin`): a block with
#: no distance near the bin is skipped on a branch-free count, where a branch per distance
#: was mispredicted on the tail's few. 32 was the fastest of 16-256 at the default
#: configuration's 200 x 4000 distances (the gather 0.95 -> 0.61 ms, the level 1.80 ->
#: 1.45 ms). Computing the histogram's bins a block at a time as well made it slower.
LEVEL_BLOCK = 32


@kernel
def exp_weights(log_w, out):
    """``out = exp(log_w)`` for (R, N) arrays (0 for -inf)."""
    for r in range(log_w.shape[0]):
        row, dest = log_w[r], out[r]
        for i in range(row.shape[0]):
            dest[i] = exp(row[i])


@kernel
def _set_sums(x, y, z, w_a, w_b, pair, ref, sums_a, sums_b):
    """Per sample s and weights a (and b when ``pair``): ``sums[s] = (W, sum w r (3),
    sum w r r^T (xx, xy, xz, yy, yz, zz))`` with ``r = x - ref``; weights have S rows or
    one shared row. One pass over the positions for both (each sum adds in particle
    order, as two passes would)."""
    shared_a, shared_b = w_a.shape[0] == 1, w_b.shape[0] == 1
    n_sets = x.shape[0]
    for s in range(n_sets):
        # ``pair`` is passed as a constant so that the inlined loop is compiled without the
        # second set of sums when it is not wanted.
        if pair:
            _moment_sums(x[s], y[s], z[s], ref, w_a[0] if shared_a else w_a[s], sums_a[s],
                         w_b[0] if shared_b else w_b[s], sums_b[s], True)
        else:
            _moment_sums(x[s], y[s], z[s], ref, w_a[0] if shared_a else w_a[s], sums_a[s],
                         w_a[0] if shared_a else w_a[s], sums_b[s], False)


@inline_kernel
def _moment_sums(xs, ys, zs, ref, w, out, v, out_v, pair):
    """``out = (sum w, sum w r (3), sum w r r^T (6))`` of the positions relative to
    ``ref``, ``r = (xs, ys, zs) - ref``; the same under the weights ``v`` into ``out_v``
    when ``pair``.

    The two sets of accumulators are written out, not a loop over the weights: scalars
    stay in registers, and one pass over the positions serves both."""
    s_w = s0 = s1 = s2 = 0.0
    e00 = e01 = e02 = e11 = e12 = e22 = 0.0
    t_w = t0 = t1 = t2 = 0.0
    f00 = f01 = f02 = f11 = f12 = f22 = 0.0
    ref0, ref1, ref2 = ref[0], ref[1], ref[2]
    for i in range(xs.shape[0]):
        r0, r1, r2 = xs[i] - ref0, ys[i] - ref1, zs[i] - ref2
        wi = w[i]
        w0, w1, w2 = wi * r0, wi * r1, wi * r2
        s_w += wi
        s0 += w0
        s1 += w1
        s2 += w2
        e00 += w0 * r0
        e01 += w0 * r1
        e02 += w0 * r2
        e11 += w1 * r1
        e12 += w1 * r2
        e22 += w2 * r2
        if pair:
            vi = v[i]
            v0, v1, v2 = vi * r0, vi * r1, vi * r2
            t_w += vi
            t0 += v0
            t1 += v1
            t2 += v2
            f00 += v0 * r0
            f01 += v0 * r1
            f02 += v0 * r2
            f11 += v1 * r1
            f12 += v1 * r2
            f22 += v2 * r2
    out[0], out[1], out[2], out[3] = s_w, s0, s1, s2
    out[4], out[5], out[6], out[7], out[8], out[9] = e00, e01, e02, e11, e12, e22
    if pair:
        out_v[0], out_v[1], out_v[2], out_v[3] = t_w, t0, t1, t2
        out_v[4], out_v[5], out_v[6], out_v[7], out_v[8], out_v[9] = (f00, f01, f02, f11,
                                                                      f12, f22)


@kernel
def _pool(sums, ref, index, offsets, mean, cov):
    """Mean and covariance of the equal-share mixture of the M posteriors from the
    per-sample sums: each sample's moments ``mean_s = sum w x``,
    ``cov_s = sum w (x - mean_s)(x - mean_s)^T`` (weights as given), component means
    ``mean_s - offset_j``, and the covariance of the mixture (within plus between).
    Covariances are packed as (xx, xy, xz, yy, yz, zz)."""
    n_sets, n_post = sums.shape[0], index.shape[0]
    u = np.empty((n_sets, 3))              # mean_s - ref
    c = np.empty((n_sets, 6))
    for s in range(n_sets):
        s_w = sums[s, 0]
        for a in range(3):
            u[s, a] = (s_w - 1.0) * ref[a] + sums[s, 1 + a]
        for k in range(6):
            a, b = _PAIRS[k]
            c[s, k] = (sums[s, 4 + k] - u[s, a] * sums[s, 1 + b] - sums[s, 1 + a] * u[s, b]
                       + s_w * u[s, a] * u[s, b])
    centre = np.zeros(3)
    for j in range(n_post):
        for a in range(3):
            centre[a] += u[index[j], a] - offsets[j, a]
    for a in range(3):
        centre[a] /= n_post
    packed = np.zeros(6)
    d = np.empty(3)
    for j in range(n_post):
        s = index[j]
        for a in range(3):
            d[a] = u[s, a] - offsets[j, a] - centre[a]
        for k in range(6):
            a, b = _PAIRS[k]
            packed[k] += c[s, k] + d[a] * d[b]
    for k in range(6):
        a, b = _PAIRS[k]
        cov[a, b] = cov[b, a] = packed[k] / n_post
    for a in range(3):
        mean[a] = ref[a] + centre[a]


@kernel
def _cholesky3(a, floor):
    """Lower Cholesky factor of ``a + floor I`` (3 x 3)."""
    low = np.zeros((3, 3))
    for i in range(3):
        for j in range(i + 1):
            v = a[i, j] + (floor if i == j else 0.0)
            for k in range(j):
                v -= low[i, k] * low[j, k]
            low[i, j] = math.sqrt(v) if i == j else v / low[j, j]
    return low


@kernel
def gaussian_kl(mean0, cov0, mean1, cov1, floor):
    """KL(N0 || N1) of 3D Gaussians with ``floor`` added to both diagonals [nats]
    (Cholesky factors; plain loops, no BLAS)."""
    l0 = _cholesky3(cov0, floor)
    l1 = _cholesky3(cov1, floor)
    # li = L1^-1 (lower triangular); inv1 = li^T li.
    li = np.zeros((3, 3))
    for i in range(3):
        li[i, i] = 1.0 / l1[i, i]
        for j in range(i):
            v = 0.0
            for k in range(j, i):
                v -= l1[i, k] * li[k, j]
            li[i, j] = v / l1[i, i]
    inv1 = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            for k in range(3):
                inv1[i, j] += li[k, i] * li[k, j]
    trace = maha = 0.0
    for i in range(3):
        for k in range(3):
            trace += inv1[i, k] * (cov0[k, i] + (floor if k == i else 0.0))
            maha += (mean1[i] - mean0[i]) * inv1[i, k] * (mean1[k] - mean0[k])
    logdet0 = 2.0 * (math.log(l0[0, 0]) + math.log(l0[1, 1]) + math.log(l0[2, 2]))
    logdet1 = 2.0 * (math.log(l1[0, 0]) + math.log(l1[1, 1]) + math.log(l1[2, 2]))
    return 0.5 * (trace + maha - 3.0 + logdet1 - logdet0)


@kernel
def pooled_moments(x, y, z, w_a, index_a, offsets_a, w_b, index_b, offsets_b, pair,
                   floor):
    """Pooled moments of posteriors a (and priors b when ``pair``) and KL(a || b).

    Args:
        x, y, z: (S, N) particle positions, east, north, up [m].
        w_a, w_b: (S, N) or (1, N) weights.
        index_a, index_b: (M,) sample of each posterior.
        offsets_a, offsets_b: (M, 3) displacement of each posterior [m].
        pair: Compute b and the divergence as well.
        floor: Diagonal floor of the Gaussian KL [m^2].

    Returns:
        ``(mean_a (3,), cov_a (3, 3), mean_b, cov_b, kl)``; without ``pair`` b repeats a
        and kl is 0.
    """
    ref = np.array([x[0, 0], y[0, 0], z[0, 0]])
    n_sets = x.shape[0]
    sums_a, sums_b = np.empty((n_sets, 10)), np.empty((n_sets, 10))
    _set_sums(x, y, z, w_a, w_b, pair, ref, sums_a, sums_b)
    mean_a, cov_a = np.empty(3), np.empty((3, 3))
    _pool(sums_a, ref, index_a, offsets_a, mean_a, cov_a)
    if not pair:
        return mean_a, cov_a, mean_a, cov_a, 0.0
    mean_b, cov_b = np.empty(3), np.empty((3, 3))
    _pool(sums_b, ref, index_b, offsets_b, mean_b, cov_b)
    return mean_a, cov_a, mean_b, cov_b, gaussian_kl(mean_a, cov_a, mean_b, cov_b, floor)


@inline_kernel
def _relative(x, y, z, centre, dims):
    """``r = x - centre`` of every particle, (dims, S, N)."""
    n_sets, n = x.shape
    rel = np.empty((dims, n_sets, n))
    c0, c1 = centre[0], centre[1]
    c2 = centre[2] if dims == 3 else 0.0
    for s in range(n_sets):
        xs, ys, zs, rx, ry = x[s], y[s], z[s], rel[0, s], rel[1, s]
        if dims == 3:
            rz = rel[2, s]
            for i in range(n):
                rx[i] = xs[i] - c0
                ry[i] = ys[i] - c1
                rz[i] = zs[i] - c2
        else:
            for i in range(n):
                rx[i] = xs[i] - c0
                ry[i] = ys[i] - c1
    return rel


@inline_kernel
def _row_distances(rel, s, offset, dims, dest):
    """``dest[i] = |r_si - offset|`` over the first ``dims`` axes (:func:`_relative`)."""
    rx, ry = rel[0, s], rel[1, s]
    ox, oy = offset[0], offset[1]
    if dims == 3:
        rz, oz = rel[2, s], offset[2]
        for i in range(dest.shape[0]):
            dx, dy, dz = rx[i] - ox, ry[i] - oy, rz[i] - oz
            dest[i] = math.sqrt(dx * dx + dy * dy + dz * dz)
    else:
        for i in range(dest.shape[0]):
            dx, dy = rx[i] - ox, ry[i] - oy
            dest[i] = math.sqrt(dx * dx + dy * dy)


@kernel
def distances(x, y, z, index, offsets, centre, dims, out):
    """``out[j, i] = |x_si - centre - offsets_j|`` over the first ``dims`` axes (2 or 3),
    ``s = index[j]``: ``r = x - centre`` once per particle, then ``r - offset_j``."""
    rel = _relative(x, y, z, centre, dims)
    for j in range(index.shape[0]):
        _row_distances(rel, index[j], offsets[j], dims, out[j])


@kernel
def _sift_down(keys, payload, root, end):
    """Restore the max-heap below ``root`` within ``[0, end)``, moving both arrays."""
    while True:
        child = 2 * root + 1
        if child >= end:
            return
        if child + 1 < end and keys[child + 1] > keys[child]:
            child += 1
        if keys[root] >= keys[child]:
            return
        keys[root], keys[child] = keys[child], keys[root]
        payload[root], payload[child] = payload[child], payload[root]
        root = child


@kernel
def _sort_pairs(keys, payload):
    """Sort ``keys`` ascending in place, ``payload`` along (heap sort: O(n log n), no
    extra memory, small to compile)."""
    n = keys.shape[0]
    for root in range(n // 2 - 1, -1, -1):
        _sift_down(keys, payload, root, n)
    for end in range(n - 1, 0, -1):
        keys[0], keys[end] = keys[end], keys[0]
        payload[0], payload[end] = payload[end], payload[0]
        _sift_down(keys, payload, 0, end)


@kernel
def _walk(values, weights, base, q_mass):
    """Smallest value v among ``values`` (or below them) with ``base`` + the mass of the
    values strictly above v at most ``q_mass``; ``base`` (the mass beyond all of them) is
    at most ``q_mass``. Returns ``(level, exhausted)``: exhausted when even the smallest
    value's whole group fits, i.e. the level lies below every value given. Sorts both
    arrays in place."""
    _sort_pairs(values, weights)
    idx = values.shape[0] - 1
    level = values[idx]
    acc = base
    while True:
        v = values[idx]
        while idx >= 0 and values[idx] == v:
            acc += weights[idx]
            idx -= 1
        if acc > q_mass:
            return level, False
        if idx < 0:
            return level, True
        level = values[idx]


@kernel
def _crossing(hist, base, q_mass):
    """Highest bin b whose mass plus all above it exceeds ``q_mass`` and the mass above
    it; -1 when no bin does."""
    acc = base
    for b in range(hist.shape[0] - 1, -1, -1):
        if acc + hist[b] > q_mass:
            return b, acc
        acc += hist[b]
    return -1, acc


@kernel
def _gather_bin(dist, w, index, scale, b_cross, values, weights):
    """Distances (M, N) of histogram bin ``b_cross`` (``min(int(d * scale), LEVEL_BINS -
    1)``) and their weights into ``values`` and ``weights``, in order; returns how many,
    or -1 when they do not fit.

    Only the distances within a bin's width of the bin take the bin arithmetic (rounding
    moves none further); the others, nearly all, pass on two comparisons, counted a block
    of ``LEVEL_BLOCK`` at a time without a branch (a block with none near is skipped).
    """
    m, n = dist.shape
    shared = w.shape[0] == 1
    top_bin = LEVEL_BINS - 1
    low, high = (b_cross - 1) / scale, (b_cross + 2) / scale
    capacity = values.shape[0]
    k = 0
    for j in range(m):
        row, wr = dist[j], w[0] if shared else w[index[j]]
        for start in range(0, n, LEVEL_BLOCK):
            end = min(start + LEVEL_BLOCK, n)
            near = 0
            for i in range(start, end):
                near += (row[i] >= low) & (row[i] < high)
            if near == 0:
                continue
            for i in range(start, end):
                d = row[i]
                if d >= low and d < high and min(int(d * scale), top_bin) == b_cross:
                    if k == capacity:
                        return -1
                    values[k] = d
                    weights[k] = wr[i]
                    k += 1
    return k


@kernel
def tail_level(dist, w, index, q_mass, d_max):
    """Protection level over ``dist`` (M, N) with weights ``w[index[j]]`` (rows of S or a
    shared row): the smallest v in ``{0} ∪ {dist}`` whose mass strictly beyond v is at
    most ``q_mass`` (> 0; weights and ``q_mass`` in the same unit); ``d_max`` is the
    largest distance (negative: not known yet)."""
    m, n = dist.shape
    shared = w.shape[0] == 1
    if d_max < 0.0:
        for j in range(m):
            row = dist[j]
            for i in range(n):
                d_max = max(d_max, row[i])
    if d_max <= 0.0:
        return 0.0
    hist = np.zeros(LEVEL_BINS)
    scale = LEVEL_BINS / d_max
    top_bin = LEVEL_BINS - 1
    for j in range(m):
        row, wr = dist[j], w[0] if shared else w[index[j]]
        for i in range(n):
            b = min(int(row[i] * scale), top_bin)
            hist[b] += wr[i]
    b_cross, base = _crossing(hist, 0.0, q_mass)
    if b_cross < 0:
        return 0.0                     # all the mass (so all beyond 0) is within q_mass
    count = np.zeros(LEVEL_BINS, dtype=np.int64)
    if True:
        # Gather the crossing bin (in the histogram's order and by its bin arithmetic).
        # Its size is not known: a count per bin cost a third of the histogram pass. A
        # guess of its size is nearly always enough; where not, room for every distance.
        values, weights = np.empty(4 * LEVEL_SORT_MAX), np.empty(4 * LEVEL_SORT_MAX)
        k = _gather_bin(dist, w, index, scale, b_cross, values, weights)
        if k < 0:
            values, weights = np.empty(m * n), np.empty(m * n)
            k = _gather_bin(dist, w, index, scale, b_cross, values, weights)
        values, weights = values[:k], weights[:k]
        # Split a crowded bin again until its crossing bin is small (or one value).
        while values.shape[0] > LEVEL_SORT_MAX:
            lo, hi = values.min(), values.max()
            if lo == hi:
                break
            hist[:] = 0.0
            count[:] = 0
            scale = LEVEL_BINS / (hi - lo)
            for i in range(values.shape[0]):
                b = min(int((values[i] - lo) * scale), top_bin)
                hist[b] += weights[i]
                count[b] += 1
            sub, base_sub = _crossing(hist, base, q_mass)
            if sub < 0:
                break                  # rounding: let the exact walk below decide
            base = base_sub
            k = 0
            for i in range(values.shape[0]):
                if min(int((values[i] - lo) * scale), top_bin) == sub:
                    values[k] = values[i]
                    weights[k] = weights[i]
                    k += 1
            values, weights = values[:k].copy(), weights[:k].copy()
        level, exhausted = _walk(values, weights, base, q_mass)
        if not exhausted:
            return level
    # The sums of the bins and of the sorted values rounded differently: a full sort.
    values = np.empty(m * n)
    weights = np.empty(m * n)
    for j in range(m):
        row, wr = dist[j], w[0] if shared else w[index[j]]
        for i in range(n):
            values[j * n + i] = row[i]
            weights[j * n + i] = wr[i]
    level, exhausted = _walk(values, weights, 0.0, q_mass)
    return 0.0 if exhausted else level


@kernel
def hazard_and_level(x, y, z, w, index, offsets, centre, dims, radii, q_mass, want_level,
                     masses):
    """Hazard masses and protection level of the M posteriors around ``centre``.

    Args:
        x, y, z: (S, N) particle positions, east, north, up (z unused when
            ``dims`` is 2) [m].
        w: (S, N) or (1, N) weights of the samples.
        index: (M,) sample of each posterior.
        offsets: (M, >= dims) displacement of each posterior [m].
        centre: (3,) the estimate [m].
        dims: 2 (horizontal) or 3.
        radii: (A,) alert radii [m].
        q_mass: M times the largest admissible empirical risk (> 0 with ``want_level``).
        want_level: Compute the level (else it is returned as inf).
        masses: (A,) output: the mean over the posteriors of the mass at or beyond each
            radius, clipped to [0, 1].

    Returns:
        The protection level [m].
    """
    m, n = index.shape[0], x.shape[1]
    shared = w.shape[0] == 1
    dist = np.empty((m, n))
    # Each posterior's distances (:func:`distances`), then their masses while they are in
    # the cache.
    rel = _relative(x, y, z, centre, dims)
    n_radii = radii.shape[0]
    total = np.zeros(n_radii)
    d_max = 0.0
    stop = n - n % 4
    for j in range(m):
        row, wr = dist[j], w[0] if shared else w[index[j]]
        _row_distances(rel, index[j], offsets[j], dims, row)
        # Branch-free (the comparisons are unpredictable): four partial sums per radius.
        for a in range(n_radii):
            r = radii[a]
            p0 = p1 = p2 = p3 = 0.0
            for i in range(0, stop, 4):
                p0 += wr[i] * (row[i] >= r)
                p1 += wr[i + 1] * (row[i + 1] >= r)
                p2 += wr[i + 2] * (row[i + 2] >= r)
                p3 += wr[i + 3] * (row[i + 3] >= r)
            for i in range(stop, n):
                p0 += wr[i] * (row[i] >= r)
            total[a] += (p0 + p1) + (p2 + p3)
        if want_level:
            d_max = max(d_max, largest(row, 0.0))
    for a in range(n_radii):
        masses[a] = min(max(total[a] / m, 0.0), 1.0)
    if not want_level:
        return np.inf
    return tail_level(dist, w, index, q_mass, d_max)


@kernel
def _bernoulli_kl(q, p):
    """``kl(q || p)`` with p clipped to [1e-300, 1 - 1e-16] [nats]."""
    p = min(max(p, 1e-300), 1.0 - 1e-16)
    out = q * math.log(q / p) if q > 0.0 else 0.0
    return out + ((1.0 - q) * math.log((1.0 - q) / (1.0 - p)) if q < 1.0 else 0.0)


@kernel
def bernoulli_gap(q, eps, iterations, out):
    """``out[i] = t >= 0`` with ``kl(q_i || q_i + t) = eps_i``: bisection on ``[q_i, 1]``
    (``eps`` of one value applies to every ``q_i``)."""
    one = eps.shape[0] == 1
    for i in range(q.shape[0]):
        lo, hi = q[i], 1.0
        budget = eps[0] if one else eps[i]
        for _ in range(iterations):
            mid = 0.5 * (lo + hi)
            if _bernoulli_kl(q[i], mid) > budget:
                hi = mid
            else:
                lo = mid
        out[i] = 0.5 * (lo + hi) - q[i]


@kernel
def max_empirical_risk(target, eps, iterations):
    """Largest q with ``kl(q || target) >= eps`` (0 when even q = 0 falls short)."""
    if -math.log1p(-target) < eps:
        return 0.0
    lo, hi = 0.0, target
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        if _bernoulli_kl(mid, target) >= eps:
            lo = mid
        else:
            hi = mid
    return lo


def warm_up() -> None:
    """Compile (or load from the disk cache) the kernels for the argument types of
    ``core.integrity`` on a tiny input (coordinates are strided (S, N) views of the
    particles, whatever the particle array)."""
    particles = np.zeros((2, 4, 4))
    particles[:, :, 0] = np.arange(4.0)
    log_w = np.full((2, 4), -math.log(4.0))
    w = np.empty((2, 4))
    exp_weights(log_w, w)
    index = np.arange(2, dtype=np.int64)
    offsets = np.zeros((2, 3))
    centre = np.zeros(3)
    radii = np.array([1.0, 2.0])
    masses = np.empty(2)
    x, y, z = particles[..., 0], particles[..., 1], particles[..., 2]
    pooled_moments(x, y, z, w, index, offsets, w[:1], index, offsets, True, 1e-2)
    for dims in (2, 3):
        hazard_and_level(x, y, z, w, index, offsets, centre, dims, radii, 0.1, True, masses)
        distances(x, y, z, index, offsets, centre, dims, np.empty((2, 4)))
    tail_level(np.zeros((2, 4)), w, index, 0.1, -1.0)
    bernoulli_gap(np.zeros(1), np.ones(1), 64, np.empty(1))
    max_empirical_risk(0.1, 0.05, 60)
