"""Camera model and lighting of the emulated street imagery.

Camera model: pinhole (:class:`CameraIntrinsics`, 640x480, 80 deg horizontal field of view
by default), level (no pitch or roll; the emulated ground is flat), looking along the yaw
``psi`` (ENU, counter-clockwise from east). Camera axes: x right, y down, z forward.

Lighting (:class:`Lighting`) is one pass's illumination and camera response: the sun's
direction (the renderer shades walls by their orientation to it and puts the lower part of
sunlit walls in the shadow of the buildings across the street), ambient light, and a
global exposure gain, gamma and colour cast.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole camera with square pixels and the principal point at the image centre.

    Attributes:
        width: Image width [px].
        height: Image height [px].
        hfov_deg: Horizontal field of view [deg].
    """

    width: int = 640
    height: int = 480
    hfov_deg: float = 80.0

    def __post_init__(self):
        if self.width < 16 or self.height < 16:
            raise ValueError(f'image size must be at least 16x16, got '
                             f'{self.width}x{self.height}')
        if not 10.0 <= self.hfov_deg <= 150.0:
            raise ValueError(f'hfov_deg must be in [10, 150], got {self.hfov_deg}')

    @property
    def fx(self) -> float:
        """Focal length [px]."""
        return 0.5 * self.width / math.tan(math.radians(0.5 * self.hfov_deg))

    @property
    def fy(self) -> float:
        """Focal length [px] (square pixels)."""
        return self.fx

    @property
    def cx(self) -> float:
        """Principal point column [px] (pixel centres at integers)."""
        return 0.5 * (self.width - 1)

    @property
    def cy(self) -> float:
        """Principal point row [px]; also the horizon row of a level camera."""
        return 0.5 * (self.height - 1)

    @property
    def matrix(self) -> np.ndarray:
        """(3, 3) camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def as_dict(self) -> dict:
        return {'width': self.width, 'height': self.height, 'hfov_deg': self.hfov_deg,
                'fx': self.fx, 'fy': self.fy, 'cx': self.cx, 'cy': self.cy}


@dataclass(frozen=True)
class Lighting:
    """Scene illumination and camera response of one pass through the city.

    Attributes:
        gain: Global exposure multiplier (1 = nominal).
        gamma: Response exponent, ``out = 255 (gain * c * in / 255) ** gamma``.
        cast_bgr: Per-channel multipliers (colour cast, white balance error).
        sun_azimuth_rad: Sun direction, ENU, counter-clockwise from east [rad].
        sun_elevation_rad: Sun elevation above the horizon [rad].
        ambient: Brightness of shaded walls relative to a wall facing the sun (1 = diffuse,
            overcast light without shadows).
        shadow_caster_m: Typical height of the buildings across the street that cast the
            shadow band on sunlit walls [m].
        sky_zenith_bgr: Sky colour at the top of the image.
        sky_horizon_bgr: Sky colour at the horizon.
    """

    gain: float = 1.0
    gamma: float = 1.0
    cast_bgr: tuple[float, float, float] = (1.0, 1.0, 1.0)
    sun_azimuth_rad: float = 0.7
    sun_elevation_rad: float = 0.7
    ambient: float = 0.55
    shadow_caster_m: float = 22.0
    sky_zenith_bgr: tuple[int, int, int] = (205, 140, 85)
    sky_horizon_bgr: tuple[int, int, int] = (240, 220, 200)

    def __post_init__(self):
        if not (self.gain > 0 and self.gamma > 0 and 0 < self.ambient <= 1):
            raise ValueError('gain and gamma must be > 0 and ambient in (0, 1]')

    @classmethod
    def sunny(cls, rng: np.random.Generator) -> 'Lighting':
        """A random sunny daytime lighting (hard shadows, warm or neutral cast)."""
        return cls(gain=float(rng.uniform(0.95, 1.1)), gamma=float(rng.uniform(0.9, 1.05)),
                   cast_bgr=tuple(float(v) for v in rng.uniform([0.92, 0.97, 1.0],
                                                                [1.0, 1.0, 1.06])),
                   sun_azimuth_rad=float(rng.uniform(-np.pi, np.pi)),
                   sun_elevation_rad=float(rng.uniform(0.45, 1.0)),
                   ambient=float(rng.uniform(0.5, 0.65)),
                   sky_zenith_bgr=tuple(int(v) for v in rng.integers([190, 120, 60],
                                                                     [230, 160, 100])),
                   sky_horizon_bgr=tuple(int(v) for v in rng.integers([225, 205, 185],
                                                                      [250, 230, 215])))

    @classmethod
    def overcast(cls, rng: np.random.Generator) -> 'Lighting':
        """A random overcast lighting (no shadows, darker, bluish, flatter response)."""
        return cls(gain=float(rng.uniform(0.75, 0.9)), gamma=float(rng.uniform(1.05, 1.25)),
                   cast_bgr=tuple(float(v) for v in rng.uniform([1.0, 0.96, 0.88],
                                                                [1.06, 1.0, 0.95])),
                   sun_azimuth_rad=float(rng.uniform(-np.pi, np.pi)),
                   sun_elevation_rad=float(rng.uniform(0.3, 0.9)),
                   ambient=float(rng.uniform(0.85, 0.95)),
                   sky_zenith_bgr=tuple(int(v) for v in rng.integers([170, 165, 160],
                                                                     [190, 185, 180])),
                   sky_horizon_bgr=tuple(int(v) for v in rng.integers([215, 212, 208],
                                                                      [230, 228, 225])))

    def as_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}

    def lut(self, gain: float = 1.0) -> np.ndarray:
        """(1, 256, 3) uint8 per-channel response table for ``cv2.LUT`` (BGR images).

        Args:
            gain: Extra exposure multiplier (e.g. per-frame auto-exposure jitter).
        """
        v = np.arange(256, dtype=np.float64) / 255.0
        g = self.gain * gain * np.asarray(self.cast_bgr, dtype=np.float64)
        out = 255.0 * np.clip(v[:, None] * g[None, :], 0.0, 1.0) ** self.gamma
        return np.clip(np.rint(out), 0, 255).astype(np.uint8)[None, :, :]
