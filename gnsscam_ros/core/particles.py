"""Particle sets: propagation with odometry perturbations, weights and resampling.

A particle is ``(east_m, north_m, up_m, yaw_rad)`` in the local ENU ``map`` frame; yaw is
counter-clockwise from east. Sets are ``(..., N, 4)`` arrays with log-weights ``(..., N)``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import logsumexp

STATE_DIM = 4
POS = slice(0, 3)
YAW = 3


@dataclass(frozen=True)
class MotionIncrement:
    """Vehicle motion between two GNSS epochs, in the vehicle frame.

    Attributes:
        dt_s: Elapsed time [s].
        distance_m: Distance travelled along the heading [m].
        dyaw_rad: Heading change [rad].
        distance_var_m2: Variance of ``distance_m`` [m^2].
        dyaw_var_rad2: Variance of ``dyaw_rad`` [rad^2].
        dup_m: Height change [m] (0 for planar odometry).
        unknown_s: Part of ``dt_s`` not covered by dead reckoning (lost, or reset) [s]:
            over it the vehicle may have moved anywhere its maximum speed allows.
    """

    dt_s: float
    distance_m: float
    dyaw_rad: float
    distance_var_m2: float
    dyaw_var_rad2: float
    dup_m: float = 0.0
    unknown_s: float = 0.0

    @classmethod
    def stationary(cls, dt_s: float) -> 'MotionIncrement':
        """Measured standstill: the propagation noise alone spreads the set."""
        return cls(dt_s=dt_s, distance_m=0.0, dyaw_rad=0.0, distance_var_m2=0.0,
                   dyaw_var_rad2=0.0)

    @classmethod
    def unknown(cls, dt_s: float) -> 'MotionIncrement':
        """No dead reckoning for the whole interval: the motion is unknown."""
        return cls(dt_s=dt_s, distance_m=0.0, dyaw_rad=0.0, distance_var_m2=0.0,
                   dyaw_var_rad2=0.0, unknown_s=max(dt_s, 0.0))


def normalize_log_weights(log_w: np.ndarray) -> np.ndarray:
    """Return log-weights shifted so that ``exp`` of each row sums to one."""
    return log_w - logsumexp(log_w, axis=-1, keepdims=True)


def effective_sample_size(log_w: np.ndarray) -> np.ndarray:
    """Effective sample size ``1 / sum w^2`` of normalised log-weights (last axis)."""
    return np.exp(-logsumexp(2.0 * log_w, axis=-1))


def systematic_resample(log_w: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Systematic resampling: one uniform draw, N evenly spaced pointers.

    Args:
        log_w: (N,) normalised log-weights.
        rng: Random generator (explicit; never global state).

    Returns:
        (N,) indices of the selected particles, non-decreasing.
    """
    n = log_w.shape[0]
    cdf = np.cumsum(np.exp(log_w - log_w.max()))
    cdf /= cdf[-1]
    pointers = (rng.random() + np.arange(n)) / n
    return np.minimum(np.searchsorted(cdf, pointers, side='right'), n - 1)


def motion_samples(motion: MotionIncrement, n_samples: int, scale: float,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Draw M motion samples around the measured odometry (paper §2, perturbations).

    Sample 0 is the measured motion itself, so the unperturbed hypothesis is always among
    the M posteriors; the others are drawn from the odometry noise inflated by ``scale``.

    Returns:
        ``(distance_m (M,), dyaw_rad (M,))``.
    """
    distance = np.full(n_samples, motion.distance_m)
    dyaw = np.full(n_samples, motion.dyaw_rad)
    if n_samples > 1:
        distance[1:] += scale * np.sqrt(motion.distance_var_m2) * rng.standard_normal(
            n_samples - 1)
        dyaw[1:] += scale * np.sqrt(motion.dyaw_var_rad2) * rng.standard_normal(n_samples - 1)
    return distance, dyaw


def propagate(particles: np.ndarray, distance_m: np.ndarray, dyaw_rad: np.ndarray,
              dup_m: float, pos_var_m2: np.ndarray, yaw_var_rad2: float,
              rng: np.random.Generator) -> np.ndarray:
    """Move one particle set by each of M motion samples, with per-particle process noise.

    The position advances along the mid-interval heading (second-order accurate for a
    constant turn rate).

    Args:
        particles: (N, 4) set to propagate.
        distance_m: (M,) distance of each motion sample [m].
        dyaw_rad: (M,) heading change of each motion sample [rad].
        dup_m: Height change [m].
        pos_var_m2: (3,) east, north, up position noise variances for this interval [m^2].
        yaw_var_rad2: Heading noise variance for this interval [rad^2].
        rng: Random generator.

    Returns:
        (M, N, 4) propagated sets, one per motion sample.
    """
    m, n = distance_m.shape[0], particles.shape[0]
    # Single-precision draws are twice as fast and ample for process noise.
    noise = rng.standard_normal((m, n, STATE_DIM), dtype=np.float32)
    # cos(yaw + d) = cos(yaw) cos(d) - sin(yaw) sin(d): the trigonometry runs on the N
    # headings once, not on all M * N.
    cos_n, sin_n = np.cos(particles[:, YAW]), np.sin(particles[:, YAW])
    half = 0.5 * dyaw_rad
    step_c = (distance_m * np.cos(half))[:, None]
    step_s = (distance_m * np.sin(half))[:, None]
    out = np.empty((m, n, STATE_DIM))
    out[..., 0] = particles[None, :, 0] + step_c * cos_n - step_s * sin_n
    out[..., 1] = particles[None, :, 1] + step_c * sin_n + step_s * cos_n
    out[..., 2] = particles[None, :, 2] + dup_m
    out[..., :3] += np.sqrt(pos_var_m2) * noise[..., :3]
    out[..., YAW] = particles[None, :, YAW] + dyaw_rad[:, None] + np.sqrt(yaw_var_rad2) * noise[
        ..., YAW]
    return out


def weighted_mean_cov(points: np.ndarray, log_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean (d,) and covariance (d, d) of (N, d) points with normalised log-weights."""
    w = np.exp(log_w)
    mean = w @ points
    centred = points - mean
    cov = (centred * w[:, None]).T @ centred
    return mean, cov
