"""Compile (or load from the cache) every epoch kernel before the first real epoch.

numba compiles a kernel on its first call, for the argument types of that call, and
caches the machine code on disk; a process that finds the cache loads it instead. A node
calls :func:`warm_up_kernels` at start-up so that its first epoch costs what any epoch
costs: it runs a few epochs of a tiny synthetic drive through an :class:`EpochEngine`
with each likelihood and with camera matches, so every kernel sees the argument types the
filter gives it (sizes do not matter to the compiled code).
"""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from .engine import EpochEngine
from .filter import FilterConfig
from .frames import LocalFrame, sagnac_corrected
from .fusion import CameraMeasurement
from .gnss import LIKELIHOODS
from .kernels import bias as bias_kernels
from .motion import DeadReckoningState
from .types import GLONASS, GPS, GnssEpoch

#: Where the synthetic drive is (any place works).
_ORIGIN_LLH = (52.5, 13.4, 40.0)


def _sky_epoch(frame: LocalFrame, stamp_ns: int, position_enu_m: np.ndarray) -> GnssEpoch:
    """Ten satellites of two systems in a spread sky, pseudoranges exact (clock 100 m)."""
    azimuth = np.radians(np.arange(10) * 36.0)
    elevation = np.radians(np.array([15.0, 30.0, 45.0, 60.0, 75.0] * 2))
    directions = np.c_[np.cos(elevation) * np.sin(azimuth),
                       np.cos(elevation) * np.cos(azimuth), np.sin(elevation)]
    sv = frame.enu_to_ecef(directions * 2.2e7)
    rx = frame.enu_to_ecef(position_enu_m)
    pr = np.linalg.norm(sagnac_corrected(sv, rx) - rx, axis=1) + 100.0
    return GnssEpoch(stamp_ns=stamp_ns, sv_pos_ecef_m=sv, pr_m=pr, var_m2=np.full(10, 4.0),
                     sv_id=np.arange(1, 11), system=np.array([GPS] * 5 + [GLONASS] * 5),
                     elevation_deg=np.degrees(elevation), cn0_dbhz=np.full(10, 45.0))


def warm_up_kernels(config: FilterConfig | None = None, epochs: int = 4) -> float:
    """Run a tiny synthetic drive through each likelihood; returns the seconds it took.

    Args:
        config: The configuration to warm up (its likelihood first); sizes are replaced
            by tiny ones.
        epochs: GNSS epochs per likelihood (the first initialises, the second fuses
            camera matches; heading acquisition and resampling happen along the way).
    """
    started = time.perf_counter()
    base = config if config is not None else FilterConfig()
    frame = LocalFrame(*_ORIGIN_LLH)
    for likelihood in (base.likelihood,) + tuple(n for n in LIKELIHOODS
                                                 if n != base.likelihood):
        tiny = replace(base, likelihood=likelihood, n_particles=32, acquisition_particles=96,
                       n_posteriors=4, n_motion_samples=2, heading_acquisition_m=10.0)
        engine = EpochEngine(tiny, frame=frame, rng=np.random.default_rng(0))
        for k in range(epochs):
            stamp = (k + 1) * 1_000_000_000
            x = 8.0 * k
            engine.add_dead_reckoning(DeadReckoningState(
                stamp_ns=stamp, x_m=x, y_m=0.0, yaw_rad=0.0, speed_mps=8.0,
                yaw_rate_rps=0.0, speed_var=0.01, yaw_rate_var=1e-4,
                distance_var_m2=0.01 * k, yaw_var_rad2=1e-5 * k))
            for j in range(2):
                at = stamp - (j + 1) * 300_000_000
                engine.add_camera(at, CameraMeasurement(
                    stamp_ns=at, position_enu_m=np.array([x - 2.4 * (j + 1), 0.0, 0.0]),
                    score=1.0, frame_id=2 * k + j) if k else None)
            engine.add_gnss(_sky_epoch(frame, stamp, np.array([x, 0.0, 0.0])))
            list(engine.ready_reports())
    bias_kernels.warm_up()          # what a drive of a few epochs does not reach
    return time.perf_counter() - started
