"""Propagation of a particle set by S motion samples, and weighted moments (paper §2, §7).

One pass writes the S propagated sets.
"""
from __future__ import annotations

import math

import numpy as np

from . import kernel


@kernel
def propagate_sets(particles, distance_m, dyaw_rad, dup_m, position_sd_m, yaw_sd_rad, noise,
                   out):
    """Move the (N, 4) set by each of S motion samples into ``out`` (S, N, 4).

    The position advances along the mid-interval heading (second-order accurate for a
    constant turn rate); ``cos(yaw + d) = cos(yaw) cos(d) - sin(yaw) sin(d)`` keeps the
    trigonometry at one cosine and one sine per particle, not per particle and sample.

    Args:
        particles: (N, 4) east, north, up [m], yaw [rad].
        distance_m: (S,) distance of each motion sample [m].
        dyaw_rad: (S,) heading change of each motion sample [rad].
        dup_m: Height change [m].
        position_sd_m: (3,) process noise standard deviations east, north, up [m].
        yaw_sd_rad: Heading process noise standard deviation [rad].
        noise: (S, N, 4) standard normal draws (float32 is ample for process noise).
        out: (S, N, 4) float64, written.
    """
    n = particles.shape[0]
    s_count = distance_m.shape[0]
    cos_n = np.empty(n)
    sin_n = np.empty(n)
    for i in range(n):
        cos_n[i] = math.cos(particles[i, 3])
        sin_n[i] = math.sin(particles[i, 3])
    sd0, sd1, sd2 = position_sd_m[0], position_sd_m[1], position_sd_m[2]
    for s in range(s_count):
        half = 0.5 * dyaw_rad[s]
        step_c = distance_m[s] * math.cos(half)
        step_s = distance_m[s] * math.sin(half)
        for i in range(n):
            out[s, i, 0] = (particles[i, 0] + step_c * cos_n[i] - step_s * sin_n[i]
                            + sd0 * np.float64(noise[s, i, 0]))
            out[s, i, 1] = (particles[i, 1] + step_c * sin_n[i] + step_s * cos_n[i]
                            + sd1 * np.float64(noise[s, i, 1]))
            out[s, i, 2] = particles[i, 2] + dup_m + sd2 * np.float64(noise[s, i, 2])
            out[s, i, 3] = (particles[i, 3] + dyaw_rad[s]
                            + yaw_sd_rad * np.float64(noise[s, i, 3]))
