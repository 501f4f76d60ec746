"""Camera match state: the matched image position moved to the GNSS epoch (paper §4).

The camera node reports the position of the best-matching database image at the image
time. Before it is compared with the particles at a GNSS epoch, it is moved there with the
vehicle's motion:

    x_t = x_{t-1} + v dt + a dt^2 / 2

The distribution over the particles built from it (a softmax of the distances with a
temperature in metres, plus an "elsewhere" cell) is in :func:`.fusion.camera_fusion`.

Pure numpy; no OpenCV and no rclpy.
"""
from __future__ import annotations

import numpy as np


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
