"""The bias hypotheses' small linear algebra (``core.bias``) in one call each.

Per epoch the bound moves M offsets through the GNSS update and shrinks them to what the
particle sets do not already hold: a dozen 3 x 3 to 8 x 8 matrix operations and M x k
products. In numpy each was a call of microseconds (about 0.19 ms an epoch at M = 200,
twelve satellites); here they run in one call each. The matrices are small and
symmetric, so they are decomposed here (cyclic Jacobi rotations for the eigenvalues,
Cholesky for the inverse of a covariance) and multiplied in plain loops: LAPACK's and
BLAS's routines, called from a kernel, cost several microseconds each in an epoch (their
setup, their code out of the cache) for arithmetic of a few hundred operations, and an
epoch made nine of them (0.07 ms at N = 120, about a tenth of it). The results agree with
numpy's forms (``test/oracles.py``) to rounding.
"""
from __future__ import annotations

import numpy as np

from . import kernel

#: Stamp of a row of the bias table taken for a satellite whose bias is not drawn yet.
NEW_ROW_NS = np.iinfo(np.int64).min
#: ``rcond`` of numpy's ``pinv`` (its default): singular values up to this share of the
#: largest count as zero.
PINV_RCOND = 1e-15


#: Jacobi sweeps at most: a symmetric matrix of up to eight rows converges in well under
#: ten; the cap only stops a matrix that is not finite.
MAX_SWEEPS = 30


@kernel
def symmetric_eigen(matrix):
    """Eigenvalues (ascending) and eigenvectors (columns, orthonormal) of the symmetric
    part of a small square matrix, by cyclic Jacobi rotations: ``(values (n,), vectors
    (n, n))``."""
    n = matrix.shape[0]
    a = np.empty((n, n))
    total = 0.0
    for i in range(n):
        for j in range(n):
            a[i, j] = 0.5 * (matrix[i, j] + matrix[j, i])
            total += a[i, j] * a[i, j]
    v = np.eye(n)
    for _ in range(MAX_SWEEPS):
        off = 0.0
        for p in range(n):
            for q in range(p + 1, n):
                off += a[p, q] * a[p, q]
        if not off > 1e-32 * total:         # converged (or zero, or not finite)
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = a[p, q]
                if apq == 0.0:
                    continue
                theta = (a[q, q] - a[p, p]) / (2.0 * apq)
                t = 1.0 / (abs(theta) + np.sqrt(theta * theta + 1.0))
                if abs(theta) > 1e150:
                    t = 0.5 / abs(theta)
                if theta < 0.0:
                    t = -t
                c = 1.0 / np.sqrt(t * t + 1.0)
                s = t * c
                for k in range(n):
                    akp, akq = a[k, p], a[k, q]
                    a[k, p] = c * akp - s * akq
                    a[k, q] = s * akp + c * akq
                for k in range(n):
                    apk, aqk = a[p, k], a[q, k]
                    a[p, k] = c * apk - s * aqk
                    a[q, k] = s * apk + c * aqk
                for k in range(n):
                    vkp, vkq = v[k, p], v[k, q]
                    v[k, p] = c * vkp - s * vkq
                    v[k, q] = s * vkp + c * vkq
    values = np.empty(n)
    for i in range(n):
        values[i] = a[i, i]
    order = np.argsort(values)
    vectors = np.empty((n, n))
    for c in range(n):
        for r in range(n):
            vectors[r, c] = v[r, order[c]]
    return values[order], vectors


@kernel
def _from_eigen(values, vectors):
    """``V diag(values) V^T``."""
    n = values.shape[0]
    out = np.zeros((n, n))
    for i in range(n):
        for j in range(i, n):
            total = 0.0
            for c in range(n):
                total += vectors[i, c] * values[c] * vectors[j, c]
            out[i, j] = total
            out[j, i] = total
    return out


@kernel
def _inverse(matrix):
    """Inverse of a symmetric positive definite matrix by Cholesky; one that is not
    (a pivot not positive) by its eigenvalues, as numpy's ``inv`` would give it; NaN for
    a matrix that is not finite (a broken state, which the filter's checks discard)."""
    n = matrix.shape[0]
    if not np.isfinite(matrix).all():
        return np.full((n, n), np.nan)
    low = np.zeros((n, n))
    for j in range(n):
        pivot = matrix[j, j]
        for c in range(j):
            pivot -= low[j, c] * low[j, c]
        if not pivot > 0.0:
            values, vectors = symmetric_eigen(matrix)
            return _from_eigen(1.0 / values, vectors)
        low[j, j] = np.sqrt(pivot)
        for i in range(j + 1, n):
            total = matrix[i, j]
            for c in range(j):
                total -= low[i, c] * low[j, c]
            low[i, j] = total / low[j, j]
    # L^-1 by forward substitution, then (L^-1)^T L^-1.
    inv_low = np.zeros((n, n))
    for j in range(n):
        inv_low[j, j] = 1.0 / low[j, j]
        for i in range(j + 1, n):
            total = 0.0
            for c in range(j, i):
                total -= low[i, c] * inv_low[c, j]
            inv_low[i, j] = total / low[i, i]
    out = np.empty((n, n))
    for i in range(n):
        for j in range(i, n):
            total = 0.0
            for c in range(max(i, j), n):
                total += inv_low[c, i] * inv_low[c, j]
            out[i, j] = total
            out[j, i] = total
    return out


@kernel
def _pseudo_inverse(matrix):
    """numpy's ``pinv`` of a symmetric matrix: eigenvalues whose size is at most
    ``PINV_RCOND`` of the largest count as zero."""
    values, vectors = symmetric_eigen(matrix)
    cutoff = PINV_RCOND * max(abs(values[0]), abs(values[-1]))
    inverse = np.zeros_like(values)
    for c in range(values.shape[0]):
        if abs(values[c]) > cutoff:
            inverse[c] = 1.0 / values[c]
    return _from_eigen(inverse, vectors)


@kernel
def psd_part(matrix):
    """The positive part of the symmetric part of a square matrix (its eigenvalues below
    zero set to zero)."""
    values, vectors = symmetric_eigen(matrix)
    return _from_eigen(np.maximum(values, 0.0), vectors)


@kernel
def _matmul(a, b):
    """``a @ b`` of small matrices, in loops."""
    n, m, p = a.shape[0], a.shape[1], b.shape[1]
    out = np.zeros((n, p))
    for i in range(n):
        for c in range(m):
            x = a[i, c]
            for j in range(p):
                out[i, j] += x * b[c, j]
    return out


@kernel
def leverages(line_of_sight, weights, sys_index, n_systems):
    """Diagonal of the weighted least-squares hat matrix (``core.bias.leverages``), (k,):
    ``h_i = w_i d_i^T (D^T W D)^+ d_i`` with the design rows ``d_i = (-l_i, e_sys(i))``."""
    k = line_of_sight.shape[0]
    n = 3 + n_systems
    design = np.zeros((k, n))
    for i in range(k):
        for a in range(3):
            design[i, a] = -line_of_sight[i, a]
        design[i, 3 + sys_index[i]] = 1.0
    info = np.zeros((n, n))
    for i in range(k):
        for a in range(n):
            x = weights[i] * design[i, a]
            for b in range(n):
                info[a, b] += x * design[i, b]
    cov = _pseudo_inverse(info)
    out = np.empty(k)
    for i in range(k):
        h = 0.0
        for a in range(n):
            for b in range(n):
                h += design[i, a] * cov[a, b] * design[i, b]
        out[i] = min(max(h * weights[i], 0.0), 1.0)
    return out


@kernel
def _system_shares(weights, sys_index, n_systems):
    """Each satellite's share of its constellation's weight, ``w_i / sum_s w``, (k,)."""
    per_system = np.zeros(n_systems)
    for i in range(weights.shape[0]):
        per_system[sys_index[i]] += weights[i]
    for c in range(n_systems):
        per_system[c] = max(per_system[c], 1e-300)
    shares = np.empty(weights.shape[0])
    for i in range(weights.shape[0]):
        shares[i] = weights[i] / per_system[sys_index[i]]
    return shares


@kernel
def _projected_gain(biases, line_of_sight, weights, shares, sys_index, n_systems):
    """``G^T Wp b`` of each hypothesis, (3, M): ``Wp`` the weights with each
    constellation's clock out (``W - W S (S^T W S)^-1 S^T W``), so that satellite i
    weighs ``w_i (b_i - bbar_s)`` with ``bbar_s`` the mean bias of its constellation
    weighted by ``shares`` (:func:`_system_shares`); ``G = -line of sight``."""
    k, m = biases.shape
    mean = np.zeros((n_systems, m))
    for i in range(k):
        for j in range(m):
            mean[sys_index[i], j] += shares[i] * biases[i, j]
    gain = np.zeros((3, m))
    for i in range(k):
        s = sys_index[i]
        for a in range(3):
            x = -line_of_sight[i, a] * weights[i]
            for j in range(m):
                gain[a, j] += x * (biases[i, j] - mean[s, j])
    return gain


@kernel
def _moved(offsets, info, gain, cov):
    """``(offsets info + gain^T) cov``, (M, 3); ``gain`` (3, M) or (3, 0): none."""
    m = offsets.shape[0]
    out = np.empty((m, 3))
    row = np.empty(3)
    for j in range(m):
        for b in range(3):
            total = 0.0
            for a in range(3):
                total += offsets[j, a] * info[a, b]
            row[b] = total + (gain[b, j] if gain.shape[1] == m else 0.0)
        for b in range(3):
            total = 0.0
            for a in range(3):
                total += row[a] * cov[a, b]
            out[j, b] = total
    return out


@kernel
def update_offsets(offsets, fault_offsets, biases, fault_biases, line_of_sight, weights,
                   sys_index, n_systems, prior_cov, posterior_cov, cov_floor):
    """Offsets and their hidden-fault part after one GNSS update (``core.bias``:
    ``o+ = P (P-^-1 o- + G^T Wp b)``), new (M, 3) arrays. ``fault_biases`` (k, M), or
    (k, 0) for none (their offsets then move by the information alone)."""
    eye = np.eye(3)
    prior_info = _inverse(prior_cov + cov_floor * eye)
    gained = psd_part(_inverse(posterior_cov + cov_floor * eye) - prior_info)
    cov = _inverse(prior_info + gained)
    shares = _system_shares(weights, sys_index, n_systems)
    gain = _projected_gain(biases, line_of_sight, weights, shares, sys_index, n_systems)
    fault_gain = (_projected_gain(fault_biases, line_of_sight, weights, shares, sys_index,
                                  n_systems)
                  if fault_biases.shape[1] == biases.shape[1] else np.zeros((3, 0)))
    return (_moved(offsets, prior_info, gain, cov),
            _moved(fault_offsets, prior_info, fault_gain, cov))


@kernel
def hidden_fault_sizes(core_sd, leverage, core_sds, largest):
    """``core.bias.hidden_fault_sizes``, (k,): ``min(c s / sqrt(max(1 - h, 1e-12)),
    largest)`` per satellite in numpy's arithmetic (a NaN stays NaN, as in np.maximum and
    np.minimum)."""
    k = core_sd.shape[0]
    out = np.empty(k)
    for i in range(k):
        room = 1.0 - leverage[i]
        if room < 1e-12:
            room = 1e-12
        unseen = core_sds * core_sd[i] / np.sqrt(room)
        out[i] = largest[i] if largest[i] < unseen or largest[i] != largest[i] else unseen
    return out


@kernel
def with_hidden_faults(biases, sizes):
    """``core.bias.with_hidden_faults``: a copy of the (k, M) biases, k > 0, with
    hypothesis j biasing satellite ``j mod k`` by ``+size`` in even rounds over the
    satellites and ``-size`` in odd ones (numpy's values; a NaN size, which the filter's
    state check resets on, may differ in its sign bit)."""
    k, m = biases.shape
    out = biases.copy()
    for j in range(m):
        s = j % k
        out[s, j] += sizes[s] if (j // k) % 2 == 0 else -sizes[s]
    return out


@kernel
def decay_exponents(stamps, rows, stamp_ns, tau):
    """``-max(dt, 0) / tau`` of each satellite's bias (numpy's arithmetic, for numpy's
    exp), ``dt = (stamp_ns - stamps[rows[i]]) * 1e-9`` [s] (0 for a row without a bias
    yet: ``NEW_ROW_NS``)."""
    k = rows.shape[0]
    out = np.zeros(k)
    for i in range(k):
        then = stamps[rows[i]]
        if then != NEW_ROW_NS:
            dt = (stamp_ns - then) * 1e-9
            out[i] = -(dt if dt > 0.0 else 0.0) / tau
    return out


@kernel
def advance_biases(table, stamps, rows, decay, sigma, draws, stamp_ns):
    """The Gauss-Markov step of the satellites' biases (``core.bias.BiasHypotheses.
    biases_at``), ``b <- phi b + sqrt(1 - phi^2) sigma xi``, in numpy's arithmetic element
    for element: ``phi`` is 0 for a row without a bias yet (``NEW_ROW_NS``), 1 for a bias
    not behind the stamp, else its ``decay`` (numpy's exp, taken by the caller).
    Satellite i's bias is row ``rows[i]`` of ``table`` (M per row), which takes the new
    bias, and of ``stamps``, which takes ``stamp_ns``. Returns the (k, M) biases, a new
    array."""
    k, m = draws.shape
    out = np.empty((k, m))
    for i in range(k):
        row = rows[i]
        then = stamps[row]
        phi = 0.0 if then == NEW_ROW_NS else (1.0 if stamp_ns <= then else decay[i])
        scale = np.sqrt(1.0 - phi * phi) * sigma[i]
        for j in range(m):
            out[i, j] = phi * table[row, j] + scale * draws[i, j]
            table[row, j] = out[i, j]
        stamps[row] = stamp_ns
    return out


@kernel
def beyond_cloud(offsets, fault_offsets, cloud_cov, dims):
    """The offsets the bound displaces the posteriors by (``core.bias.beyond_cloud``), a
    new (M, 3) array, from the (dims, dims) second moment of the Gauss-Markov offsets
    ``(offsets - fault_offsets)[:, :dims]``."""
    m = offsets.shape[0]
    out = offsets.copy()
    gm = np.empty((m, dims))
    for j in range(m):
        for a in range(dims):
            gm[j, a] = offsets[j, a] - fault_offsets[j, a]
    moment = np.zeros((dims, dims))
    for j in range(m):
        for a in range(dims):
            for b in range(dims):
                moment[a, b] += gm[j, a] * gm[j, b]
    scale_m = 1.0 / max(m, 1)
    for a in range(dims):
        for b in range(dims):
            moment[a, b] *= scale_m
    values, vectors = symmetric_eigen(moment)
    if not values[-1] > 0.0:
        return out                                  # no Gauss-Markov part to shrink
    # O^(-1/2) on the span of the offsets (a direction they never take stays at zero).
    floor = values[-1] * 1e-12
    scale = np.zeros(dims)
    for c in range(dims):
        if values[c] > floor:
            scale[c] = 1.0 / np.sqrt(max(values[c], floor))
    inv_sqrt = _from_eigen(scale, vectors)
    excess = psd_part(moment - cloud_cov[:dims, :dims])
    ex_values, ex_vectors = symmetric_eigen(excess)
    ex_sqrt = _from_eigen(np.sqrt(np.maximum(ex_values, 0.0)), ex_vectors)
    shrink = _matmul(ex_sqrt, inv_sqrt)             # g' = A g, A = ex_sqrt inv_sqrt
    for j in range(m):
        for a in range(dims):
            total = 0.0
            for b in range(dims):
                total += shrink[a, b] * gm[j, b]
            out[j, a] = fault_offsets[j, a] + total
    return out


def warm_up() -> None:
    """Compile (or load from the disk cache) the kernels for the filter's argument types
    on a tiny input (``beyond_cloud`` runs only once the error model has measured how
    long the errors persist: no warm-up drive of a few epochs reaches it)."""
    line = np.array([[0.0, 0.6, 0.8], [0.6, 0.0, 0.8], [0.0, -0.6, 0.8], [-0.6, 0.0, 0.8],
                     [0.0, 0.0, 1.0]])
    weights = np.ones(5)
    sys_index = np.zeros(5, dtype=np.int64)
    leverages(line, weights, sys_index, 1)
    offsets = np.ones((2, 3))
    biases = np.ones((5, 2))
    update_offsets(offsets, offsets, biases, biases, line, weights, sys_index, 1, np.eye(3),
                   np.eye(3), 1e-4)
    update_offsets(offsets, offsets, biases, np.empty((5, 0)), line, weights, sys_index, 1,
                   np.eye(3), np.eye(3), 1e-4)
    for dims in (2, 3):
        beyond_cloud(offsets, 0.5 * offsets, np.eye(3), dims)
