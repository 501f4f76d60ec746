"""Seeded emulated urban drive: ground truth, IMU, wheel odometry and GNSS pseudoranges.

The drive follows the streets of a generated grid city (:mod:`.city`) anchored at a real city
centre (Frankfurt am Main by default). Everything is deterministic per seed and independent
random streams are used for each ingredient (city, route, IMU, GNSS, faults, ...), so that
changing one option (e.g. the number of faulty satellites) leaves the others untouched.

Models, in short (details in the function docstrings):

* **Route** (:class:`Route`): a ~2.3 km lane-centre path through the street grid, driving
  on the right, made of straight lines and circular turn arcs (radius 10 m) at
  intersections. Speed limits 8-14 m/s per street, 5 m/s in turns, stops at some
  intersections, accelerations <= 1.5 m/s^2 and braking <= 2 m/s^2, smoothed by a Gaussian
  kernel so that acceleration is continuous. The ground is flat (``u`` = antenna height).
* **IMU** (100 Hz, body x forward, y left, z up): specific force
  ``(dv/dt, kappa v^2, g)`` and gyro ``(0, 0, kappa v)`` plus constant biases and white
  noise. The Earth rate is not included (below the gyro bias of an automotive MEMS IMU).
* **Odometry** (10 Hz): truth speed and yaw rate plus white noise; a wheel-speed sensor
  reads exactly 0 at standstill and never a negative speed.
* **GNSS**: GPS (30 satellites, 6 planes, 55 deg, a = 26,560 km) and GLONASS (24, 3 planes,
  64.8 deg, a = 25,508 km) circular orbits with a seeded constellation phase. Per epoch
  12 satellites above the 10 deg mask are tracked (kept while visible, at most 8 GPS so
  that GLONASS always has >= 4). Pseudoranges are simulated exactly with the light-time
  equation in an Earth-fixed frame (satellite positions reported at transmission, so the
  Sagnac correction of :func:`..core.frames.sagnac_corrected` is needed), plus the receiver
  clock (2-state random walk, metres, common to all satellites of a system), a constant
  GLONASS-GPS inter-system bias, white noise of variance 10 m^2, NLOS errors and injected
  faults.

Add a camera stream later with :func:`make_scenario` (same seed, same truth) and
:meth:`Scenario.pose_at`; the random stream ``'camera'`` is reserved for it.
"""
from __future__ import annotations

import datetime as _dt
from dataclasses import asdict, dataclass, field

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.signal import lfilter
from scipy.special import ndtr

from ...core.frames import OMEGA_EARTH_RPS, SPEED_OF_LIGHT_MPS, LocalFrame
from ...core.types import GLONASS, GPS, Drive, GnssEpoch, ImuSeries, OdometrySeries, Trajectory
from ..city import City, los_blocked, make_city

GRAVITY_MPS2 = 9.81                 # local gravity magnitude used for the IMU [m/s^2]
MU_EARTH_M3PS2 = 3.986004418e14     # WGS84 gravitational parameter [m^3/s^2]
GPS_SEMI_MAJOR_AXIS_M = 26_559_700.0
GLONASS_SEMI_MAJOR_AXIS_M = 25_508_000.0

# Independent random streams, one per ingredient. Append new names at the END only: the
# position in this tuple selects the SeedSequence child, so existing streams stay unchanged.
STREAMS = ('city', 'route', 'time', 'imu', 'odometry', 'constellation', 'clock', 'noise',
           'nlos', 'faults', 'camera')


def stream_rng(seed: int, name: str) -> np.random.Generator:
    """The independent random generator of one ingredient of the drive of ``seed``.

    Args:
        seed: Drive seed.
        name: One of :data:`STREAMS` (``'camera'`` is reserved for the camera stream).

    Returns:
        A fresh generator; calling twice gives identical sequences.
    """
    child = np.random.SeedSequence(int(seed)).spawn(len(STREAMS))[STREAMS.index(name)]
    return np.random.default_rng(child)


@dataclass(frozen=True)
class EmulationConfig:
    """Every physical parameter of the emulated drive (defaults follow the paper/design).

    Attributes:
        origin_llh: (lat_deg, lon_deg, alt_m) of the ENU origin (Frankfurt city centre).
        route_length_m: Length of the driven path [m].
        antenna_height_m: Height of the truth point (GNSS antenna = IMU) above ground [m].
        lane_offset_m: Lane centre to the right of the street centre line [m].
        turn_radius_m: Radius of the turn arcs at intersections [m].
        cruise_speed_mps: (min, max) speed limit drawn per street segment [m/s].
        turn_speed_mps: Speed limit in turns [m/s].
        accel_mps2: Maximum acceleration [m/s^2].
        decel_mps2: Maximum braking deceleration [m/s^2].
        stop_prob: Probability of stopping at an intersection (traffic light).
        stop_duration_s: (min, max) uniform dwell time of a stop [s].
        standstill_s: Standstill at the start and at the end of the drive [s].
        smoothing_s: Std of the Gaussian kernel smoothing the distance-time profile [s].
        imu_rate_hz: IMU and truth rate [Hz].
        odom_rate_hz: Odometry rate [Hz] (must divide ``imu_rate_hz``).
        accel_noise_mps2: Accelerometer white noise std per sample [m/s^2].
        gyro_noise_rps: Gyro white noise std per sample [rad/s].
        accel_bias_mps2: Std of the constant accelerometer bias per axis [m/s^2].
        gyro_bias_rps: Std of the constant gyro bias per axis [rad/s].
        odom_speed_std_mps: Wheel speed noise std [m/s].
        odom_yaw_rate_std_rps: Odometry yaw-rate noise std [rad/s].
        n_sv: Satellites per GNSS epoch.
        max_gps: At most this many of them are GPS (the rest GLONASS).
        elevation_mask_deg: Elevation mask [deg].
        pr_var_m2: Pseudorange white-noise variance [m^2].
        clock_bias0_m: Initial receiver clock bias ~ U(-x, x) [m].
        clock_drift0_mps: Initial clock drift ~ U(-x, x) [m/s].
        clock_bias_rw_m: Clock-bias random walk density [m/sqrt(s)].
        clock_drift_rw_mps: Clock-drift random walk density [m/s/sqrt(s)].
        isb_std_m: Std of the constant GLONASS-minus-GPS inter-system bias [m].
        nlos_range_m: (min, max) of the NLOS excess delay [m].
        nlos_corr_time_s: Correlation time of the NLOS delay of one satellite [s].
        nlos_cn0_drop_db: (min, max) uniform C/N0 loss of a blocked satellite [dB].
        fault_free_start_s: No fault before this time (filter initialisation) [s].
        fault_episode_s: (min, max) uniform duration of a fault episode [s].
        fault_sigma_frac: Std of the fault magnitude as a fraction of ``bias_m``.
        fault_clip_m: (min, max) clip of the fault magnitude [m] (paper: 20-200 m).
    """

    origin_llh: tuple[float, float, float] = (50.1109, 8.6821, 110.0)
    route_length_m: float = 2300.0
    antenna_height_m: float = 1.8
    lane_offset_m: float = 3.0
    turn_radius_m: float = 10.0
    cruise_speed_mps: tuple[float, float] = (8.0, 14.0)
    turn_speed_mps: float = 5.0
    accel_mps2: float = 1.5
    decel_mps2: float = 2.0
    stop_prob: float = 0.3
    stop_duration_s: tuple[float, float] = (3.0, 20.0)
    standstill_s: float = 3.0
    smoothing_s: float = 0.5
    imu_rate_hz: float = 100.0
    odom_rate_hz: float = 10.0
    accel_noise_mps2: float = 0.05
    gyro_noise_rps: float = 2e-3
    accel_bias_mps2: float = 0.05
    gyro_bias_rps: float = 1e-3
    odom_speed_std_mps: float = 0.05
    odom_yaw_rate_std_rps: float = 0.01
    n_sv: int = 12
    max_gps: int = 8
    elevation_mask_deg: float = 10.0
    pr_var_m2: float = 10.0
    clock_bias0_m: float = 3.0e5
    clock_drift0_mps: float = 50.0
    clock_bias_rw_m: float = 0.3
    clock_drift_rw_mps: float = 0.05
    isb_std_m: float = 15.0
    nlos_range_m: tuple[float, float] = (5.0, 60.0)
    nlos_corr_time_s: float = 30.0
    nlos_cn0_drop_db: tuple[float, float] = (6.0, 14.0)
    fault_free_start_s: float = 10.0
    fault_episode_s: tuple[float, float] = (3.0, 10.0)
    fault_sigma_frac: float = 0.25
    fault_clip_m: tuple[float, float] = (20.0, 200.0)


# --------------------------------------------------------------------------------------------
# Route geometry
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Route:
    """A planar path made of straight lines (``kappa = 0``) and circular arcs.

    Primitive ``i`` starts at arc length ``s0_m[i]`` at point ``p0_m[i]`` with heading
    ``psi0_rad[i]`` (ENU, counter-clockwise from east) and has constant curvature
    ``kappa_pm[i]`` (positive = left turn) over ``len_m[i]``.

    Attributes:
        s0_m: (P,) start arc length [m].
        len_m: (P,) length [m].
        p0_m: (P, 2) start point (east, north) [m].
        psi0_rad: (P,) start heading [rad].
        kappa_pm: (P,) curvature [1/m].
        node_s_m: (N,) arc length where the route passes each grid node it visits [m].
        stop_s_m: (N,) arc length of the stop line before each node [m].
    """

    s0_m: np.ndarray
    len_m: np.ndarray
    p0_m: np.ndarray
    psi0_rad: np.ndarray
    kappa_pm: np.ndarray
    node_s_m: np.ndarray
    stop_s_m: np.ndarray

    @property
    def length_m(self) -> float:
        """Total length [m]."""
        return float(self.s0_m[-1] + self.len_m[-1])

    def evaluate(self, s_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Point, heading and curvature at arc lengths ``s_m``.

        Args:
            s_m: (n,) arc lengths [m], clipped to ``[0, length_m]``.

        Returns:
            ``(en (n, 2) [m], psi (n,) [rad, unwrapped], kappa (n,) [1/m])``.
        """
        s = np.clip(np.asarray(s_m, dtype=float), 0.0, self.length_m)
        i = np.clip(np.searchsorted(self.s0_m, s, side='right') - 1, 0, len(self.s0_m) - 1)
        u = s - self.s0_m[i]
        k, psi0 = self.kappa_pm[i], self.psi0_rad[i]
        psi = psi0 + k * u
        straight = k == 0.0
        k_safe = np.where(straight, 1.0, k)
        de = np.where(straight, u * np.cos(psi0), (np.sin(psi) - np.sin(psi0)) / k_safe)
        dn = np.where(straight, u * np.sin(psi0), -(np.cos(psi) - np.cos(psi0)) / k_safe)
        return self.p0_m[i] + np.column_stack([de, dn]), psi, k


_DIRS = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])   # E, N, W, S; +1 index = left turn


def _walk_nodes(city: City, rng: np.random.Generator, min_len_m: float):
    """Random walk over interior street nodes: no U-turns, revisited streets discouraged.

    Returns:
        (m+1, 2) node grid indices and (m,) direction indices (into ``_DIRS``) of the edges.
    """
    nx, ny = len(city.street_e_m) - 1, len(city.street_n_m) - 1
    # Interior streets only, so that the route always runs in a canyon.
    node = np.array([rng.integers(1, nx), rng.integers(1, ny)])
    d = int(rng.integers(4))
    nodes, dirs, visited = [node.copy()], [], set()
    length = 0.0
    while True:
        options, weights = [], []
        for turn, w in ((0, 0.45), (1, 0.275), (-1, 0.275)):
            dn = (d + turn) % 4
            nxt = node + _DIRS[dn]
            if 1 <= nxt[0] <= nx - 1 and 1 <= nxt[1] <= ny - 1:
                edge = frozenset((tuple(node), tuple(nxt)))
                options.append(dn)
                weights.append(w * (0.1 if edge in visited else 1.0))
        if not options:
            raise RuntimeError('street grid too small for a route')
        weights = np.asarray(weights) / np.sum(weights)
        d = options[int(rng.choice(len(options), p=weights))]
        nxt = node + _DIRS[d]
        visited.add(frozenset((tuple(node), tuple(nxt))))
        nodes.append(nxt.copy())
        dirs.append(d)
        node = nxt
        length += city.pitch_m
        if length >= min_len_m:
            return np.asarray(nodes), np.asarray(dirs)


def _build_route(city: City, nodes: np.ndarray, dirs: np.ndarray, cfg: EmulationConfig,
                 length_m: float) -> Route:
    """Lane-centre path (drive on the right) with fillet arcs at the turns, cut to length."""
    r, off = cfg.turn_radius_m, cfg.lane_offset_m
    stop_back = 0.5 * city.street_width_m + 1.0   # stop line before the crossing street

    def right(k):
        v = _DIRS[k].astype(float)
        return np.array([v[1], -v[0]])

    prims = []    # (p0, psi0, kappa, length)
    node_s, stop_s = [], []
    centre = np.array([city.street_e_m[nodes[0][0]], city.street_n_m[nodes[0][1]]])
    p = centre + off * right(dirs[0])
    s = 0.0
    for i in range(1, len(nodes)):
        d_in = dirs[i - 1]
        centre = np.array([city.street_e_m[nodes[i][0]], city.street_n_m[nodes[i][1]]])
        u_in = _DIRS[d_in].astype(float)
        psi_in = np.arctan2(u_in[1], u_in[0])
        d_out = dirs[i] if i < len(dirs) else d_in
        turn = (d_out - d_in) % 4          # 0 straight, 1 left, 3 right
        if turn == 0:
            # Straight on: the line simply continues; close it at the node for bookkeeping.
            end = centre + off * right(d_in)
            seg = float(np.dot(end - p, u_in))
            prims.append((p, psi_in, 0.0, seg))
            s += seg
            node_s.append(s)
            stop_s.append(s - stop_back)
            p = end
            continue
        corner = centre + off * right(d_in) + off * right(d_out)
        a_start = corner - r * u_in
        seg = float(np.dot(a_start - p, u_in))
        prims.append((p, psi_in, 0.0, seg))
        s += seg
        # Stop line, measured along the incoming lane, never inside the arc.
        along_start = float(np.dot(a_start - centre, u_in))
        stop_s.append(s + min(0.0, -stop_back - along_start))
        kappa = 1.0 / r if turn == 1 else -1.0 / r
        arc = 0.5 * np.pi * r
        prims.append((a_start, psi_in, kappa, arc))
        node_s.append(s + 0.5 * arc)
        s += arc
        p = corner + r * _DIRS[d_out].astype(float)
    s0 = np.concatenate([[0.0], np.cumsum([q[3] for q in prims])[:-1]])
    lens = np.array([q[3] for q in prims])
    keep = s0 < length_m
    lens = np.minimum(lens[keep], length_m - s0[keep])
    node_s, stop_s = np.asarray(node_s), np.asarray(stop_s)
    inside = node_s < length_m - 1.0
    return Route(s0_m=s0[keep], len_m=lens,
                 p0_m=np.array([q[0] for q in prims])[keep],
                 psi0_rad=np.array([q[1] for q in prims])[keep],
                 kappa_pm=np.array([q[2] for q in prims])[keep],
                 node_s_m=node_s[inside], stop_s_m=np.maximum(stop_s[inside], 0.0))


# --------------------------------------------------------------------------------------------
# Motion along the route
# --------------------------------------------------------------------------------------------

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


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def _speed_profile(route: Route, rng: np.random.Generator, cfg: EmulationConfig):
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
        return Pose(enu_m=enu, yaw_rad=_wrap(psi), speed_mps=v, accel_mps2=a,
                    yaw_rate_rps=kappa * v)


def _unix_to_era_rad(t_unix_s: float) -> float:
    """Earth rotation angle (IERS 2003, UT1 ~ UTC) at a Unix time [rad]."""
    jd = t_unix_s / 86400.0 + 2440587.5
    return float(2 * np.pi * ((0.7790572732640 + 1.00273781191135448 * (jd - 2451545.0)) % 1.0))


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
    nodes, dirs = _walk_nodes(city, rng, cfg.route_length_m + 2 * city.pitch_m)
    route = _build_route(city, nodes, dirs, cfg, cfg.route_length_m)
    t, s, v, a, stops = _speed_profile(route, rng, cfg)
    # Start between 08:00 and 16:00 UTC on 2024-06-12, a whole second.
    base = int(_dt.datetime(2024, 6, 12, 8, tzinfo=_dt.timezone.utc).timestamp())
    t0_s = base + int(stream_rng(seed, 'time').integers(0, 8 * 3600))
    return Scenario(seed=int(seed), config=cfg, city=city, frame=LocalFrame(*cfg.origin_llh),
                    route=route, t_s=t, s_m=s, v_mps=v, a_mps2=a, t0_ns=t0_s * 10 ** 9,
                    stops=stops)


# --------------------------------------------------------------------------------------------
# GNSS constellation and pseudoranges
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class _Constellation:
    """Circular orbits: semi-major axis, inclination, RAAN, argument of latitude at t = 0."""

    system: np.ndarray
    sv_id: np.ndarray
    a_m: np.ndarray
    incl: np.ndarray
    raan: np.ndarray
    u0: np.ndarray
    era0: float   # Earth rotation angle at t = 0 [rad]

    def ecef(self, t_s: np.ndarray) -> np.ndarray:
        """(n, S, 3) satellite ECEF positions (frame of time t) at times (n,) or (n, S) [m]."""
        t = np.asarray(t_s, dtype=float)
        if t.ndim == 1:
            t = t[:, None]
        u = self.u0 + np.sqrt(MU_EARTH_M3PS2 / self.a_m ** 3) * t
        cu, su = np.cos(u), np.sin(u)
        co, so = np.cos(self.raan), np.sin(self.raan)
        ci, si = np.cos(self.incl), np.sin(self.incl)
        x = self.a_m * (co * cu - so * su * ci)
        y = self.a_m * (so * cu + co * su * ci)
        z = self.a_m * su * si
        th = self.era0 + OMEGA_EARTH_RPS * t
        ct, st = np.cos(th), np.sin(th)
        return np.stack([ct * x + st * y, -st * x + ct * y, np.broadcast_to(z, x.shape)], -1)


def _make_constellation(rng: np.random.Generator, era0: float) -> _Constellation:
    """GPS 6x5 and GLONASS 3x8 with a seeded overall phase and small slot irregularities."""
    deg = np.pi / 180.0
    p, k = np.meshgrid(np.arange(6), np.arange(5), indexing='ij')
    gps_raan = rng.uniform(0, 2 * np.pi) + 60 * deg * p.ravel()
    gps_u = (rng.uniform(0, 2 * np.pi) + 72 * deg * k.ravel() + 14 * deg * p.ravel()
             + rng.normal(0, 4 * deg, p.size))
    p2, k2 = np.meshgrid(np.arange(3), np.arange(8), indexing='ij')
    glo_raan = rng.uniform(0, 2 * np.pi) + 120 * deg * p2.ravel()
    glo_u = rng.uniform(0, 2 * np.pi) + 45 * deg * k2.ravel() + 15 * deg * p2.ravel()
    n_gps, n_glo = p.size, p2.size
    return _Constellation(
        system=np.r_[np.full(n_gps, GPS), np.full(n_glo, GLONASS)],
        sv_id=np.r_[np.arange(1, n_gps + 1), np.arange(1, n_glo + 1)],
        a_m=np.r_[np.full(n_gps, GPS_SEMI_MAJOR_AXIS_M),
                  np.full(n_glo, GLONASS_SEMI_MAJOR_AXIS_M)],
        incl=np.r_[np.full(n_gps, 55.0 * deg), np.full(n_glo, 64.8 * deg)],
        raan=np.r_[gps_raan, glo_raan], u0=np.r_[gps_u, glo_u], era0=era0)


def _rot_z(xyz: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Rotate ECEF vectors into the frame turned by ``theta`` about z (as sagnac_corrected)."""
    c, s = np.cos(theta), np.sin(theta)
    return np.stack([c * xyz[..., 0] + s * xyz[..., 1], -s * xyz[..., 0] + c * xyz[..., 1],
                     xyz[..., 2]], -1)


def _light_time(const: _Constellation, t_rx_s: np.ndarray, rx_ecef: np.ndarray):
    """Solve the light-time equation for every (epoch, satellite).

    Finds the flight time ``tau`` with ``c tau = |R_z(w tau) x_sv(t_rx - tau) - x_rx|``: the
    satellite position at transmission, expressed in the Earth-fixed frame of the reception
    time. The fixed-point iteration contracts by ~v_sv/c ~ 1e-5 per step.

    Returns:
        ``(sv_tx (n, S, 3) ECEF of transmission time, sv_rx (n, S, 3) same point in the
        ECEF frame of reception, range (n, S) geometric range [m])``.
    """
    tau = np.full((len(t_rx_s), len(const.system)), 0.075)
    for _ in range(4):
        sv_tx = const.ecef(t_rx_s[:, None] - tau)
        sv_rx = _rot_z(sv_tx, OMEGA_EARTH_RPS * tau)
        rng_m = np.linalg.norm(sv_rx - rx_ecef[:, None, :], axis=-1)
        tau = rng_m / SPEED_OF_LIGHT_MPS
    sv_tx = const.ecef(t_rx_s[:, None] - tau)
    sv_rx = _rot_z(sv_tx, OMEGA_EARTH_RPS * tau)
    return sv_tx, sv_rx, np.linalg.norm(sv_rx - rx_ecef[:, None, :], axis=-1)


def _select(el_deg: np.ndarray, system: np.ndarray, cfg: EmulationConfig) -> np.ndarray:
    """Pick ``n_sv`` tracked satellites per epoch (kept while above the mask).

    Args:
        el_deg: (n, S) elevations.
        system: (S,) system ids.
        cfg: Parameters.

    Returns:
        (n, n_sv) satellite indices per epoch, sorted by (system, sv index).
    """
    out = np.empty((el_deg.shape[0], cfg.n_sv), dtype=np.int64)
    tracked: list[int] = []
    is_gps = system == GPS
    for k, el in enumerate(el_deg):
        vis = el > cfg.elevation_mask_deg
        keep = [i for i in tracked if vis[i]]
        n_gps = int(sum(is_gps[i] for i in keep))
        cand = [int(i) for i in np.argsort(-el) if vis[i] and i not in keep]
        for i in cand:                      # highest first, respecting the GPS cap
            if len(keep) == cfg.n_sv:
                break
            if is_gps[i] and n_gps >= cfg.max_gps:
                continue
            keep.append(i)
            n_gps += int(is_gps[i])
        for i in cand:                      # relax the cap if still short
            if len(keep) == cfg.n_sv:
                break
            if i not in keep:
                keep.append(i)
        if len(keep) < cfg.n_sv:
            raise RuntimeError(f'only {len(keep)} satellites above the mask at epoch {k}')
        tracked = keep
        out[k] = np.sort(keep)
    return out


def _fault_episodes(rng: np.random.Generator, t_ep: np.ndarray, rate_hz: float,
                    fraction: float, cfg: EmulationConfig) -> list[tuple[int, int]]:
    """Random fault episodes ``[start, stop)`` (epoch indices) covering ~``fraction``.

    Episode durations are U(fault_episode_s) seconds; the fault-free gaps between them are
    exponential with mean ``mean_episode * (1 - fraction) / fraction`` (at least one epoch),
    the first gap starting at ``fault_free_start_s``.
    """
    if fraction <= 0.0:
        return []
    mean_ep = 0.5 * sum(cfg.fault_episode_s) * rate_hz
    mean_gap = mean_ep * (1.0 - fraction) / max(fraction, 1e-9)
    k = int(np.searchsorted(t_ep, cfg.fault_free_start_s))
    out = []
    while True:
        k += max(1, int(round(rng.exponential(mean_gap)))) if mean_gap > 0 else 0
        n = max(1, int(round(rng.uniform(*cfg.fault_episode_s) * rate_hz)))
        if k >= len(t_ep):
            return out
        out.append((k, min(k + n, len(t_ep))))
        k += n


def make_emulated_drive(seed: int, faults: int = 0, bias_m: float = 100.0, nlos: bool = True,
                        duration_s: float | None = None, gnss_rate_hz: float = 1.0,
                        fault_fraction: float = 0.3,
                        config: EmulationConfig | None = None,
                        camera: bool = False) -> Drive:
    """Generate the seeded emulated urban drive.

    Pseudorange of satellite j at epoch k (metres)::

        pr = rho_kj + b_k + isb * [j is GLONASS] + n_kj + nlos_kj + f_kj

    * ``rho_kj``: geometric range from the light-time equation (satellite at transmission
      time, Earth rotation during the flight included). ``sv_pos_ecef_m`` holds the
      position at transmission in the ECEF frame of transmission, so a user must apply
      ``sagnac_corrected`` to recover ``rho``.
    * ``b_k``: receiver clock bias, ``b0 ~ U(-3e5, 3e5)`` m, drift ``d0 ~ U(-50, 50)`` m/s,
      both random walks (0.3 m/sqrt(s), 0.05 m/s/sqrt(s)). ``isb ~ N(0, 15^2)`` m, constant.
    * ``n_kj ~ N(0, 10 m^2)`` white (``var_m2`` = 10).
    * ``nlos_kj`` (only if ``nlos`` and the line of sight is blocked by a building):
      ``5 + 55 * Phi(x_j(t))`` m, where ``x_j`` is a unit-variance Gauss-Markov process of
      satellite j with correlation time 30 s and ``Phi`` the standard normal CDF, i.e.
      uniform on [5, 60] m and correlated in time; its C/N0 is lowered by U(6, 14) dB.
      LOS C/N0 is ``30 + 20 sin(el) + N(0, 1.5^2)`` dB-Hz.
    * ``f_kj`` (only if ``faults > 0``): fault episodes of U(3, 10) s, separated by
      exponential gaps so that about ``fault_fraction`` of the epochs after the first 10 s
      are faulty. In each episode ``faults`` of the 12 satellites (uniformly at random) get
      a bias constant over the episode: ``sign * clip(|N(bias_m, (bias_m/4)^2)|, 20, 200)``
      with a random sign (+/-1 equally likely). If a faulty satellite stops being tracked
      during its episode, another satellite takes its place so that every epoch of the
      episode has exactly ``faults`` faulty satellites. The same seed with a different
      ``faults`` gives the same episodes, and the faulty sets are nested.

    Args:
        seed: Drive seed (all randomness derives from it).
        faults: Number of faulty satellites per faulty epoch (0 .. 12).
        bias_m: Mean fault magnitude [m].
        nlos: Add NLOS errors on blocked satellites (False: open-sky-like measurements).
        duration_s: Keep only the first ``duration_s`` seconds (None: the whole drive).
        gnss_rate_hz: GNSS epoch rate [Hz] (the truth rate should be a multiple of it).
        fault_fraction: Target fraction of faulty epochs.
        config: Physical parameters (defaults when None).
        camera: Attach the rendered camera stream (``datasets.camera.with_camera``).

    Returns:
        The drive. ``info`` holds the provenance and the error decomposition; the arrays
        ``gnss_*`` of shape (n_epochs, 12) are aligned with each epoch's satellites.
    """
    cfg = config or EmulationConfig()
    if not 0 <= faults <= cfg.n_sv:
        raise ValueError(f'faults must be in 0..{cfg.n_sv}, got {faults}')
    if gnss_rate_hz <= 0:
        raise ValueError(f'gnss_rate_hz must be positive, got {gnss_rate_hz}')
    sc = make_scenario(seed, cfg)
    frame = sc.frame

    # --- truth, IMU, odometry (whole drive, cut at the end) ------------------------------
    pose = sc.pose_at(sc.t_s)
    n = len(sc.t_s)
    stamps = sc.stamps_ns(sc.t_s)
    truth_ecef = frame.enu_to_ecef(pose.enu_m)
    rng = stream_rng(seed, 'imu')
    acc_bias = rng.normal(0.0, cfg.accel_bias_mps2, 3)
    gyro_bias = rng.normal(0.0, cfg.gyro_bias_rps, 3)
    accel = np.column_stack([pose.accel_mps2, pose.speed_mps * pose.yaw_rate_rps,
                             np.full(n, GRAVITY_MPS2)])
    gyro = np.column_stack([np.zeros(n), np.zeros(n), pose.yaw_rate_rps])
    accel = accel + acc_bias + rng.normal(0.0, cfg.accel_noise_mps2, (n, 3))
    gyro = gyro + gyro_bias + rng.normal(0.0, cfg.gyro_noise_rps, (n, 3))
    rng = stream_rng(seed, 'odometry')
    step = int(round(cfg.imu_rate_hz / cfg.odom_rate_hz))
    io = np.arange(0, n, step)
    v_o = pose.speed_mps[io]
    speed = np.where(v_o < 1e-3, 0.0,
                     np.maximum(v_o + rng.normal(0.0, cfg.odom_speed_std_mps, len(io)), 0.0))
    yaw_rate = pose.yaw_rate_rps[io] + rng.normal(0.0, cfg.odom_yaw_rate_std_rps, len(io))

    # --- GNSS ----------------------------------------------------------------------------
    t_ep = np.arange(int(np.floor(sc.duration_s * gnss_rate_hz + 1e-9)) + 1) / gnss_rate_hz
    n_ep = len(t_ep)
    rx_enu = sc.pose_at(t_ep).enu_m
    rx_ecef = frame.enu_to_ecef(rx_enu)
    rng = stream_rng(seed, 'constellation')
    era0 = _unix_to_era_rad(sc.t0_ns / 1e9)
    for _ in range(100):
        # Redraw the constellation phase until >= n_sv + 2 satellites (>= 4 GLONASS) are
        # above the mask at every epoch, so that tracking never runs short.
        const = _make_constellation(rng, era0)
        sv_tx, sv_rx, rho = _light_time(const, t_ep, rx_ecef)
        los = (sv_rx - rx_ecef[:, None, :]) @ frame.rot_ecef_to_enu.T     # (n, S, 3) ENU
        el_all = np.degrees(np.arcsin(los[..., 2] / rho))
        vis = el_all > cfg.elevation_mask_deg
        if (vis.sum(1).min() >= cfg.n_sv + 2
                and vis[:, const.system == GLONASS].sum(1).min() >= cfg.n_sv - cfg.max_gps):
            break
    else:
        raise RuntimeError('no constellation phase with enough visible satellites')
    sel = _select(el_all, const.system, cfg)                           # (n_ep, 12)
    rows = np.arange(n_ep)[:, None]
    sys_sel, id_sel = const.system[sel], const.sv_id[sel]
    rho_sel, el_sel = rho[rows, sel], el_all[rows, sel]
    sv_pos = sv_tx[rows, sel]
    blocked = np.stack([los_blocked(sc.city, rx_enu[k], los[k, sel[k]]) for k in range(n_ep)])

    rng = stream_rng(seed, 'clock')
    dt_ep = 1.0 / gnss_rate_hz
    b0 = rng.uniform(-cfg.clock_bias0_m, cfg.clock_bias0_m)
    d0 = rng.uniform(-cfg.clock_drift0_mps, cfg.clock_drift0_mps)
    isb = rng.normal(0.0, cfg.isb_std_m)
    drift = d0 + np.concatenate(
        [[0.0], np.cumsum(rng.normal(0.0, cfg.clock_drift_rw_mps * np.sqrt(dt_ep), n_ep - 1))])
    clock = b0 + np.concatenate([[0.0], np.cumsum(
        drift[:-1] * dt_ep + rng.normal(0.0, cfg.clock_bias_rw_m * np.sqrt(dt_ep), n_ep - 1))])
    clock_sel = clock[:, None] + np.where(sys_sel == GLONASS, isb, 0.0)

    rng = stream_rng(seed, 'noise')
    noise = rng.normal(0.0, np.sqrt(cfg.pr_var_m2), (n_ep, cfg.n_sv))
    cn0 = 30.0 + 20.0 * np.sin(np.radians(el_sel)) + rng.normal(0.0, 1.5, (n_ep, cfg.n_sv))
    cn0_drop = rng.uniform(*cfg.nlos_cn0_drop_db, (n_ep, cfg.n_sv))

    rng = stream_rng(seed, 'nlos')
    phi = np.exp(-dt_ep / cfg.nlos_corr_time_s)
    w = rng.normal(0.0, 1.0, (n_ep, len(const.system)))
    w[1:] *= np.sqrt(1.0 - phi ** 2)     # x_0 ~ N(0, 1): stationary from the first epoch
    x = lfilter([1.0], [1.0, -phi], w, axis=0)
    lo, hi = cfg.nlos_range_m
    nlos_all = lo + (hi - lo) * ndtr(x)
    nlos_err = np.where(blocked, nlos_all[rows, sel], 0.0) if nlos else np.zeros_like(rho_sel)
    if nlos:
        cn0 = np.where(blocked, cn0 - cn0_drop, cn0)

    fault = np.zeros_like(rho_sel)
    fault_records = []
    rng = stream_rng(seed, 'faults')
    episodes = _fault_episodes(rng, t_ep, gnss_rate_hz, fault_fraction, cfg) if faults else []
    for e, (k0, k1) in enumerate(episodes):
        # Draws do not depend on ``faults``: the same seed gives the same episodes, and the
        # faulty satellites for f faults are the first f of the same random order.
        order = [int(i) for i in sel[k0][rng.permutation(cfg.n_sv)]]
        mag = np.clip(np.abs(rng.normal(bias_m, cfg.fault_sigma_frac * bias_m, 2 * cfg.n_sv)),
                      *cfg.fault_clip_m)
        biases = rng.choice([-1.0, 1.0], 2 * cfg.n_sv) * mag
        # Satellite -> bias: rank in ``order``; replacements take the spare draws 12, 13, ...
        bias_of = {i: biases[r] for r, i in enumerate(order)}
        for k in range(k0, k1):
            present = [int(i) for i in sel[k]]
            ranked = [i for i in order if i in present]
            ranked += [i for i in present if i not in order]
            for i in ranked[:faults]:
                if i not in bias_of:
                    order.append(i)
                    bias_of[i] = biases[(len(order) - 1) % len(biases)]
                j = present.index(i)
                fault[k, j] = bias_of[i]
                fault_records.append({
                    'epoch': k, 'stamp_ns': int(sc.stamps_ns(t_ep[k])), 'index': j,
                    'system': int(const.system[i]), 'sv_id': int(const.sv_id[i]),
                    'bias_m': float(bias_of[i]), 'episode': e})

    pr = rho_sel + clock_sel + noise + nlos_err + fault

    # --- cut to the requested duration and pack ------------------------------------------
    t_end = sc.duration_s if duration_s is None else min(float(duration_s), sc.duration_s)
    keep_t = sc.t_s <= t_end + 1e-9
    keep_o = keep_t[io]
    n_keep = int(np.sum(t_ep <= t_end + 1e-9))
    ep_stamps = sc.stamps_ns(t_ep)
    gnss = [GnssEpoch(stamp_ns=int(ep_stamps[k]), sv_pos_ecef_m=sv_pos[k], pr_m=pr[k],
                      var_m2=np.full(cfg.n_sv, cfg.pr_var_m2), sv_id=id_sel[k].astype(np.int64),
                      system=sys_sel[k].astype(np.int64), elevation_deg=el_sel[k],
                      cn0_dbhz=cn0[k])
            for k in range(n_keep)]
    odom = OdometrySeries(stamp_ns=stamps[io][keep_o], speed_mps=speed[keep_o],
                          yaw_rate_rps=yaw_rate[keep_o],
                          speed_var=np.full(int(keep_o.sum()), cfg.odom_speed_std_mps ** 2),
                          yaw_rate_var=np.full(int(keep_o.sum()),
                                               cfg.odom_yaw_rate_std_rps ** 2))
    imu = ImuSeries(stamp_ns=stamps[keep_t], accel_mps2=accel[keep_t], gyro_rps=gyro[keep_t])
    truth = Trajectory(stamp_ns=stamps[keep_t], ecef_m=truth_ecef[keep_t],
                       yaw_rad=pose.yaw_rad[keep_t])
    s_end = float(np.interp(t_end, sc.t_s, sc.s_m))
    info = {
        'generator': 'gnsscam_ros.datasets.emulated.drive.make_emulated_drive',
        'seed': int(seed), 'faults': int(faults), 'bias_m': float(bias_m), 'nlos': bool(nlos),
        'duration_s': float(t_end), 'gnss_rate_hz': float(gnss_rate_hz),
        'fault_fraction': float(fault_fraction), 'config': asdict(cfg),
        't0_ns': int(sc.t0_ns), 'route_length_m': s_end, 'stops': list(sc.stops),
        'systems': {'GPS': GPS, 'GLONASS': GLONASS},
        'gravity_mps2': GRAVITY_MPS2,
        'imu_bias': {'accel_mps2': acc_bias, 'gyro_rps': gyro_bias},
        'rx_clock_bias_m': clock[:n_keep], 'rx_clock_drift_mps': drift[:n_keep],
        'isb_glonass_m': float(isb),
        'gnss_truth_ecef_m': rx_ecef[:n_keep],
        'gnss_geometric_range_m': rho_sel[:n_keep],
        'gnss_clock_m': clock_sel[:n_keep],
        'gnss_noise_m': noise[:n_keep],
        'gnss_blocked': blocked[:n_keep],
        'gnss_nlos_m': nlos_err[:n_keep],
        'gnss_fault_m': fault[:n_keep],
        'gnss_faults': [r for r in fault_records if r['epoch'] < n_keep],
        'fault_episodes': [(a, min(b, n_keep)) for a, b in episodes if a < n_keep],
    }
    name = f'emulated-urban-s{seed}-f{faults}' + ('' if nlos else '-nonlos')
    drive = Drive(name=name, origin_llh=frame.origin_llh, gnss=gnss, odometry=odom, imu=imu,
                  truth=truth, camera=None, info=info)
    if camera:
        from .camera import with_camera      # camera.py imports this module
        drive = with_camera(drive)
    return drive
