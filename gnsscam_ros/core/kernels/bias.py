"""The bias hypotheses' small linear algebra (``core.bias``) in one call each.

Per epoch the bound moves M offsets through the GNSS update and shrinks them to what the
particle sets do not already hold: a dozen 3 x 3 to 6 x 6 matrix operations and M x k
products. In numpy each was a call of microseconds (about 0.19 ms an epoch at M = 200,
twelve satellites); here they run in one call each.

Each step is numpy's arithmetic, operation for operation: products through ``np.dot``
(the BLAS calls numpy's ``@`` makes), inverses through LAPACK's ``gesv`` on the identity
(numpy's ``inv``), the pseudo-inverse as numpy's ``pinv`` forms it, ``eigh`` as numpy's.
The offsets are numpy's to the bit (``test/oracles.py`` holds the numpy forms). That
matters even though only the bound uses them: they carry over from epoch to epoch, and a
difference in the last bits (products in plain loops) grew to 3e-5 of a protection level
over the smartLoc drive with GLONASS alone, and changed one epoch's verdict.
One product numpy makes differently, ``g^T g`` of a matrix with itself (BLAS ``syrk``),
is left to the caller.
"""
from __future__ import annotations

import numpy as np

from . import kernel

#: Stamp of a row of the bias table taken for a satellite whose bias is not drawn yet.
NEW_ROW_NS = np.iinfo(np.int64).min
#: ``rcond`` of numpy's ``pinv`` (its default): singular values up to this share of the
#: largest count as zero.
PINV_RCOND = 1e-15


@kernel
def _eigh(matrix):
    """numpy's ``eigh`` (values, vectors), in numpy's (C) layout: the layout decides how
    BLAS is called on a result, and with it the rounding of a product (so for every
    LAPACK result here)."""
    values, vectors = np.linalg.eigh(matrix)
    return values, np.ascontiguousarray(vectors)


@kernel
def _inverse(matrix):
    """numpy's ``inv``: LAPACK ``gesv`` on the identity, in numpy's (C) layout."""
    return np.ascontiguousarray(np.linalg.solve(matrix, np.eye(matrix.shape[0])))


@kernel
def _pseudo_inverse(matrix):
    """numpy's ``pinv``: SVD, singular values up to ``PINV_RCOND`` of the largest
    dropped."""
    u, s, vt = np.linalg.svd(matrix, full_matrices=False)
    u, vt = np.ascontiguousarray(u), np.ascontiguousarray(vt)
    cutoff = PINV_RCOND * s.max()
    inverse = np.zeros_like(s)
    for c in range(s.shape[0]):
        if s[c] > cutoff:
            inverse[c] = 1.0 / s[c]
    return np.dot(vt.T, inverse.reshape(-1, 1) * u.T)


@kernel
def psd_part(matrix):
    """The positive part of the symmetric part of a square matrix (its eigenvalues below
    zero set to zero)."""
    values, vectors = _eigh(0.5 * (matrix + matrix.T))
    return np.dot(vectors * np.maximum(values, 0.0), vectors.T)


@kernel
def _onehot(sys_index, n_systems):
    onehot = np.zeros((sys_index.shape[0], n_systems))
    for i in range(sys_index.shape[0]):
        onehot[i, sys_index[i]] = 1.0
    return onehot


@kernel
def leverages(line_of_sight, weights, sys_index, n_systems):
    """Diagonal of the weighted least-squares hat matrix (``core.bias.leverages``), (k,)."""
    k = line_of_sight.shape[0]
    design = np.empty((k, 3 + n_systems))
    design[:, :3] = -line_of_sight
    design[:, 3:] = _onehot(sys_index, n_systems)
    cov = _pseudo_inverse(np.dot(design.T, weights.reshape(-1, 1) * design))
    out = np.empty(k)
    n = design.shape[1]
    for i in range(k):
        # numpy's einsum('ij,jk,ik->i'): one sum over j then k, products left to right.
        h = 0.0
        for a in range(n):
            for b in range(n):
                h += design[i, a] * cov[a, b] * design[i, b]
        out[i] = min(max(h * weights[i], 0.0), 1.0)
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
    # Wp = W - W S (S^T W S)^-1 S^T W: the weights with each constellation's clock out.
    onehot = _onehot(sys_index, n_systems)
    ws = weights.reshape(-1, 1) * onehot
    # Each constellation's weight summed in the satellites' order (numpy's bincount), not
    # through BLAS: with one constellation numpy's product is a dot and this one a gemv,
    # which round differently on some BLAS builds (Debian 12's OpenBLAS).
    per_system = np.zeros(n_systems)
    for i in range(sys_index.shape[0]):
        per_system[sys_index[i]] += weights[i]
    per_system = np.maximum(per_system, 1e-300)
    wp = np.diag(weights) - np.dot(ws / per_system, ws.T)
    gain = np.dot(-line_of_sight.T, wp)                 # G^T Wp, G = -line of sight
    new_offsets = np.dot(np.dot(offsets, prior_info) + np.dot(gain, biases).T, cov)
    moved = np.dot(fault_offsets, prior_info)
    if fault_biases.shape[1] == biases.shape[1]:
        moved = moved + np.dot(gain, fault_biases).T
    return new_offsets, np.dot(moved, cov)


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
def beyond_cloud(offsets, fault_offsets, moment, cloud_cov, dims):
    """The offsets the bound displaces the posteriors by (``core.bias.beyond_cloud``), a
    new (M, 3) array; ``moment`` is the (dims, dims) second moment of the Gauss-Markov
    offsets ``(offsets - fault_offsets)[:, :dims]``."""
    out = offsets.copy()
    values, vectors = _eigh(moment)
    if not values[-1] > 0.0:
        return out                                  # no Gauss-Markov part to shrink
    # O^(-1/2) on the span of the offsets (a direction they never take stays at zero).
    floor = values[-1] * 1e-12
    scale = np.zeros(dims)
    for c in range(dims):
        if values[c] > floor:
            scale[c] = 1.0 / np.sqrt(max(values[c], floor))
    inv_sqrt = np.dot(vectors * scale, vectors.T)
    excess = psd_part(moment - cloud_cov[:dims, :dims])
    ex_values, ex_vectors = _eigh(excess)
    ex_sqrt = np.dot(ex_vectors * np.sqrt(np.maximum(ex_values, 0.0)), ex_vectors.T)
    gm = np.ascontiguousarray((offsets - fault_offsets)[:, :dims])   # np.dot would copy
    out[:, :dims] = fault_offsets[:, :dims] + np.dot(gm, np.dot(ex_sqrt, inv_sqrt).T)
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
        beyond_cloud(offsets, 0.5 * offsets, np.eye(dims), np.eye(3), dims)
