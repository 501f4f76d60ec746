"""Motion along the route of the emulated drive: the distance-time profile and the pose.

:func:`speed_profile` drives the route as fast as the limits allow: one speed limit per
street segment, a lower one in turns, stops at some intersections (traffic lights) and at
both ends, accelerations <= ``accel_mps2`` and braking <= ``decel_mps2``, smoothed by a
Gaussian kernel so that the acceleration is continuous. :class:`Pose` holds the truth
kinematics sampled from it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d

from .config import EmulationConfig
from .route import Route


@dataclass(frozen=True)
class Pose:
    """Truth kinematics at a set of times (planar motion, heading = direction of travel).

    Attributes:
        enu_m: (n, 3) antenna position in the local ENU frame [m].
        yaw_rad: (n,) heading, counter-clockwise from east, wrapped to [-pi, pi) [rad].
        speed_mps: (n,) forward speed [m/s].
        accel_mps2: (n,) forward acceleration [m/s^2].
        yaw_rate_rps: (n,) yaw rate [rad/s].
    """

    enu_m: np.ndarray
    yaw_rad: np.ndarray
    speed_mps: np.ndarray
    accel_mps2: np.ndarray
    yaw_rate_rps: np.ndarray


def wrap_angle(a):
    """Angles wrapped to [-pi, pi) [rad]."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def speed_profile(route: Route, rng: np.random.Generator, cfg: EmulationConfig):
    """Distance-time profile: speed limits, stops, bounded accel/braking, smoothing.

    Returns:
        ``(t_s, s_m, v_mps, a_mps2, stops)`` at ``cfg.imu_rate_hz`` with ``stops`` a list of
        ``(arc_length_m, dwell_s)``.
    """
    L = route.length_m
    ds = 0.25
    s_g = np.linspace(0.0, L, int(np.ceil(L / ds)) + 1)
    ds = s_g[1] - s_g[0]
    # Speed limit: one cruise speed per street segment between nodes, turn speed on arcs.
    bounds = np.concatenate([[0.0], route.node_s_m, [L]])
    cruise = rng.uniform(*cfg.cruise_speed_mps, size=len(bounds) - 1)
    vlim = cruise[np.clip(np.searchsorted(bounds, s_g, side='right') - 1, 0, len(cruise) - 1)]
    _, _, kappa = route.evaluate(s_g)
    vlim = np.where(kappa != 0.0, np.minimum(vlim, cfg.turn_speed_mps), vlim)
    # Stops at some intersections (traffic lights), plus start and end.
    dwell = np.zeros_like(s_g)
    stop_here = rng.random(len(route.stop_s_m)) < cfg.stop_prob
    durations = rng.uniform(*cfg.stop_duration_s, size=len(route.stop_s_m))
    stops = []
    for s_stop, dur in zip(route.stop_s_m[stop_here], durations[stop_here]):
        k = int(round(s_stop / ds))
        if 0 < k < len(s_g) - 1:
            vlim[k], dwell[k] = 0.0, dur
            stops.append((float(s_g[k]), float(dur)))
    vlim[0] = vlim[-1] = 0.0
    dwell[0] = dwell[-1] = cfg.standstill_s
    # Fastest profile under the limits with bounded acceleration (forward pass) and braking
    # (backward pass), in closed form: v^2(s) = min_j vlim_j^2 + 2 a |s - s_j| on each side.
    v2_f = 2 * cfg.accel_mps2 * s_g + np.minimum.accumulate(vlim ** 2 - 2 * cfg.accel_mps2 * s_g)
    g = vlim ** 2 + 2 * cfg.decel_mps2 * s_g
    v2_b = np.minimum.accumulate(g[::-1])[::-1] - 2 * cfg.decel_mps2 * s_g
    v = np.sqrt(np.maximum(np.minimum(v2_f, v2_b), 0.0))
    dt = 2.0 * ds / np.maximum(v[:-1] + v[1:], 1e-9)
    t_arr = np.concatenate([[0.0], np.cumsum(dt)]) + np.concatenate([[0.0], np.cumsum(dwell)[:-1]])
    has = dwell > 0
    t_knots = np.concatenate([t_arr, t_arr[has] + dwell[has]])
    s_knots = np.concatenate([s_g, s_g[has]])
    order = np.argsort(t_knots, kind='stable')
    t_knots, s_knots = t_knots[order], s_knots[order]
    step = 1.0 / cfg.imu_rate_hz
    t = np.arange(int(np.floor(t_knots[-1] / step)) + 1) * step
    s_raw = np.interp(t, t_knots, s_knots)
    # Smoothing s(t) with a positive kernel keeps it monotone (speed >= 0) and makes the
    # acceleration continuous (no jerk spikes in the IMU). Derivatives are taken by finite
    # differences BEFORE smoothing (the operations commute): scipy's derivative-of-Gaussian
    # kernels do not sum exactly to zero, which on s ~ 2 km gives accelerations off by m/s^2.
    sig = cfg.smoothing_s / step
    s_m = gaussian_filter1d(s_raw, sig, mode='nearest')
    v_raw = np.gradient(s_raw, step)
    v_mps = np.maximum(gaussian_filter1d(v_raw, sig, mode='nearest'), 0.0)
    a_mps2 = gaussian_filter1d(np.gradient(v_raw, step), sig, mode='nearest')
    return t, np.clip(s_m, 0.0, L), v_mps, a_mps2, stops
