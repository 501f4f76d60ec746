"""Vocabulary tree: hierarchical k-majority clustering of binary (ORB) descriptors.

The tree is complete and B-ary with depth L. Node ``j`` of level ``l`` (0-based within the
level, levels 1..L) has children ``j*B + c`` of level ``l+1``; the root (level 0) is implicit.
Each node holds a 256-bit centre; distances are Hamming distances and centres are the bitwise
majority vote of their members (k-means for binary data: the mean of bits rounded to the
nearest vertex of the hypercube). A node that received no training descriptor is invalid and
is never chosen during quantisation, so unbalanced data just leaves holes in the tree.

Training runs level by level for all nodes of a level at once (vectorised over nodes and
descriptors), so its cost is O(iterations * n * B * L) popcounts with no Python loop over
nodes. Descriptors are handled as 4 x uint64 words for the Hamming distance.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from .features import DESCRIPTOR_BYTES

_WORDS = DESCRIPTOR_BYTES // 8      # uint64 words per descriptor
_INVALID_PENALTY = 1 << 12          # added to the distance of invalid nodes (> 256 bits)
_CHUNK = 4096                       # rows per vectorised block: temporaries stay in cache
_MAX_LEAVES = 10_000_000            # B**L limit (Nister & Stewenius used 10**6)

if hasattr(np, 'bitwise_count'):    # numpy >= 2.0: hardware popcount per uint64 word
    _bitcount = np.bitwise_count
else:                               # pragma: no cover - numpy 1.26 fallback (lookup table)
    _LUT = np.array([bin(i).count('1') for i in range(256)], dtype=np.uint8)

    def _bitcount(x64: np.ndarray) -> np.ndarray:
        b = _LUT[x64.view(np.uint8)]
        return b.reshape(x64.shape + (8,)).sum(axis=-1, dtype=np.uint8)


def _popcount4(x64: np.ndarray) -> np.ndarray:
    """Set bits of (..., 4) uint64 -> (...,) uint16, i.e. Hamming weight of 256 bits.

    Sums the four per-word counts through a uint16 view instead of ``sum(axis=-1)``:
    numpy's reduction over a length-4 axis costs ~10x more than these two vector adds,
    and this is the query hot path. Each per-word count is <= 64, so the byte-pair sums
    (<= 128) cannot carry into the neighbouring byte.
    """
    v = _bitcount(x64).view(np.uint16)          # (..., 2): byte pairs of the 4 counts
    s = v[..., 0] + v[..., 1]
    return (s & 0xFF) + (s >> 8)


def as_words(descriptors: np.ndarray) -> np.ndarray:
    """(n, 32) uint8 descriptors -> (n, 4) uint64 view (copied only if not contiguous)."""
    d = np.ascontiguousarray(descriptors, dtype=np.uint8)
    if d.ndim != 2 or d.shape[1] != DESCRIPTOR_BYTES:
        raise ValueError(f'expected (n, {DESCRIPTOR_BYTES}) uint8 descriptors, got {d.shape}')
    return d.view(np.uint64)


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distances [bits] between broadcastable (..., 32) uint8 descriptor arrays."""
    a = np.ascontiguousarray(a, dtype=np.uint8)
    b = np.ascontiguousarray(b, dtype=np.uint8)
    return _popcount4(a.view(np.uint64) ^ b.view(np.uint64)).astype(np.int32)


def _level_size(branching: int, level: int) -> int:
    return branching ** level


class VocabularyTree:
    """A trained tree; use :meth:`train` or :meth:`from_arrays` to make one.

    Attributes:
        branching: B, children per node.
        depth: L, number of levels below the root.
        centres: per level l = 1..L, (B**l, 4) uint64 centres (index l-1).
        valid: per level, (B**l,) bool, False for nodes without training data.
    """

    def __init__(self, branching: int, depth: int, centres: list[np.ndarray],
                 valid: list[np.ndarray]):
        if branching < 2 or depth < 1:
            raise ValueError(f'need branching >= 2 and depth >= 1, got {branching}, {depth}')
        if len(centres) != depth or len(valid) != depth:
            raise ValueError('one centre array and one validity mask per level expected')
        for level, (c, v) in enumerate(zip(centres, valid), start=1):
            n = _level_size(branching, level)
            if c.shape != (n, _WORDS) or c.dtype != np.uint64 or v.shape != (n,):
                raise ValueError(f'level {level}: centres {c.shape} {c.dtype}, '
                                 f'valid {v.shape}; expected ({n}, {_WORDS}) uint64')
        self.branching = int(branching)
        self.depth = int(depth)
        self.centres = [np.ascontiguousarray(c) for c in centres]
        self.valid = [np.asarray(v, dtype=bool) for v in valid]
        # Per level, centres and distance offsets grouped by parent, (B**(l-1), B, ...), so
        # that quantisation gathers one contiguous block of B children per descriptor.
        self._c3 = [c.reshape(-1, self.branching, _WORDS) for c in self.centres]
        self._pen = [_penalty(v).reshape(-1, self.branching) for v in self.valid]

    # ----------------------------------------------------------------------------- sizes
    @property
    def n_leaves(self) -> int:
        """Number of leaf slots, B**L (some may be invalid)."""
        return _level_size(self.branching, self.depth)

    @property
    def level_offsets(self) -> np.ndarray:
        """(L+1,) start of each level's block in the flat node numbering (levels 1..L)."""
        sizes = [_level_size(self.branching, lv) for lv in range(1, self.depth + 1)]
        return np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)

    @property
    def n_nodes(self) -> int:
        """Number of nodes below the root, sum of B**l for l = 1..L."""
        return int(self.level_offsets[-1])

    # ------------------------------------------------------------------------- training
    @classmethod
    def train(cls, descriptors: np.ndarray, branching: int = 10, depth: int = 5,
              iterations: int = 6, seed: int | np.random.Generator = 0,
              max_descriptors: int | None = 200_000,
              progress: Callable[[str, int, int], None] | None = None) -> 'VocabularyTree':
        """Hierarchical k-majority clustering (k-means++ seeding) of binary descriptors.

        Args:
            descriptors: (n, 32) uint8 ORB descriptors.
            branching: B, children per node (>= 2).
            depth: L, levels below the root; the tree has up to B**L leaves.
            iterations: Maximum k-majority iterations per level (stops early when no
                assignment changes).
            seed: Seed or generator; the same seed and data give the same tree.
            max_descriptors: Train on a uniform random subsample of at most this many
                descriptors (None: all); the database quantises every descriptor anyway.
            progress: optional ``progress('train', level, depth)`` after each level.

        Returns:
            The trained tree.
        """
        if branching < 2 or depth < 1:
            raise ValueError(f'need branching >= 2 and depth >= 1, got {branching}, {depth}')
        if branching ** depth > _MAX_LEAVES:
            # Node arrays are dense (B**L rows), so guard against a typo eating the RAM.
            raise ValueError(f'branching**depth = {branching ** depth} leaves exceeds '
                             f'{_MAX_LEAVES}')
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        x8 = np.ascontiguousarray(descriptors, dtype=np.uint8)
        if x8.ndim != 2 or x8.shape[1] != DESCRIPTOR_BYTES or x8.shape[0] == 0:
            raise ValueError(f'expected (n>0, {DESCRIPTOR_BYTES}) uint8 descriptors, '
                             f'got {x8.shape}')
        if max_descriptors is not None and x8.shape[0] > max_descriptors:
            keep = np.sort(rng.choice(x8.shape[0], size=max_descriptors, replace=False))
            x8 = x8[keep]
        x64 = x8.view(np.uint64)
        # Unpacked bits for the majority vote, as contiguous float32 blocks of 64 bits
        # (the sparse product wants float; slicing + casting per iteration costs more than
        # the product itself). 1 KiB per training descriptor.
        bits = [np.unpackbits(x8[:, c // 8:(c + 64) // 8], axis=1).astype(np.float32)
                for c in range(0, 8 * DESCRIPTOR_BYTES, 64)]
        n = x8.shape[0]
        parent = np.zeros(n, dtype=np.int64)  # node of each descriptor at the previous level
        centres, valid = [], []
        for level in range(1, depth + 1):
            n_nodes = _level_size(branching, level)
            c64, ok = _seed_kmeanspp(x64, parent, branching, n_nodes, rng)
            labels = None
            for _ in range(iterations):
                new = _assign(x64, parent, c64, ok, branching)
                if labels is not None and np.array_equal(new, labels):
                    break
                labels = new
                c64, ok = _majority(bits, labels, n_nodes)
            # Final assignment with the final centres: exactly what quantise() computes.
            labels = _assign(x64, parent, c64, ok, branching)
            centres.append(c64)
            valid.append(ok)
            parent = labels
            if progress:
                progress('train', level, depth)
        return cls(branching, depth, centres, valid)

    # ---------------------------------------------------------------------- quantisation
    def quantise_path(self, descriptors: np.ndarray) -> np.ndarray:
        """Node of every descriptor at every level.

        Args:
            descriptors: (n, 32) uint8.

        Returns:
            (n, L) int64 node indices within each level (column l-1 is level l).
        """
        q = as_words(descriptors)
        out = np.empty((q.shape[0], self.depth), dtype=np.int64)
        for s in range(0, q.shape[0], _CHUNK):
            # The query tiled to (m, B, 4) once, so every level XORs same-shaped arrays
            # (a broadcast XOR over a length-4 axis is several times slower).
            qt = np.repeat(q[s:s + _CHUNK, None, :], self.branching, axis=1)
            node = np.zeros(qt.shape[0], dtype=np.int64)
            for lv in range(self.depth):
                node = node * self.branching + _nearest_child(qt, node, self._c3[lv],
                                                              self._pen[lv])
                out[s:s + _CHUNK, lv] = node
        return out

    def quantise(self, descriptors: np.ndarray) -> np.ndarray:
        """(n, 32) uint8 descriptors -> (n,) int64 leaf indices in [0, B**L)."""
        return self.quantise_path(descriptors)[:, -1]

    # ----------------------------------------------------------------------- persistence
    def to_arrays(self) -> dict[str, np.ndarray]:
        """Flat arrays for ``np.savez`` (no pickled objects)."""
        return {
            'tree_branching': np.int64(self.branching),
            'tree_depth': np.int64(self.depth),
            'tree_centres': np.concatenate(self.centres).view(np.uint8),   # (n_nodes, 32)
            'tree_valid': np.concatenate(self.valid),
        }

    @classmethod
    def from_arrays(cls, arrays) -> 'VocabularyTree':
        """Inverse of :meth:`to_arrays` (accepts a mapping such as an ``NpzFile``)."""
        b, d = int(arrays['tree_branching']), int(arrays['tree_depth'])
        flat = np.ascontiguousarray(arrays['tree_centres'], dtype=np.uint8)
        ok = np.asarray(arrays['tree_valid'], dtype=bool)
        sizes = [_level_size(b, lv) for lv in range(1, d + 1)]
        if flat.shape != (sum(sizes), DESCRIPTOR_BYTES) or ok.shape != (sum(sizes),):
            raise ValueError(f'tree arrays {flat.shape}, {ok.shape} do not match '
                             f'branching {b} and depth {d}')
        splits = np.cumsum(sizes)[:-1]
        return cls(b, d, [c.view(np.uint64) for c in np.split(flat, splits)],
                   np.split(ok, splits))


# ----------------------------------------------------------------------------- helpers
def _penalty(valid: np.ndarray) -> np.ndarray:
    """uint16 distance offset per node: 0 if valid, larger than any Hamming distance if not."""
    return np.where(valid, 0, _INVALID_PENALTY).astype(np.uint16)


def _nearest_child(xt, parent, c3, pen2):
    """Index in [0, B) of the nearest valid child of each row's parent.

    Args:
        xt: (m, B, 4) uint64 descriptors, each repeated B times.
        parent: (m,) parent node index within its level.
        c3: (P, B, 4) uint64 child centres grouped by parent.
        pen2: (P, B) uint16 penalties of the children.

    Returns:
        (m,) int64; ties go to the lowest index, so the result is deterministic.
    """
    # mode='clip' skips the bounds check that makes np.take buffer its output.
    g = np.take(c3, parent, axis=0, mode='clip')
    np.bitwise_xor(g, xt, out=g)
    dist = _popcount4(g) + np.take(pen2, parent, axis=0, mode='clip')
    return np.argmin(dist, axis=1)


def _assign(x64, parent, c64, ok, branching):
    """Nearest valid child (index within the level) of each descriptor's parent."""
    c3 = c64.reshape(-1, branching, _WORDS)
    pen2 = _penalty(ok).reshape(-1, branching)
    out = np.empty(x64.shape[0], dtype=np.int64)
    for s in range(0, x64.shape[0], _CHUNK):
        xt = np.repeat(x64[s:s + _CHUNK, None, :], branching, axis=1)
        ps = parent[s:s + _CHUNK]
        out[s:s + _CHUNK] = ps * branching + _nearest_child(xt, ps, c3, pen2)
    return out


def _majority(bits, labels, n_nodes):
    """Bitwise majority centre of each node's members; nodes without members are invalid.

    Per-node bit counts are a sparse one-hot (nodes x descriptors) product with the
    unpacked bits: one pass over the data, independent of the number of nodes (a sorted
    ``reduceat`` costs per group and is ~5x slower at the deep levels).

    Args:
        bits: list of (n, 64) float32 blocks of unpacked descriptor bits.
        labels: (n,) node of each descriptor.
        n_nodes: number of nodes of the level.
    """
    from scipy import sparse     # training only: camera_node, which only queries, skips it

    nodes, inverse, counts = np.unique(labels, return_inverse=True, return_counts=True)
    n = labels.shape[0]
    onehot = sparse.csr_matrix((np.ones(n, np.float32), (inverse, np.arange(n))),
                               shape=(nodes.size, n))
    half = counts.astype(np.float32)[:, None] / 2
    # Strict majority; a 50/50 split gives 0, arbitrary but deterministic. The float32
    # sums are exact (integers < 2**24).
    major = np.concatenate([onehot @ block > half for block in bits], axis=1)
    c64 = np.zeros((n_nodes, _WORDS), dtype=np.uint64)
    c64[nodes] = np.packbits(major, axis=1).view(np.uint64)
    ok = np.zeros(n_nodes, dtype=bool)
    ok[nodes] = True
    return c64, ok


def _seed_kmeanspp(x64, parent, branching, n_nodes, rng):
    """k-means++ seeding run for all parents at once.

    Every parent draws its first centre uniformly among its members, then each further
    centre with probability proportional to the squared distance to the nearest chosen one.
    A parent whose members all coincide with chosen centres stops drawing (its remaining
    children stay invalid), which is how parents with fewer than B distinct members end.
    """
    n = x64.shape[0]
    order = np.argsort(parent, kind='stable')
    sp = parent[order]
    groups, gstart, gcount = np.unique(sp, return_index=True, return_counts=True)
    group_of = np.repeat(np.arange(groups.size), gcount)     # group index, sorted order
    xs = x64[order]
    c64 = np.zeros((n_nodes, _WORDS), dtype=np.uint64)
    ok = np.zeros(n_nodes, dtype=bool)
    first = gstart + (rng.random(groups.size) * gcount).astype(np.int64)
    first = np.minimum(first, gstart + gcount - 1)
    c64[groups * branching] = xs[first]
    ok[groups * branching] = True
    nearest = np.full(n, np.iinfo(np.int32).max, dtype=np.int64)
    last = xs[first][group_of]                                  # newest centre per row
    for c in range(1, branching):
        nearest = np.minimum(nearest, _popcount4(xs ^ last).astype(np.int64))
        w = nearest.astype(np.float64) ** 2
        cum = np.cumsum(w)
        base = np.concatenate([[0.0], cum])[gstart]             # cumulative before group
        total = cum[gstart + gcount - 1] - base
        draw = total > 0
        target = base + rng.random(groups.size) * total
        pick = np.searchsorted(cum, target, side='right')
        # Clamp into the group (floating point at the group edges).
        pick = np.clip(pick, gstart, gstart + gcount - 1)
        # Never re-pick a zero-weight row (an existing centre) even after clamping.
        pick = np.where(w[pick] > 0, pick, _last_positive(w, gstart, gcount, pick))
        node = groups * branching + c
        c64[node[draw]] = xs[pick[draw]]
        ok[node[draw]] = True
        new_last = np.where(draw[:, None], xs[pick], xs[first])
        last = new_last[group_of]
        if not draw.any():
            break
    return c64, ok


def _last_positive(w, gstart, gcount, pick):
    """For rare clamped picks on a zero-weight row: nearest positive-weight row in group."""
    out = pick.copy()
    for g in np.flatnonzero(w[pick] <= 0):
        idx = np.flatnonzero(w[gstart[g]:gstart[g] + gcount[g]] > 0)
        if idx.size:
            out[g] = gstart[g] + idx[np.argmin(np.abs(gstart[g] + idx - pick[g]))]
    return out
