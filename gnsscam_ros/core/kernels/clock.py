"""The receiver clock weights at a point (``core.gnss.clock_weights``) in one call.

An epoch asks for them at three points (the cloud's centre, the snapshot solution, the
cloud moved onto it). The residuals at the point were five numpy calls before the kernel,
more than the arithmetic on a dozen satellites; here they are taken in the same call, in
``frames.row_norms``' arithmetic (``test/test_kernels_gnss.py`` holds them to it).
"""
from __future__ import annotations

import math

import numpy as np

from . import kernel
from .gnss import clock_inlier_weights


@kernel
def clock_weights_at(sv_enu, pr, centre, sigma, sys_index, n_systems, spread_m, iterations):
    """``clock_inlier_weights`` of the residuals ``pr - |sv_enu - centre|`` (k,), each
    range numpy's ``sqrt(add.reduce(d * d, axis=1))``: the squares summed left to right."""
    k = pr.shape[0]
    residual = np.empty(k)
    for j in range(k):
        dx = sv_enu[j, 0] - centre[0]
        dy = sv_enu[j, 1] - centre[1]
        dz = sv_enu[j, 2] - centre[2]
        residual[j] = pr[j] - math.sqrt((dx * dx + dy * dy) + dz * dz)
    return clock_inlier_weights(residual, sigma, sys_index, n_systems, spread_m, iterations)
