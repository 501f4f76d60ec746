"""Dead reckoning: odometry and IMU samples -> planar states -> the motion between two GNSS
epochs (one implementation for the nodes and every offline run)."""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from .parameters import ParameterSpec, field_specs, invalid, parameter, problems
from .types import ImuSeries, OdometrySeries

# Online dead reckoning shared by imu_node (which publishes the states) and the epoch engine
# (``core.engine``: fusion_node and every offline run), which turns consecutive states into
# the MotionIncrement of each GNSS interval: one implementation, no rclpy.

ODOMETRY = 'odometry'
IMU = 'imu'
DR_SOURCES = (ODOMETRY, IMU)       # at equal stamps, odometry samples are taken first
YAW_RATE_SOURCES = (ODOMETRY, IMU)


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


def wrap_angle(angle_rad: float) -> float:
    """Wrap an angle to [-pi, pi) [rad]."""
    return float((angle_rad + np.pi) % (2.0 * np.pi) - np.pi)


@dataclass(frozen=True)
class DeadReckoningConfig:
    """Parameters of :class:`DeadReckoner`; each field's default, meaning, unit and range
    is its parameter metadata (``core.parameters``), from which imu_node declares its node
    parameters of the same names (``config/imu_node.yaml`` documents them).

    The speed comes from the odometry while it is received, else from the integrated
    forward acceleration; the yaw rate from ``yaw_rate_source`` while it is received, else
    the other source.
    """

    yaw_rate_source: str = parameter(
        ODOMETRY, "Yaw-rate source while both are received: 'odometry' (the vehicle's yaw "
        "rate, what the offline evaluation integrates) or 'imu' (gyro z); the other source "
        'is used while the preferred one is inactive.', choices=YAW_RATE_SOURCES)
    gyro_yaw_rate_var: float = parameter(
        1e-4, 'Variance of one gyro yaw-rate sample.', '(rad/s)^2', low=0.0)
    accel_var: float = parameter(
        0.01, 'Variance of one forward-acceleration sample.', '(m/s^2)^2', low=0.0)
    default_speed_var: float = parameter(
        0.0025, 'Speed variance used for an odometry sample (odom/twist) that reports none '
        '(covariance <= 0).', '(m/s)^2', low=0.0)
    default_yaw_rate_var: float = parameter(
        1e-4, 'Yaw-rate variance used for an odometry sample (odom/twist) that reports '
        'none.', '(rad/s)^2', low=0.0)
    speed_error_correlation_s: float = parameter(
        1.0, 'Without odometry the speed is the integral of the forward acceleration; its '
        'error is then not white but persists, and is taken to persist this long when it '
        'adds to the distance variance.', 's', low=0.0)
    output_period_s: float = parameter(
        0.1, 'Emit one state per this much stamp time, the first at or after each multiple '
        'of the period (a grid in absolute stamp time, so that stamps on a common grid, such '
        'as whole-second GNSS epochs and 100 Hz IMU samples, get a state exactly); 0 = one '
        'per sample stamp. The integration runs at every sample stamp either way: the fusion '
        'needs the motion between its epochs, and each published state costs each Python '
        'subscriber about a millisecond.', 's', low=0.0)

    def __post_init__(self):
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        reasons = problems(field_specs(DeadReckoningConfig), values)
        reasons += [f'{name} must be finite, got {value}' for name, value in values.items()
                    if isinstance(value, float) and not np.isfinite(value)]
        if reasons:
            raise invalid(reasons, 'dead-reckoning configuration')

    @classmethod
    def parameter_specs(cls) -> tuple[ParameterSpec, ...]:
        """Every field's parameter metadata, in field order."""
        return field_specs(cls, cls.__name__)


@dataclass(frozen=True)
class DeadReckoningState:
    """Planar dead-reckoned pose in the ``odom`` frame (origin and heading 0 at the start).

    Attributes:
        stamp_ns: Time of the state [ns].
        x_m: East-like coordinate in the odom frame [m].
        y_m: North-like coordinate in the odom frame [m].
        yaw_rad: Heading, counter-clockwise from the odom x axis, not wrapped [rad].
        speed_mps: Forward speed at ``stamp_ns`` [m/s].
        yaw_rate_rps: Yaw rate at ``stamp_ns`` [rad/s].
        speed_var: Variance of ``speed_mps`` [(m/s)^2].
        yaw_rate_var: Variance of ``yaw_rate_rps`` [(rad/s)^2].
        distance_var_m2: Accumulated variance of the travelled distance since the start
            [m^2] (along-track; the increments between two states are what matters).
        yaw_var_rad2: Accumulated heading variance since the start [rad^2].
    """

    stamp_ns: int
    x_m: float
    y_m: float
    yaw_rad: float
    speed_mps: float
    yaw_rate_rps: float
    speed_var: float
    yaw_rate_var: float
    distance_var_m2: float
    yaw_var_rad2: float


class DeadReckoner:
    """Integrates odometry twist and/or IMU samples into planar dead-reckoning states.

    Sources: odometry (forward speed and yaw rate, with variances) and IMU (forward
    acceleration and gyro z). Forward speed comes from the odometry while it is active,
    otherwise from integrating the IMU's forward acceleration (starting from rest: drifts).
    Yaw rate comes from ``config.yaw_rate_source`` while it is active, else the other.

    Samples are buffered per source; :meth:`advance` integrates up to the *watermark*, the
    newest stamp that every active source has reached, and emits the states of those sample
    stamps (one per ``config.output_period_s`` of stamp time), so that both
    signals can be interpolated linearly at every emitted stamp and the result does not
    depend on the order in which the two streams' messages arrive. Between two stamps the
    speed and yaw rate are integrated with the trapezoidal rule and the position advances
    along the mid-interval heading (as :func:`.particles.propagate`). Which sources are
    active is the caller's call (a node: received recently; offline: present).

    Args:
        config: Parameters.
    """

    def __init__(self, config: DeadReckoningConfig | None = None):
        self.config = config or DeadReckoningConfig()
        # Per source, samples as tuples (stamp_ns, value_a, value_b, var_a, var_b); odometry:
        # (speed, yaw rate, speed var, yaw-rate var), imu: (accel x, gyro z, 0, 0).
        self._samples: dict[str, list[tuple]] = {ODOMETRY: [], IMU: []}
        self.state: DeadReckoningState | None = None
        self._imu_speed = 0.0           # speed integrated from the accelerometer [m/s]
        self._imu_speed_var = 0.0
        self._last_accel: float | None = None
        self._last_emitted_ns: int | None = None

    def newest_stamp_ns(self, source: str) -> int | None:
        """Stamp of the newest buffered sample of ``source`` (None when none yet)."""
        samples = self._samples[source]
        return samples[-1][0] if samples else None

    def add_odometry(self, stamp_ns: int, speed_mps: float, yaw_rate_rps: float,
                     speed_var: float = 0.0, yaw_rate_var: float = 0.0) -> None:
        """Buffer one odometry sample.

        Args:
            stamp_ns: Sample time [ns]; must be newer than the previous odometry sample.
            speed_mps: Forward speed [m/s].
            yaw_rate_rps: Yaw rate [rad/s], counter-clockwise positive.
            speed_var: Speed variance [(m/s)^2]; <= 0 uses ``config.default_speed_var``.
            yaw_rate_var: Yaw-rate variance [(rad/s)^2]; <= 0 uses the default.

        Raises:
            ValueError: Non-finite values, or a stamp not after the previous sample's.
        """
        cfg = self.config
        self._add(ODOMETRY, stamp_ns, (float(speed_mps), float(yaw_rate_rps),
                                       float(speed_var) if speed_var > 0 else
                                       cfg.default_speed_var,
                                       float(yaw_rate_var) if yaw_rate_var > 0 else
                                       cfg.default_yaw_rate_var))

    def add_imu(self, stamp_ns: int, accel_x_mps2: float, gyro_z_rps: float) -> None:
        """Buffer one IMU sample (body x forward, z up).

        Raises:
            ValueError: Non-finite values, or a stamp not after the previous IMU sample's.
        """
        self._add(IMU, stamp_ns, (float(accel_x_mps2), float(gyro_z_rps), 0.0, 0.0))

    def _add(self, source: str, stamp_ns: int, values: tuple) -> None:
        if not all(np.isfinite(values)):
            raise ValueError(f'{source} sample at {stamp_ns} ns has non-finite values')
        newest = self.newest_stamp_ns(source)
        if newest is not None and stamp_ns <= newest:
            raise ValueError(f'{source} sample at {stamp_ns} ns is not after the previous '
                             f'one at {newest} ns')
        self._samples[source].append((int(stamp_ns), *values))

    def watermark_ns(self, active: tuple | set | list | None = None) -> int | None:
        """Newest stamp every active source has reached (None when nothing is active)."""
        sources = self._active(active)
        if not sources:
            return None
        return min(self._samples[s][-1][0] for s in sources)

    def _active(self, active) -> list[str]:
        wanted = DR_SOURCES if active is None else active
        return [s for s in DR_SOURCES if s in wanted and self._samples[s]]

    def advance(self, active: tuple | set | list | None = None) -> list[DeadReckoningState]:
        """Integrate the buffered samples up to the watermark.

        Args:
            active: Sources to use (None: every source with samples). An inactive source's
                samples are ignored for the stamps emitted now.

        Returns:
            The new states of the distinct sample stamps in ``(previous state, watermark]``
            of the active sources (thinned to one per ``config.output_period_s``), oldest
            first.
        """
        sources = self._active(active)
        mark = self.watermark_ns(sources)
        if mark is None:
            return []
        after = -1 if self.state is None else self.state.stamp_ns
        stamps = sorted({s[0] for src in sources for s in self._samples[src]
                         if after < s[0] <= mark})
        out = []
        period_ns = int(round(self.config.output_period_s * 1e9))
        for stamp in stamps:
            self.state = self._step(stamp, sources)
            last = self._last_emitted_ns
            if period_ns <= 0 or last is None or stamp // period_ns > last // period_ns:
                out.append(self.state)
                self._last_emitted_ns = stamp
        self._trim()
        return out

    def _interp(self, source: str, stamp_ns: int) -> tuple[np.ndarray, float]:
        """A source's values at ``stamp_ns`` and the length of its sample period there [s].

        Values are interpolated linearly between the bracketing samples (the watermark
        guarantees a sample at or after ``stamp_ns``); before the first sample the first
        value is held. Variances are those of the sample opening the period, not blended.
        """
        samples = self._samples[source]
        k = len(samples) - 1
        while k > 0 and samples[k - 1][0] >= stamp_ns:
            k -= 1
        hi = samples[k]
        if k == 0:
            period_s = (samples[1][0] - hi[0]) * 1e-9 if len(samples) > 1 else 0.0
            return np.array(hi[1:]), period_s
        lo = samples[k - 1]
        period_s = (hi[0] - lo[0]) * 1e-9
        if hi[0] == stamp_ns:
            return np.array(hi[1:]), period_s
        f = (stamp_ns - lo[0]) / (hi[0] - lo[0])
        values = np.array(lo[1:]) + f * (np.array(hi[1:]) - np.array(lo[1:]))
        values[2:] = lo[3:]
        return values, period_s

    def _step(self, stamp_ns: int, sources: list[str]) -> DeadReckoningState:
        cfg = self.config
        odo = self._interp(ODOMETRY, stamp_ns) if ODOMETRY in sources else None
        imu = self._interp(IMU, stamp_ns) if IMU in sources else None
        prev = self.state
        dt_s = 0.0 if prev is None else (stamp_ns - prev.stamp_ns) * 1e-9
        # Speed: odometry, else the integral of the forward acceleration.
        if odo is not None:
            speed, speed_var, speed_period = odo[0][0], odo[0][2], odo[1]
            self._imu_speed, self._imu_speed_var = speed, speed_var
        elif imu is not None:
            accel_prev = imu[0][0] if self._last_accel is None else self._last_accel
            self._imu_speed += 0.5 * (accel_prev + imu[0][0]) * dt_s
            self._imu_speed_var += cfg.accel_var * imu[1] * dt_s
            speed, speed_var = self._imu_speed, self._imu_speed_var
            speed_period = cfg.speed_error_correlation_s
        else:
            speed, speed_var, speed_period = 0.0, 0.0, 0.0
        if imu is not None:
            self._last_accel = imu[0][0]
        # Yaw rate: the preferred source while active, else the other.
        use_imu_yaw = imu is not None and (cfg.yaw_rate_source == IMU or odo is None)
        if use_imu_yaw:
            yaw_rate, yaw_rate_var, yaw_period = imu[0][1], cfg.gyro_yaw_rate_var, imu[1]
        elif odo is not None:
            yaw_rate, yaw_rate_var, yaw_period = odo[0][1], odo[0][3], odo[1]
        else:
            yaw_rate, yaw_rate_var, yaw_period = 0.0, 0.0, 0.0
        if prev is None:
            return DeadReckoningState(stamp_ns, 0.0, 0.0, 0.0, speed, yaw_rate, speed_var,
                                      yaw_rate_var, 0.0, 0.0)
        distance = 0.5 * (prev.speed_mps + speed) * dt_s
        dyaw = 0.5 * (prev.yaw_rate_rps + yaw_rate) * dt_s
        heading = prev.yaw_rad + 0.5 * dyaw
        # Each sample's error persists over its own sample period T: the variance grows by
        # sigma^2 * T * dt (= sigma^2 * T^2 per period).
        return DeadReckoningState(
            stamp_ns=stamp_ns, x_m=prev.x_m + distance * np.cos(heading),
            y_m=prev.y_m + distance * np.sin(heading), yaw_rad=prev.yaw_rad + dyaw,
            speed_mps=speed, yaw_rate_rps=yaw_rate, speed_var=speed_var,
            yaw_rate_var=yaw_rate_var,
            distance_var_m2=prev.distance_var_m2 + speed_var * speed_period * dt_s,
            yaw_var_rad2=prev.yaw_var_rad2 + yaw_rate_var * yaw_period * dt_s)

    def _trim(self) -> None:
        # Keep, per source, the newest sample at or before the state (for interpolation)
        # and everything after it.
        if self.state is None:
            return
        for source, samples in self._samples.items():
            k = 0
            while k + 1 < len(samples) and samples[k + 1][0] <= self.state.stamp_ns:
                k += 1
            if k:
                del samples[:k]


def dead_reckon(imu: ImuSeries | None, odometry: OdometrySeries | None,
                config: DeadReckoningConfig | None = None) -> list[DeadReckoningState]:
    """Run a :class:`DeadReckoner` over whole series, as imu_node does message by message.

    Samples are fed in stamp order (odometry first at equal stamps) and the states are
    advanced after every sample with the sources seen so far, which is what imu_node does
    when the messages arrive in stamp order.

    Returns:
        Every state, oldest first.
    """
    events = []
    if odometry is not None:
        events += [(int(t), 0, k) for k, t in enumerate(odometry.stamp_ns)]
    if imu is not None:
        events += [(int(t), 1, k) for k, t in enumerate(imu.stamp_ns)]
    events.sort()
    dr = DeadReckoner(config)
    seen: set[str] = set()
    out: list[DeadReckoningState] = []
    for stamp, source, k in events:
        if source == 0:
            dr.add_odometry(stamp, odometry.speed_mps[k], odometry.yaw_rate_rps[k],
                            odometry.speed_var[k], odometry.yaw_rate_var[k])
            seen.add(ODOMETRY)
        else:
            dr.add_imu(stamp, imu.accel_mps2[k, 0], imu.gyro_rps[k, 2])
            seen.add(IMU)
        out += dr.advance(seen)
    return out


def motion_between(s0: DeadReckoningState, s1: DeadReckoningState) -> MotionIncrement:
    """Motion from one dead-reckoning state to the next (consecutive states).

    The heading change is the wrapped difference (states close in time) and the distance
    the displacement projected on the mid heading, which inverts one integration step of
    :class:`DeadReckoner` exactly; the variances are the growth of the accumulated ones.
    """
    dyaw = wrap_angle(s1.yaw_rad - s0.yaw_rad)
    heading = s0.yaw_rad + 0.5 * dyaw
    distance = (s1.x_m - s0.x_m) * np.cos(heading) + (s1.y_m - s0.y_m) * np.sin(heading)
    return MotionIncrement(dt_s=(s1.stamp_ns - s0.stamp_ns) * 1e-9, distance_m=float(distance),
                           dyaw_rad=dyaw,
                           distance_var_m2=max(s1.distance_var_m2 - s0.distance_var_m2, 0.0),
                           dyaw_var_rad2=max(s1.yaw_var_rad2 - s0.yaw_var_rad2, 0.0))


#: Outcomes of :meth:`MotionAccumulator.add`.
ADDED, OUT_OF_ORDER, RESET = 'added', 'out_of_order', 'reset'
#: Slack on the accumulated variances before a decrease counts as a restart [m^2, rad^2].
RESET_VARIANCE_SLACK = 1e-9
#: Most dead-reckoning states a MotionAccumulator keeps (oldest dropped first): its age
#: limit is stamp time, so a stream of states nanoseconds apart would otherwise grow it
#: without bound, and every epoch's motion sums over it. 60 s at imu_node's 10 Hz is 600;
#: at 100 Hz (``output_period_s`` 0) 6,000.
MAX_MOTION_STATES = 20_000


class MotionAccumulator:
    """Buffer of dead-reckoning states that answers "how did the vehicle move from t0 to t1".

    fusion_node adds every ``odometry/dead_reckoning`` state and asks for the motion of each
    GNSS interval; an offline run does the same with the states of :func:`dead_reckon`.

    A dead reckoner that restarts (imu_node restarted) begins again at the odom origin with
    zero accumulated variance: the step from its last state to the new one is not motion.
    :meth:`add` detects it (an accumulated variance that shrinks, or a step faster than
    ``max_speed_mps``) and leaves that interval uncovered, so the filter treats it as
    unknown motion instead of a jump. Consecutive states further apart than ``max_gap_s``
    (the dead reckoning or its inputs stopped) leave their interval uncovered as well: a
    dead reckoner that resumes after a gap has integrated nothing real across it.

    Args:
        max_age_s: States older than this behind the newest are dropped [s].
        max_speed_mps: A step between consecutive states faster than this is a reset [m/s].
        max_gap_s: Longest interval between consecutive states taken as measured motion [s].
        max_states: Most states kept (the oldest are dropped first).
    """

    def __init__(self, max_age_s: float = 60.0, max_speed_mps: float = 40.0,
                 max_gap_s: float = 1.0, max_states: int = MAX_MOTION_STATES):
        self.max_age_s = float(max_age_s)
        self.max_speed_mps = float(max_speed_mps)
        self.max_gap_s = float(max_gap_s)
        self.max_states = max(int(max_states), 2)
        self.gaps = 0
        self.dropped = 0                # states dropped by max_states before their age
        self.states: list[DeadReckoningState] = []
        self.resets = 0
        # One segment per pair of consecutive states of one run of the dead reckoner:
        # (t0_ns, t1_ns, MotionIncrement).
        self._segments: list[tuple[int, int, MotionIncrement]] = []

    @property
    def newest_stamp_ns(self) -> int | None:
        """Stamp of the newest state (None when empty)."""
        return self.states[-1].stamp_ns if self.states else None

    def clear(self) -> None:
        """Forget every state (a new time base: nothing before it relates to what comes);
        the counters stay."""
        self.states = []
        self._segments = []

    def is_reset(self, prev: DeadReckoningState, state: DeadReckoningState) -> bool:
        """Whether ``state`` starts a new run of the dead reckoner rather than follow
        ``prev``: its accumulated variances shrank, or it is farther than the maximum
        speed allows."""
        if (state.distance_var_m2 < prev.distance_var_m2 - RESET_VARIANCE_SLACK
                or state.yaw_var_rad2 < prev.yaw_var_rad2 - RESET_VARIANCE_SLACK):
            return True
        dt_s = (state.stamp_ns - prev.stamp_ns) * 1e-9
        step_m = float(np.hypot(state.x_m - prev.x_m, state.y_m - prev.y_m))
        return step_m > self.max_speed_mps * dt_s + 1.0

    def add(self, state: DeadReckoningState) -> str:
        """Append a state.

        Returns:
            ``ADDED``; ``OUT_OF_ORDER`` (ignored) when it is not the newest; ``RESET`` when
            it starts a new run of the dead reckoner (kept, but the interval from the
            previous state is left uncovered).
        """
        if self.states and state.stamp_ns <= self.states[-1].stamp_ns:
            return OUT_OF_ORDER
        outcome = ADDED
        if self.states:
            prev = self.states[-1]
            if self.is_reset(prev, state):
                outcome = RESET
                self.resets += 1
            elif (state.stamp_ns - prev.stamp_ns) * 1e-9 > self.max_gap_s:
                self.gaps += 1
            else:
                self._segments.append((prev.stamp_ns, state.stamp_ns,
                                       motion_between(prev, state)))
        self.states.append(state)
        horizon = state.stamp_ns - int(self.max_age_s * 1e9)
        k = 0
        while k + 1 < len(self.states) and self.states[k + 1].stamp_ns <= horizon:
            k += 1
        excess = len(self.states) - k - self.max_states
        if excess > 0:
            self.dropped += excess
            k += excess
        if k:
            first = self.states[k].stamp_ns
            del self.states[:k]
            j = 0
            while j < len(self._segments) and self._segments[j][0] < first:
                j += 1
            del self._segments[:j]
        return outcome

    def increment(self, t0_ns: int, t1_ns: int) -> MotionIncrement:
        """Motion over ``[t0_ns, t1_ns]``: the sum of the overlapping segments.

        A segment that overlaps partly contributes in proportion to the overlap (constant
        speed and yaw rate within it). Time no segment covers (before the first state,
        after the newest, across a reset) is reported as ``unknown_s``: the caller's filter
        treats it as unknown motion; whether to wait for more states is the caller's call.

        Raises:
            ValueError: ``t1_ns < t0_ns``.
        """
        if t1_ns < t0_ns:
            raise ValueError(f'interval ends before it starts: {t0_ns} > {t1_ns}')
        distance = dyaw = distance_var = dyaw_var = 0.0
        covered_ns = 0
        for a, b, seg in self._segments:
            if b <= t0_ns or a >= t1_ns:
                continue
            overlap = min(b, t1_ns) - max(a, t0_ns)
            covered_ns += overlap
            f = overlap / (b - a)
            distance += f * seg.distance_m
            dyaw += f * seg.dyaw_rad
            distance_var += f * seg.distance_var_m2
            dyaw_var += f * seg.dyaw_var_rad2
        return MotionIncrement(dt_s=(t1_ns - t0_ns) * 1e-9, distance_m=distance, dyaw_rad=dyaw,
                               distance_var_m2=distance_var, dyaw_var_rad2=dyaw_var,
                               unknown_s=max(t1_ns - t0_ns - covered_ns, 0) * 1e-9)

    def odometry_series(self, t0_ns: int, t1_ns: int) -> OdometrySeries:
        """Speed and yaw-rate samples of the states in ``[t0_ns, t1_ns]`` and the last one
        before ``t0_ns``, as an :class:`OdometrySeries`.

        States after ``t1_ns`` are left out on purpose: whether they have arrived yet
        depends on timing, and the answer must not.
        """
        stamps = np.array([s.stamp_ns for s in self.states], dtype=np.int64)
        lo = max(int(np.searchsorted(stamps, t0_ns, side='right')) - 1, 0)
        hi = int(np.searchsorted(stamps, t1_ns, side='right'))
        sel = self.states[lo:hi]
        return OdometrySeries(
            stamp_ns=np.array([s.stamp_ns for s in sel], dtype=np.int64),
            speed_mps=np.array([s.speed_mps for s in sel]),
            yaw_rate_rps=np.array([s.yaw_rate_rps for s in sel]),
            speed_var=np.array([s.speed_var for s in sel]),
            yaw_rate_var=np.array([s.yaw_rate_var for s in sel]))
