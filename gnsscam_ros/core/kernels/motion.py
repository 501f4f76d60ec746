"""Propagation of a particle set by S motion samples, and weighted moments (paper §2, §7).

One pass writes the S propagated sets; one more gives the weighted mean and covariance of
a set (of the first, the measured motion: the epoch's reference point for the satellites
and the clock).
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


@kernel
def weighted_moments(points, log_w):
    """Weighted mean (3,) and covariance (3, 3) of the first three columns of ``points``
    (N, >= 3) under normalised log-weights ``log_w`` (N,).

    One pass about a reference point (the first point): coordinates relative to it are
    small, so the one-pass formula loses nothing to cancellation.
    """
    n = points.shape[0]
    ref0, ref1, ref2 = points[0, 0], points[0, 1], points[0, 2]
    w_sum = 0.0
    m = np.zeros(3)
    c = np.zeros((3, 3))
    d = np.empty(3)
    for i in range(n):
        w = math.exp(log_w[i])
        d[0] = points[i, 0] - ref0
        d[1] = points[i, 1] - ref1
        d[2] = points[i, 2] - ref2
        w_sum += w
        for a in range(3):
            wd = w * d[a]
            m[a] += wd
            for b in range(a, 3):
                c[a, b] += wd * d[b]
    mean = np.empty(3)
    for a in range(3):
        m[a] /= w_sum
    for a in range(3):
        for b in range(a, 3):
            c[a, b] = c[a, b] / w_sum - m[a] * m[b]
            c[b, a] = c[a, b]
    mean[0] = ref0 + m[0]
    mean[1] = ref1 + m[1]
    mean[2] = ref2 + m[2]
    return mean, c
