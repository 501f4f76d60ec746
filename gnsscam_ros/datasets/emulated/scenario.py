"""The seeded world of one emulated drive: city, route, motion, frame and start time.

:func:`make_scenario` builds it from the seed; :func:`make_emulated_drive
<.drive.make_emulated_drive>` synthesises the sensors from it and the camera stream
(:mod:`.camera`) renders it, each with its own random stream, so that both see the same
truth. :func:`scenario_of` rebuilds the scenario of an existing emulated drive.
"""
from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass, field

import numpy as np

from ...core.frames import LocalFrame
from ...core.types import Drive
from ..city import City, make_city
from .config import EmulationConfig, stream_rng
from .route import Route, make_route
from .trajectory import Pose, speed_profile, wrap_angle


@dataclass(frozen=True)
class Scenario:
    """The seeded world of one emulated drive: city, route, motion, frame and start time.

    Attributes:
        seed: Drive seed.
        config: Parameters.
        city: The city model (buildings, facades).
        frame: Local ENU frame at ``config.origin_llh``.
        route: Driven path.
        t_s: (n,) truth sample times from the start [s] at ``config.imu_rate_hz``.
        s_m: (n,) arc length along the route [m].
        v_mps: (n,) speed [m/s].
        a_mps2: (n,) forward acceleration [m/s^2].
        t0_ns: Unix time of ``t_s = 0`` [ns] (a whole second).
        stops: ``(arc_length_m, dwell_s)`` of the intersection stops.
    """

    seed: int
    config: EmulationConfig
    city: City
    frame: LocalFrame
    route: Route
    t_s: np.ndarray
    s_m: np.ndarray
    v_mps: np.ndarray
    a_mps2: np.ndarray
    t0_ns: int
    stops: list = field(default_factory=list)

    @property
    def duration_s(self) -> float:
        """Duration of the whole drive [s]."""
        return float(self.t_s[-1])

    def stamps_ns(self, t_s: np.ndarray) -> np.ndarray:
        """Times from the start [s] -> Unix stamps [ns] (int64)."""
        return self.t0_ns + np.round(np.asarray(t_s, dtype=float) * 1e9).astype(np.int64)

    def pose_at(self, t_s: np.ndarray) -> Pose:
        """Truth pose and kinematics at arbitrary times (e.g. camera frames).

        The distance-time profile is interpolated linearly between the truth samples (it is
        smooth at the sample rate), then the route geometry is evaluated exactly.

        Args:
            t_s: (n,) times from the start of the drive [s], within ``[0, duration_s]``.

        Returns:
            The pose at those times.
        """
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        s = np.interp(t, self.t_s, self.s_m)
        v = np.interp(t, self.t_s, self.v_mps)
        a = np.interp(t, self.t_s, self.a_mps2)
        en, psi, kappa = self.route.evaluate(s)
        enu = np.column_stack([en, np.full(len(t), self.config.antenna_height_m)])
        return Pose(enu_m=enu, yaw_rad=wrap_angle(psi), speed_mps=v, accel_mps2=a,
                    yaw_rate_rps=kappa * v)


def make_scenario(seed: int, config: EmulationConfig | None = None) -> Scenario:
    """Build the city, route, motion and start time of the drive of ``seed``.

    Args:
        seed: Drive seed.
        config: Parameters (defaults when None).

    Returns:
        The scenario; :func:`make_emulated_drive` with the same seed uses exactly this one.
    """
    cfg = config or EmulationConfig()
    city = make_city(stream_rng(seed, 'city'))
    rng = stream_rng(seed, 'route')
    route = make_route(city, rng, cfg)
    t, s, v, a, stops = speed_profile(route, rng, cfg)
    # Start between 08:00 and 16:00 UTC on 2024-06-12, a whole second.
    base = int(_dt.datetime(2024, 6, 12, 8, tzinfo=_dt.timezone.utc).timestamp())
    t0_s = base + int(stream_rng(seed, 'time').integers(0, 8 * 3600))
    return Scenario(seed=int(seed), config=cfg, city=city, frame=LocalFrame(*cfg.origin_llh),
                    route=route, t_s=t, s_m=s, v_mps=v, a_mps2=a, t0_ns=t0_s * 10 ** 9,
                    stops=stops)


def scenario_of(drive: Drive) -> Scenario:
    """Rebuild the scenario of an emulated drive from its ``info`` (seed and config)."""
    info = drive.info or {}
    if 'seed' not in info or 'config' not in info:
        raise ValueError(f'{drive.name}: not an emulated drive (info has no seed/config)')
    cfg = {k: (tuple(v) if isinstance(v, list) else v) for k, v in info['config'].items()}
    return make_scenario(int(info['seed']), EmulationConfig(**cfg))


def seed_of(scenario: Scenario, seed: int | None) -> int:
    """``seed``, or the scenario's seed when None (the camera passes default to it)."""
    return int(scenario.seed if seed is None else seed)
