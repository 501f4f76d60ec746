"""Compiled per-particle kernels of the epoch (numba).

Everything an epoch does per particle or per particle and satellite runs here, fused into
few passes over the arrays: propagation (``motion``), receiver clock and GNSS likelihood
(``gnss``), camera distributions and their mixture (``camera``), posterior moments,
hazard mass and protection level (``posterior``). The modules of ``core`` call these; the
plain numpy forms they replaced survive only as test oracles (``test/oracles.py``).

Kernels are compiled on first use and cached on disk (``cache=True``: the next process
loads them instead of compiling); :func:`warm_up` runs each once on a tiny input so that a
node's first epoch is not a compilation. They run on the calling thread only (no numba
threading layer, no BLAS), so an epoch costs the same whatever was imported before.
"""
from __future__ import annotations

import numba

#: Options of every kernel: compiled once and cached on disk; no Python objects inside
#: (``nopython``); released GIL so that a node's executor threads keep running; numpy's
#: error model (a division by zero gives inf/NaN as numpy would, never an exception from
#: inside a kernel: the filter's state checks catch non-finite results).
KERNEL_OPTIONS = dict(cache=True, nogil=True, error_model='numpy')


def kernel(function):
    """Compile ``function`` as an epoch kernel (:data:`KERNEL_OPTIONS`)."""
    return numba.njit(**KERNEL_OPTIONS)(function)
