"""Camera distribution over the particles (paper §4, "probability generation").

The camera node reports the position of the best-matching database image. That position is
moved to the GNSS epoch with the IMU motion, and its distance to every particle becomes a
categorical distribution over the particles:

    x_t = x_{t-1} + v dt + a dt^2 / 2
    Q_c = exp(-d_c / T) / sum_k exp(-d_k / T),   d_c = ||particle_c - x_t||

The paper's softmax is over "distance scores" without a scale; we use ``-d / T`` with a
temperature ``T`` in metres: a particle ``T`` metres farther from the matched image is
``e`` times less likely. ``T`` should be of the order of the database image spacing plus the
camera-to-image position error (a match gives the image's position, not the vehicle's).

Pure numpy/scipy; no OpenCV and no rclpy.
"""
from __future__ import annotations

import numpy as np
from scipy.special import logsumexp

DEFAULT_TEMPERATURE_M = 5.0


def propagate_match_state(pos_m, vel_mps, acc_mps2, dt_s: float) -> np.ndarray:
    """Move a matched position forward by ``dt_s`` with constant acceleration.

    Args:
        pos_m: (3,) position [m] (any (..., 3) broadcastable shape works).
        vel_mps: (3,) velocity [m/s] in the same frame.
        acc_mps2: (3,) acceleration [m/s^2] in the same frame.
        dt_s: time step [s], from the image stamp to the GNSS epoch (may be negative to
            move backwards).

    Returns:
        (3,) float64 position ``pos + vel dt + acc dt^2 / 2`` [m].

    Raises:
        ValueError: if ``dt_s`` or any input is not finite.
    """
    pos = np.asarray(pos_m, dtype=np.float64)
    vel = np.asarray(vel_mps, dtype=np.float64)
    acc = np.asarray(acc_mps2, dtype=np.float64)
    dt = float(dt_s)
    if not np.isfinite(dt):
        raise ValueError(f'dt_s must be finite, got {dt_s}')
    out = pos + vel * dt + 0.5 * acc * dt * dt
    if not np.all(np.isfinite(out)):
        raise ValueError('position, velocity and acceleration must be finite')
    return out


def camera_log_distribution(particles_enu, match_pos,
                            temperature_m: float = DEFAULT_TEMPERATURE_M) -> np.ndarray:
    """Log-probabilities of the particles under one camera match.

    Args:
        particles_enu: (P, 3) or (P, 2) particle positions [m] (local ENU). With (P, 2)
            only the horizontal distance counts.
        match_pos: (3,) matched position [m] at the particles' epoch (see
            :func:`propagate_match_state`); its first two entries are used for (P, 2).
        temperature_m: softmax temperature T [m] (> 0); see the module docstring.

    Returns:
        (P,) float64 ``log Q``, with ``logsumexp(log Q) == 0``.

    Raises:
        ValueError: for bad shapes, no particles, a non-positive temperature or
            non-finite inputs.
    """
    parts = np.asarray(particles_enu, dtype=np.float64)
    if parts.ndim != 2 or parts.shape[1] not in (2, 3) or parts.shape[0] == 0:
        raise ValueError(f'particles must be (P, 2) or (P, 3) with P > 0, got {parts.shape}')
    match = np.asarray(match_pos, dtype=np.float64).ravel()
    if match.size < parts.shape[1]:
        raise ValueError(f'match position has {match.size} coordinates, particles have '
                         f'{parts.shape[1]}')
    t = float(temperature_m)
    if not (np.isfinite(t) and t > 0):
        raise ValueError(f'temperature_m must be finite and > 0, got {temperature_m}')
    d = np.linalg.norm(parts - match[:parts.shape[1]], axis=1)
    if not np.all(np.isfinite(d)):
        raise ValueError('particle and match positions must be finite')
    # log softmax; logsumexp keeps it exact when all particles are far (d / T >> 700).
    logits = -d / t
    return logits - logsumexp(logits)
