"""Compiled per-particle kernels of the epoch (numba).

Everything an epoch does per particle or per particle and satellite runs here, fused into
few passes over the arrays: propagation (``motion``), receiver clock and GNSS likelihood
(``gnss``), the satellites' inlier probabilities under it (``inliers``), camera
distributions and their mixture (``camera``), posterior moments,
hazard mass and protection level (``posterior``); and per epoch, the snapshot solution
(``snapshot``), the bias hypotheses' small matrices (``bias``), the error model's EM
(``mixture``) and its passes over the residuals (``residuals``), and the persistence's
semivariogram (``persistence``), whose numpy or Python calls cost more than their
arithmetic. The modules of ``core`` call these; the plain numpy forms they replaced
survive only as test oracles (``test/oracles.py``).

Kernels are compiled on first use and cached on disk (``cache=True``: the next process
loads them instead of compiling); ``core.warmup`` runs each once on a tiny input so that a
node's first epoch is not a compilation. numba checks a cached kernel against its own
source file only, not against the helpers it inlines from another module
(``elementary.exp``): :func:`drop_stale_caches` removes, at import, every cached kernel of
this package older than any of its sources, so an edited helper is compiled again.

A Ctrl-C that lands in one of llvmlite's callbacks while a kernel compiles is raised again
in the main thread (``core.interrupts``) instead of being dropped.

Kernels run on the calling thread only (no numba threading layer; LAPACK only for a
rank-deficient snapshot system of a dozen rows, ``snapshot.robust_snapshot``, far below
any size that LAPACK runs on threads), so an epoch costs the same whatever was imported
before.
"""
from __future__ import annotations

import os
from pathlib import Path

import numba

#: Options of every kernel: compiled once and cached on disk; no Python objects inside
#: (``nopython``); released GIL so that a node's executor threads keep running; numpy's
#: error model (a division by zero gives inf/NaN as numpy would, never an exception from
#: inside a kernel: the filter's state checks catch non-finite results).
KERNEL_OPTIONS = dict(cache=True, nogil=True, error_model='numpy')


#: Options of the likelihood kernels: also ``contract``, which lets LLVM fuse a multiply
#: and an add into one FMA instruction (one rounding instead of two: results differ from
#: the uncontracted ones in the last bits, ~1e-8 nats here, and are deterministic on a
#: given machine). Not used where a kernel is held bit-identical to numpy (propagation).
CONTRACTED_OPTIONS = dict(KERNEL_OPTIONS, fastmath={'contract'})


#: Options of inlined helpers: the kernel options, inlined into the caller so that its
#: loops vectorise (a call would keep them scalar).
INLINE_OPTIONS = dict(KERNEL_OPTIONS, inline='always')


def kernel(function):
    """Compile ``function`` as an epoch kernel (:data:`KERNEL_OPTIONS`)."""
    return numba.njit(**KERNEL_OPTIONS)(function)


def contracted_kernel(function):
    """Compile ``function`` as an epoch kernel whose multiply-adds may fuse
    (:data:`CONTRACTED_OPTIONS`)."""
    return numba.njit(**CONTRACTED_OPTIONS)(function)


def inline_kernel(function):
    """Compile ``function`` as a helper inlined into the kernels calling it
    (:data:`INLINE_OPTIONS`)."""
    return numba.njit(**INLINE_OPTIONS)(function)


def drop_stale_caches(package_dir: Path = Path(__file__).parent) -> int:
    """Remove the cached kernels (numba's ``__pycache__/*.nbi`` index and ``*.nbc`` code
    files) of this package that are older than its newest source file; returns how many
    files went. Best effort: a cache that cannot be read or removed is left alone (an
    installed package's sources do not change after installation)."""
    removed = 0
    try:
        newest = max(f.stat().st_mtime for f in package_dir.glob('*.py'))
        cached = list((package_dir / '__pycache__').glob('*.nb[ic]'))
    except (OSError, ValueError):
        return 0
    for path in cached:
        try:
            if path.stat().st_mtime < newest:
                os.remove(path)
                removed += 1
        except OSError:
            pass
    return removed


drop_stale_caches()
