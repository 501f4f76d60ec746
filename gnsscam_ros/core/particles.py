"""Particle sets: propagation with odometry perturbations, weights and resampling
(:class:`SystematicResampler`).

A particle is ``(east_m, north_m, up_m, yaw_rad)`` in the local ENU ``map`` frame; yaw is
counter-clockwise from east. Sets are ``(..., N, 4)`` arrays with log-weights ``(..., N)``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from .kernels import motion as motion_kernels
from .kernels import weights as weight_kernels
from .motion import MotionIncrement

STATE_DIM = 4
POS = slice(0, 3)
YAW = 3


def log_sum_exp_rows(log_w: np.ndarray) -> np.ndarray:
    """``log sum exp`` over the last axis, keeping it (numpy max shift; scipy's
    ``logsumexp`` costs tens of microseconds of checks on the small arrays of an epoch)."""
    top = log_w.max(axis=-1, keepdims=True)
    top = np.where(np.isfinite(top), top, 0.0)
    with np.errstate(divide='ignore'):
        return top + np.log(np.exp(log_w - top).sum(axis=-1, keepdims=True))


def normalize_log_weights(log_w: np.ndarray) -> np.ndarray:
    """Return log-weights shifted so that ``exp`` of each row sums to one."""
    if log_w.ndim == 1:
        return weight_kernels.normalised(np.ascontiguousarray(log_w, dtype=float))
    return log_w - log_sum_exp_rows(log_w)


def effective_sample_size(log_w: np.ndarray) -> np.ndarray:
    """Effective sample size ``1 / sum w^2`` of normalised log-weights (last axis)."""
    if log_w.ndim == 1:
        return weight_kernels.effective_sample_size(np.ascontiguousarray(log_w, dtype=float))
    return np.exp(-log_sum_exp_rows(2.0 * log_w)[..., 0])


@dataclass(frozen=True)
class SystematicResampler:
    """Systematic selection from a weighted set: one comb of evenly spaced pointers
    ``(u + s) / n_slots`` over the CDF of the weights, a single offset ``u`` in [0, 1) for
    every slot ``s``.

    Every resampling and thinning of a particle set goes through here: the filter's
    resampling (:meth:`resample`, ``u`` drawn; thinned to the working size at the end of
    heading acquisition), a new set size while running (:meth:`resize`), the published
    cloud (:meth:`subsample`, ``u = 1/2``: deterministic, so publishing never draws from
    the filter's generator) and the evenly thinned set the risk bound sees during heading
    acquisition (:meth:`thin`, no selection by weight).
    """

    @staticmethod
    def indices(log_w: np.ndarray, offset: float, n_slots: int | None = None,
                slots: np.ndarray | None = None) -> np.ndarray:
        """Indices the comb selects.

        Args:
            log_w: (N,) log-weights (normalised or not).
            offset: ``u`` in [0, 1).
            n_slots: Teeth of the comb (default N).
            slots: Which teeth to use, (K,) integers in ``[0, n_slots)`` (default all, in
                order).

        Returns:
            (K,) indices into the set; non-decreasing when ``slots`` is.
        """
        n = log_w.shape[0]
        n_slots = n if n_slots is None else n_slots
        slots = np.arange(n_slots) if slots is None else slots
        cdf = np.cumsum(np.exp(log_w - log_w.max()))
        cdf /= cdf[-1]
        pointers = (offset + slots) / n_slots
        return np.minimum(np.searchsorted(cdf, pointers, side='right'), n - 1)

    def resample(self, log_w: np.ndarray, rng: np.random.Generator,
                 count: int | None = None) -> np.ndarray:
        """Resample N particles with one uniform draw: N indices, or ``count`` of them.

        With ``count`` the comb keeps its N teeth and uses ``count`` evenly spaced ones
        (the end of heading acquisition thins the set to its working size this way).
        """
        n = log_w.shape[0]
        slots = (None if count is None or count == n
                 else np.round(np.linspace(0, n - 1, count)).astype(int))
        return self.indices(log_w, rng.random(), n, slots)

    def resize(self, log_w: np.ndarray, rng: np.random.Generator, count: int) -> np.ndarray:
        """``count`` indices for a set of another size: resampled, then drawn from the
        resampled set with replacement (a size change while running)."""
        return rng.choice(self.resample(log_w, rng), size=count, replace=True)

    def subsample(self, log_w: np.ndarray, count: int) -> np.ndarray:
        """At most ``count`` indices, deterministic (pointers at ``(k + 1/2) / count``);
        every index when ``count <= 0`` or the set is no larger."""
        n = log_w.shape[0]
        if count <= 0 or n <= count:
            return np.arange(n)
        return self.indices(log_w, 0.5, count)

    @staticmethod
    def thin(n: int, count: int) -> slice:
        """Every ``n // count``-th particle of a set of ``n`` (about ``count`` of them, at
        least ``count``; the sets are in no order, so this is an even thinning); the
        weights of what is kept need normalising again."""
        return slice(None, None, max(n // count, 1))


#: The resampler of the filter and of its published cloud.
SYSTEMATIC = SystematicResampler()


def systematic_resample(log_w: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Systematic resampling: one uniform draw, N evenly spaced pointers.

    Args:
        log_w: (N,) normalised log-weights.
        rng: Random generator (explicit; never global state).

    Returns:
        (N,) indices of the selected particles, non-decreasing.
    """
    return SYSTEMATIC.resample(log_w, rng)


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
              noise: np.ndarray) -> np.ndarray:
    """Move one particle set by each of M motion samples, with per-particle process noise.

    The position advances along the mid-interval heading (second-order accurate for a
    constant turn rate); the compiled kernel is ``core.kernels.motion.propagate_sets``.

    Args:
        particles: (N, 4) set to propagate.
        distance_m: (M,) distance of each motion sample [m].
        dyaw_rad: (M,) heading change of each motion sample [rad].
        dup_m: Height change [m].
        pos_var_m2: (3,) east, north, up position noise variances for this interval [m^2].
        yaw_var_rad2: Heading noise variance for this interval [rad^2].
        noise: (M, N, 4) float32 standard normal draws (:class:`.noise.ProcessNoise`;
            single precision is ample for process noise and twice as fast to draw).

    Returns:
        (M, N, 4) propagated sets, one per motion sample.
    """
    m, n = distance_m.shape[0], particles.shape[0]
    if noise.shape != (m, n, STATE_DIM) or noise.dtype != np.float32:
        raise ValueError(f'noise of shape {noise.shape} ({noise.dtype}), expected '
                         f'{(m, n, STATE_DIM)} float32')
    out = np.empty((m, n, STATE_DIM))
    motion_kernels.propagate_sets(np.ascontiguousarray(particles, dtype=float),
                                  np.asarray(distance_m, dtype=float),
                                  np.asarray(dyaw_rad, dtype=float), float(dup_m),
                                  np.sqrt(np.asarray(pos_var_m2, dtype=float)),
                                  float(np.sqrt(yaw_var_rad2)), noise, out)
    return out


def weighted_mean_cov(points: np.ndarray, log_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean (3,) and covariance (3, 3) of (N, >= 3) points (their first three
    columns) with normalised log-weights (one compiled pass)."""
    return weight_kernels.weighted_moments(np.ascontiguousarray(points, dtype=float),
                                           np.ascontiguousarray(log_w, dtype=float))
