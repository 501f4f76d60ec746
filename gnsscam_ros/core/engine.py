"""The epoch engine: every input of the filter in, one report per GNSS epoch out.

fusion_node, the offline evaluation (``gnsscam_eval``, the campaign, the demo's offline run)
and the benches all drive the filter through :class:`EpochEngine`, so that "the nodes
reproduce the offline run" holds by construction instead of by copies:

* dead-reckoning states (imu_node's ``odometry/dead_reckoning``, or offline the states of
  ``core.motion.dead_reckon`` over the drive's odometry and IMU) go into one
  ``MotionAccumulator``, which answers the motion of each GNSS interval;
* camera matches (the best database match of each image) go into a buffer; the matches of
  an interval are moved to the epoch with the dead-reckoned speed and yaw rate;
* GNSS epochs are queued until they are *ready* (:meth:`EpochEngine.waiting_for`): every
  input stream has reached the epoch's stamp, has ended, or has been waited for long
  enough (bounded waits, wall time, only when a clock is given);
* each epoch runs ``ParticleFilter.step`` and yields an :class:`EpochReport`: the
  filter's result, the one :class:`~.verdict.IntegrityVerdict` (decided by
  ``core.verdict.integrity_verdict``) that ``integrity_risk`` publishes, the particle
  cloud and the posteriors of the risk bound. Consumers take everything from the report
  and the engine's own attributes (:attr:`EpochEngine.config`, :attr:`EpochEngine.frame`,
  :meth:`EpochEngine.set_parameters`), never from the filter.

Which inputs an epoch uses never depends on when the later ones arrive: the motion and
the camera matches of an interval only use inputs stamped at or before its end (as long as
no stream runs more than its buffer, 60 s by default, ahead of the GNSS).

Never a lie, never a crash, whatever a caller feeds in (the nodes check messages where
they enter; this is the defence behind that, for every caller, offline ones included):

* inputs the engine cannot use are refused (``REFUSED``, counted ``refused_<input>``,
  the reason in :attr:`EpochEngine.last_refusal`) and change no state: dead-reckoning
  states and camera matches with non-finite or absurd values
  (:func:`dead_reckoning_problem`, :func:`camera_problem`), malformed GNSS epochs;
* what one epoch costs is bounded: at most ``FilterConfig.satellite_limit`` satellites
  and ``MAX_CAMERA_MATCHES`` camera images per epoch, at most ``MAX_CAMERA_BUFFER``
  buffered matches and ``MAX_MOTION_STATES`` dead-reckoning states;
* a filter whose state became invalid anyway (``ParticleFilter.step`` returns
  ``INVALID``) starts again from the next usable fix; until then every verdict is STALE
  and says why (:attr:`EpochEngine.reinitialising`), counted ``filter_resets``. A new
  time base of the inputs (:meth:`EpochEngine.reset_time_base`) does the same after
  dropping everything buffered.
"""
from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from .filter import (INVALID, MAX_STATE_COORDINATE, PROPAGATED, REINITIALISING, UPDATED,
                     EpochResult, FilterConfig, ParticleFilter)
from .frames import LocalFrame
from .fusion import MAX_CAMERA_MATCHES, CameraMeasurement, measurements_at_epoch
from .gnss import epoch_problem
from .integrity import PosteriorSet
from .motion import OUT_OF_ORDER, DeadReckoningState, MotionAccumulator
from .parameters import ParameterSpec, field_specs, invalid, parameter
from .particles import MotionIncrement
from .types import GnssEpoch
from .verdict import ERROR, OK, STALE, IntegrityVerdict, integrity_verdict, stale_verdict

# Importable from here as before: the verdict's levels and type (``core.verdict``).
__all__ = ['CAMERA', 'DEAD_RECKONING', 'DROPPED_OLDEST', 'ERROR', 'ESTIMATE_STATUSES',
           'MAX_BUFFER_S', 'MAX_CAMERA_BUFFER', 'MAX_DR_VARIANCE', 'MAX_GNSS_QUEUE',
           'MAX_ODOM_COORDINATE', 'MAX_DR_SPEED_MPS', 'MAX_TIMEOUT_S', 'MAX_WAIT_S',
           'MAX_DR_YAW_RATE_RPS', 'NO_MATCH', 'OK', 'QUEUED', 'REFUSED', 'STALE', 'EpochEngine',
           'EpochReport', 'InputTiming', 'IntegrityVerdict', 'ParticleCloud', 'best_match',
           'camera_problem', 'dead_reckoning_problem']

#: Filter statuses with an estimate to publish.
ESTIMATE_STATUSES = (UPDATED, PROPAGATED)
#: Outcomes of the ``add_*`` methods besides ``motion.ADDED``/``OUT_OF_ORDER``/``RESET``;
#: ``REFUSED``: the input failed the engine's checks and changed nothing.
QUEUED, DROPPED_OLDEST, NO_MATCH, REFUSED = 'queued', 'dropped_oldest', 'no_match', 'refused'
#: What a queued epoch waits for (:meth:`EpochEngine.waiting_for`).
DEAD_RECKONING, CAMERA = 'dead_reckoning', 'camera'

# Limits of the inputs the engine takes (beyond them a value comes from a fault, and
# its arithmetic would overflow or swamp the filter's). ``DR``: of a dead-reckoning state.
# They are the backstop behind the nodes' message limits (``msg_adapters.limits``), for
# every caller, offline ones included, so speed and yaw rate are at least as wide as the
# messages': motion a node accepted is never refused here (a test checks the order).
#: Largest odom-frame coordinate of a dead-reckoning state [m] and unwrapped heading
#: [rad]: the frame starts where the dead reckoner started, so it grows with the distance
#: driven; 1e9 m is 290 days at 40 m/s and still resolves 0.1 um.
MAX_ODOM_COORDINATE = 1e9
#: Fastest forward speed of a dead-reckoning state [m/s] (either direction; 360 km/h).
MAX_DR_SPEED_MPS = 100.0
#: Fastest yaw rate of a dead-reckoning state [rad/s] (a road vehicle stays below ~1.5; a
#: spin, 10). The message limit is 5 rad/s (``msg_adapters.limits.
#: MAX_MESSAGE_YAW_RATE_RPS``: what a car does); this one only keeps the arithmetic sane.
MAX_DR_YAW_RATE_RPS = 10.0
#: Largest variance of a dead-reckoning state (rates and accumulated) [SI units squared].
MAX_DR_VARIANCE = 1e12
#: Most camera matches buffered (the oldest dropped first, counted ``camera_dropped``):
#: the buffer's age limit is stamp time, and a 30 Hz camera fills 1,024 in 34 s.
MAX_CAMERA_BUFFER = 1024

#: Upper bounds of the waits and buffers of :class:`InputTiming` (fusion_node's
#: parameters of the same names): a wait delays every verdict, so longer than 10 s is no
#: longer a wait for a late message; a silence of 60 s is a stopped stream; 10 minutes of
#: history is more than any epoch uses.
MAX_WAIT_S = 10.0
MAX_TIMEOUT_S = 60.0
MAX_BUFFER_S = 600.0
MAX_GNSS_QUEUE = 10_000


def _finite_within(values, bound: float) -> bool:
    return bool(np.all(np.isfinite(values)) and np.all(np.abs(values) <= bound))


def _within(value: float, bound: float) -> bool:
    return math.isfinite(value) and abs(value) <= bound


def dead_reckoning_problem(state: DeadReckoningState) -> str | None:
    """Why the engine refuses a dead-reckoning state (None: it takes it): a non-integer
    stamp, or values non-finite or beyond the limits (``MAX_ODOM_COORDINATE``,
    ``MAX_DR_SPEED_MPS``, ``MAX_DR_YAW_RATE_RPS``, variances in [0, ``MAX_DR_VARIANCE``])."""
    if not isinstance(state.stamp_ns, (int, np.integer)) or isinstance(state.stamp_ns, bool):
        return f'stamp must be an integer number of nanoseconds, got {state.stamp_ns!r}'
    try:
        # Plain floats: one state per dead-reckoning message, numpy would cost 20 times more.
        x, y, yaw = float(state.x_m), float(state.y_m), float(state.yaw_rad)
        speed, rate = float(state.speed_mps), float(state.yaw_rate_rps)
        var = [float(state.speed_var), float(state.yaw_rate_var),
               float(state.distance_var_m2), float(state.yaw_var_rad2)]
    except (TypeError, ValueError):
        return 'values must be numbers'
    if not all(_within(v, MAX_ODOM_COORDINATE) for v in (x, y, yaw)):
        return (f'position or heading non-finite or beyond {MAX_ODOM_COORDINATE:g}: '
                f'({x:g}, {y:g}, {yaw:g})')
    if not _within(speed, MAX_DR_SPEED_MPS):
        return f'speed {speed:g} m/s non-finite or beyond {MAX_DR_SPEED_MPS:g} m/s'
    if not _within(rate, MAX_DR_YAW_RATE_RPS):
        return f'yaw rate {rate:g} rad/s non-finite or beyond {MAX_DR_YAW_RATE_RPS:g} rad/s'
    if not all(_within(v, MAX_DR_VARIANCE) and v >= 0.0 for v in var):
        return f'variances must be finite and in [0, {MAX_DR_VARIANCE:g}]: {var}'
    return None


def camera_problem(stamp_ns: int, measurement: CameraMeasurement | None) -> str | None:
    """Why the engine refuses a camera match (None: it takes it): a non-integer stamp, or
    a matched position that is not three finite map coordinates within
    ``filter.MAX_STATE_COORDINATE`` (the score is diagnostics only)."""
    if not isinstance(stamp_ns, (int, np.integer)) or isinstance(stamp_ns, bool):
        return f'stamp must be an integer number of nanoseconds, got {stamp_ns!r}'
    if measurement is None:
        return None
    try:
        position = np.asarray(measurement.position_enu_m, dtype=float)
    except (TypeError, ValueError):
        return 'the matched position must be numbers'
    if position.shape != (3,) or not _finite_within(position, MAX_STATE_COORDINATE):
        return (f'the matched position must be 3 finite map coordinates within '
                f'{MAX_STATE_COORDINATE:g} m, got {np.array2string(position, threshold=6)}')
    return None


@dataclass(frozen=True)
class InputTiming:
    """How long inputs are kept and waited for.

    Stamp times are the inputs' own; wall times only count when the caller passes a clock
    (``now_s``; a node passes ``time.monotonic()``, an offline run passes none and feeds
    its inputs in stamp order). Each field's default, meaning, unit and range is its
    parameter metadata (``core.parameters``): fusion_node declares every field as a node
    parameter of the same name from it. The upper bounds keep every wait and timeout a
    wait (``MAX_WAIT_S``, ``MAX_TIMEOUT_S``) and the buffers bounded (``MAX_BUFFER_S``).
    """

    odometry_buffer_s: float = parameter(
        60.0, 'Dead-reckoning history kept behind the newest state (stamp time).', 's',
        low=1.0, high=MAX_BUFFER_S, read_only=True)
    camera_buffer_s: float = parameter(
        60.0, 'Camera matches kept behind the newest image (stamp time): a memory bound for '
        'a camera running ahead of GNSS; matches at or before a processed epoch are dropped '
        "anyway (only the current interval's are used).", 's', low=0.0, high=MAX_BUFFER_S)
    gnss_queue_size: int | None = parameter(
        10, 'GNSS epochs waiting for their inputs at most; when full the oldest is dropped '
        '(None: unbounded, offline).', low=1, high=MAX_GNSS_QUEUE, read_only=True)
    odometry_wait_s: float = parameter(
        0.2, 'Longest wait for the dead reckoning to reach a GNSS epoch (wall time).', 's',
        low=0.0, high=MAX_WAIT_S)
    odometry_timeout_s: float = parameter(
        1.0, 'Dead reckoning silent this long is not waited for; before any has arrived, '
        'GNSS flowing this long without it means GNSS-only operation (wall time).', 's',
        low=0.0, high=MAX_TIMEOUT_S)
    camera_wait_s: float = parameter(
        0.2, 'Longest wait for the camera images due before a GNSS epoch (wall time).', 's',
        low=0.0, high=MAX_WAIT_S)
    camera_timeout_s: float = parameter(
        2.0, 'A camera whose newest image is this far behind the newest input of any '
        'stream has stopped and is not waited for (stamp time, so that offline runs decide '
        'alike).', 's', low=0.0, high=MAX_TIMEOUT_S)

    def __post_init__(self):
        reasons = []
        for spec in self.parameter_specs():
            value = getattr(self, spec.name)
            if spec.name == 'gnss_queue_size' and value is None:
                continue                    # unbounded: an offline run feeds every epoch
            if not isinstance(value, (int, float)) or isinstance(value, bool):
                reasons.append(f'{spec.name} must be a number, got {value!r}')
            elif spec.problem(value):
                reasons.append(f'{spec.problem(value)}, got {value!r}')
        if reasons:
            raise invalid(reasons, 'input timing')

    @classmethod
    def parameter_specs(cls) -> tuple[ParameterSpec, ...]:
        """Every field's parameter metadata, in field order."""
        return field_specs(cls, cls.__name__)


@dataclass(frozen=True)
class ParticleCloud:
    """The filter's particle set after an epoch (resampled or not), as published.

    Attributes:
        particles: (N, 4) east, north, up [m] and heading [rad] in the map frame.
        log_w: (N,) normalised log-weights.
    """

    particles: np.ndarray
    log_w: np.ndarray


@dataclass(frozen=True)
class EpochReport:
    """Everything one processed GNSS epoch gives its consumers (the nodes, the
    evaluation, the benches): none of them looks into the filter.

    Attributes:
        epoch: The GNSS epoch.
        result: The filter's result: estimate, covariance, heading, protection level,
            risk bounds and the other findings behind the verdict.
        verdict: The integrity verdict (``core.verdict.integrity_verdict``), the only
            one: fusion_node publishes it, the evaluation scores it.
        late: Inputs that had not reached the epoch when it ran after its bounded wait
            (``DEAD_RECKONING``, ``CAMERA``).
        cloud: The particle set after the epoch (None without an estimate: statuses
            other than ``ESTIMATE_STATUSES``).
        posterior_set: The M posteriors the risk bound saw (None unless updated).
    """

    epoch: GnssEpoch
    result: EpochResult
    verdict: IntegrityVerdict
    late: tuple = ()
    cloud: ParticleCloud | None = None
    posterior_set: PosteriorSet | None = None


def best_match(stamp_ns: int, positions_m: np.ndarray, scores: np.ndarray,
               frame_id: int) -> CameraMeasurement | None:
    """The filter's camera measurement of one image: its best match (None: no match).

    camera_node publishes the top-k matches best first for any consumer; the fusion uses
    the best one (the paper's match state).
    """
    if len(scores) == 0:
        return None
    return CameraMeasurement(stamp_ns=int(stamp_ns),
                             position_enu_m=np.asarray(positions_m[0], dtype=float),
                             score=float(scores[0]), frame_id=int(frame_id))


class EpochEngine:
    """The particle filter with its input buffers and the readiness of each epoch.

    Args:
        config: Filter parameters.
        frame: Map frame (None: anchored at the first robust fix).
        rng: The filter's random generator.
        timing: Buffers and waits (:class:`InputTiming`).
    """

    def __init__(self, config: FilterConfig, frame: LocalFrame | None = None,
                 rng: np.random.Generator | None = None, timing: InputTiming | None = None):
        self.timing = timing or InputTiming()
        self.filter = ParticleFilter(config, frame=frame, rng=rng)
        self.motion = MotionAccumulator(self.timing.odometry_buffer_s,
                                        config.max_speed_mps)
        self.camera: list[CameraMeasurement] = []
        self.queue: deque = deque()          # (epoch, queued at [wall s] or None)
        self.counts: dict[str, int] = {}
        #: Why the filter waits for a fix to start again (None: it does not); every
        #: verdict says so until a fix has initialised it.
        self.reinitialising: str | None = None
        #: Why the last refused input was refused ('' before any).
        self.last_refusal = ''
        self._camera_stamps: deque = deque(maxlen=16)   # every image, matched or not
        self._first_gnss_s: float | None = None
        self._last_dr_s: float | None = None

    @property
    def config(self) -> FilterConfig:
        """The filter parameters in force."""
        return self.filter.config

    def set_parameters(self, **changes) -> None:
        """Change filter parameters between epochs (``ParticleFilter.set_parameters``:
        validated as a whole ``FilterConfig``, the old ones stay on error)."""
        self.filter.set_parameters(**changes)

    @property
    def frame(self) -> LocalFrame | None:
        """The map frame (None until the first robust fix anchors it)."""
        return self.filter.frame

    @property
    def initialised(self) -> bool:
        """The filter has a particle state (a fix initialised it and it was not reset)."""
        return self.filter.initialised

    # ------------------------------------------------------------------ inputs
    def add_dead_reckoning(self, state: DeadReckoningState, now_s: float | None = None) -> str:
        """Buffer a dead-reckoning state: ``ADDED``, ``OUT_OF_ORDER`` (ignored), ``RESET``
        (a restarted dead reckoner; the interval across it is unknown motion) or
        ``REFUSED`` (:func:`dead_reckoning_problem`; nothing changed)."""
        problem = dead_reckoning_problem(state)
        if problem:
            return self._refuse('dead_reckoning', problem)
        outcome = self.motion.add(state)
        if outcome != OUT_OF_ORDER:
            self._last_dr_s = now_s
        return outcome

    def add_camera(self, stamp_ns: int, measurement: CameraMeasurement | None,
                   now_s: float | None = None) -> str:
        """Buffer one image's best match (None: the image matched nothing).

        Returns:
            ``ADDED``, ``NO_MATCH`` (the image still counts as seen), ``OUT_OF_ORDER``
            (older than the previous image: ignored) or ``REFUSED``
            (:func:`camera_problem`; nothing changed). Beyond ``MAX_CAMERA_BUFFER``
            buffered matches the oldest is dropped (counted ``camera_dropped``).
        """
        problem = camera_problem(stamp_ns, measurement)
        if problem:
            return self._refuse('camera', problem)
        if self._camera_stamps and stamp_ns < self._camera_stamps[-1]:
            return OUT_OF_ORDER
        self._camera_stamps.append(int(stamp_ns))
        if measurement is None:
            return NO_MATCH
        self.camera.append(measurement)
        horizon = stamp_ns - int(self.timing.camera_buffer_s * 1e9)
        self.camera = [m for m in self.camera if m.stamp_ns >= horizon]
        excess = len(self.camera) - MAX_CAMERA_BUFFER
        if excess > 0:
            del self.camera[:excess]
            self._count('camera_dropped', excess)
        return 'added'

    def add_gnss(self, epoch: GnssEpoch, now_s: float | None = None) -> str:
        """Queue a GNSS epoch: ``QUEUED``, ``DROPPED_OLDEST`` (queued; the queue was full),
        ``OUT_OF_ORDER`` (not after the newest queued epoch: ignored) or ``REFUSED``
        (malformed: ``gnss.epoch_problem``; nothing changed). Satellites are checked one
        by one when the epoch runs."""
        problem = epoch_problem(epoch)
        if problem:
            return self._refuse('gnss', problem)
        if self.queue and epoch.stamp_ns <= self.queue[-1][0].stamp_ns:
            return OUT_OF_ORDER
        if self._first_gnss_s is None:
            self._first_gnss_s = now_s
        outcome = QUEUED
        size = self.timing.gnss_queue_size
        if size is not None and len(self.queue) >= size:
            self.queue.popleft()
            self._count('dropped_epochs')
            outcome = DROPPED_OLDEST
        self.queue.append((epoch, now_s))
        return outcome

    # ------------------------------------------------------------------ readiness
    def waiting_for(self, stamp_ns: int, queued_s: float | None = None,
                    now_s: float | None = None) -> tuple[str, ...]:
        """The input streams an epoch at ``stamp_ns`` still waits for (empty: ready).

        The first fix needs no motion and no camera. Otherwise the dead reckoning must
        have reached the stamp unless it is silent (``odometry_timeout_s``, wall time) or
        was never seen while GNSS flowed that long; the camera must have delivered every
        image due up to the stamp (no image is due when the time since its newest image
        is below its frame period) unless it is ``camera_timeout_s`` behind. Bounded
        waits (``odometry_wait_s``, ``camera_wait_s`` since ``queued_s``) end any wait.
        """
        if not self.filter.initialised:
            return ()
        waits = []
        if self._dead_reckoning_due(stamp_ns, now_s):
            waits.append(DEAD_RECKONING)
        if self._camera_due(stamp_ns):
            waits.append(CAMERA)
        if not waits or now_s is None or queued_s is None:
            return tuple(waits)
        waited = now_s - queued_s
        bound = {DEAD_RECKONING: self.timing.odometry_wait_s,
                 CAMERA: self.timing.camera_wait_s}
        return tuple(w for w in waits if waited < bound[w])

    def _latest_input_ns(self) -> int:
        """Newest stamp any input stream has delivered (GNSS queued, motion, camera)."""
        stamps = [self.queue[-1][0].stamp_ns] if self.queue else []
        if self.motion.newest_stamp_ns is not None:
            stamps.append(self.motion.newest_stamp_ns)
        if self._camera_stamps:
            stamps.append(self._camera_stamps[-1])
        return max(stamps, default=0)

    def _dead_reckoning_due(self, stamp_ns: int, now_s: float | None) -> bool:
        newest = self.motion.newest_stamp_ns
        if newest is not None and newest >= stamp_ns:
            return False
        timeout = self.timing.odometry_timeout_s
        if now_s is None:
            # Offline (inputs in stamp order): due unless it never started or the other
            # streams are more than the timeout past its newest state (it stopped).
            return (newest is not None
                    and (self._latest_input_ns() - newest) * 1e-9 <= timeout)
        if self._last_dr_s is None:
            # None yet: its first states travel another path than GNSS (imu_node) and may
            # come after the second epoch; GNSS flowing this long without any is
            # GNSS-only operation, with nothing to wait for.
            return now_s - (self._first_gnss_s if self._first_gnss_s is not None
                            else now_s) <= timeout
        return now_s - self._last_dr_s <= timeout

    def _camera_due(self, stamp_ns: int) -> bool:
        stamps = self._camera_stamps
        if not stamps or stamps[-1] >= stamp_ns:
            return False
        if (self._latest_input_ns() - stamps[-1]) * 1e-9 > self.timing.camera_timeout_s:
            return False                   # the camera stopped: GNSS (and motion) only
        if len(stamps) < 2:
            return False                   # no frame period known yet
        period_ns = float(np.median(np.diff(np.asarray(stamps, dtype=np.int64))))
        return stamp_ns - stamps[-1] >= period_ns

    # ------------------------------------------------------------------ epochs
    def ready_reports(self, now_s: float | None = None,
                      flush: bool = False) -> Iterator[EpochReport]:
        """Run the queued epochs that are ready, oldest first, yielding each report before
        the next epoch runs (``flush``: all of them, e.g. when an offline run's inputs
        have ended)."""
        while self.queue:
            epoch, queued_s = self.queue[0]
            if not flush and self.waiting_for(epoch.stamp_ns, queued_s, now_s):
                return
            self.queue.popleft()
            late = tuple(w for w in (DEAD_RECKONING, CAMERA)
                         if not flush and now_s is not None and queued_s is not None
                         and self._still_due(w, epoch.stamp_ns, now_s))
            for w in late:
                self._count(f'{w}_late')
            yield self.step(epoch, late)

    def _still_due(self, what: str, stamp_ns: int, now_s: float) -> bool:
        if what == DEAD_RECKONING:
            return self.filter.initialised and self._dead_reckoning_due(stamp_ns, now_s)
        return self.filter.initialised and self._camera_due(stamp_ns)

    def step(self, epoch: GnssEpoch, late: tuple = ()) -> EpochReport:
        """Run the filter on one epoch with the buffered motion and camera matches.

        An ``INVALID`` result (the filter discarded a broken state) counts
        ``filter_resets`` and makes every verdict STALE until a fix has initialised the
        filter again (:attr:`reinitialising`).
        """
        filt = self.filter
        t0 = filt.last_stamp_ns
        motion = self.motion_between(t0, epoch.stamp_ns)
        camera = self.camera_at(t0, epoch.stamp_ns)
        result = filt.step(epoch, motion, camera)
        if filt.last_stamp_ns is not None:
            # Later intervals start after the filter's last epoch: older matches are spent.
            self.camera = [m for m in self.camera if m.stamp_ns > filt.last_stamp_ns]
        self._count(f'epochs_{result.status}')
        if result.status == INVALID:
            self._count('filter_resets')
            self.reinitialising = result.reason
        elif result.status == UPDATED:
            self.reinitialising = None
        cloud = (ParticleCloud(filt.particles, filt.log_w)
                 if result.status in ESTIMATE_STATUSES else None)
        return EpochReport(epoch, result, self.verdict_of(result), late, cloud,
                           filt.posterior_set if result.status == UPDATED else None)

    def reset_time_base(self, reason: str) -> None:
        """The inputs adopt a new time base (a deliberate jump of their stamps): drop the
        queued epochs, the dead-reckoning states, the camera matches and the filter's
        state and time, so that nothing measured before the jump meets anything after it.
        The next usable fix initialises the filter (map frame kept); until then every
        verdict is STALE and says so. Counted ``time_base_resets``.

        Args:
            reason: What happened (it is part of the verdicts' message).
        """
        self.queue.clear()
        self.motion.clear()
        self.camera = []
        self._camera_stamps.clear()
        self._first_gnss_s = None
        self._last_dr_s = None
        self.filter.reset()
        self.filter.last_stamp_ns = None
        self._count('time_base_resets')
        self.reinitialising = f'time base reset ({reason}): {REINITIALISING}'

    def motion_between(self, t0_ns: int | None, t1_ns: int) -> MotionIncrement | None:
        """The motion argument of ``ParticleFilter.step`` (None: no dead reckoning yet,
        or the first epoch)."""
        if t0_ns is None or t1_ns <= t0_ns or not self.motion.states:
            return None
        return self.motion.increment(t0_ns, t1_ns)

    def camera_at(self, t0_ns: int | None, t1_ns: int) -> list[CameraMeasurement] | None:
        """The camera argument of ``ParticleFilter.step``: the matches of ``(t0, t1]``
        moved to ``t1`` with the dead-reckoned speed and yaw rate (None: none)."""
        last = self.filter.last_result
        if (not self.camera or t0_ns is None or t1_ns <= t0_ns or last is None
                or not np.isfinite(last.yaw_rad)):
            return None
        inside = [m for m in self.camera if t0_ns < m.stamp_ns <= t1_ns]
        if len(inside) > MAX_CAMERA_MATCHES:
            # What one epoch fuses is bounded; the newest images move least to the epoch.
            self._count('camera_over_limit', len(inside) - MAX_CAMERA_MATCHES)
            inside = inside[-MAX_CAMERA_MATCHES:]
        odometry = self.motion.odometry_series(t0_ns, t1_ns) if self.motion.states else None
        return measurements_at_epoch(inside, odometry, t0_ns, t1_ns, last.yaw_rad) or None

    def twist_at(self, stamp_ns: int) -> tuple[float, float, float, float] | None:
        """``(speed, yaw rate, their variances)`` of the newest dead-reckoning state at or
        before ``stamp_ns`` and within ``max_gap_s`` of it (None: unknown)."""
        for state in reversed(self.motion.states):
            if state.stamp_ns <= stamp_ns:
                if (stamp_ns - state.stamp_ns) * 1e-9 <= self.motion.max_gap_s:
                    return (state.speed_mps, state.yaw_rate_rps, state.speed_var,
                            state.yaw_rate_var)
                break
        return None

    # ------------------------------------------------------------------ verdicts
    def verdict_of(self, result: EpochResult) -> IntegrityVerdict:
        """The integrity verdict of an epoch result (``core.verdict.integrity_verdict``,
        with the engine's own findings: re-initialisation, dead-reckoning resets)."""
        return integrity_verdict(result, self.filter.config, self.reinitialising,
                                 self.motion.resets)

    def stale_verdict(self, stamp_ns: int, message: str) -> IntegrityVerdict:
        """A STALE verdict for silence (no GNSS, or no epoch processed): no valid
        solution behind it; the last epoch's stamp is carried."""
        return stale_verdict(stamp_ns, (message,), self.filter.config,
                             self.filter.last_stamp_ns)

    def _count(self, key: str, n: int = 1) -> None:
        self.counts[key] = self.counts.get(key, 0) + n

    def _refuse(self, what: str, problem: str) -> str:
        self._count(f'refused_{what}')
        self.last_refusal = f'{what}: {problem}'
        return REFUSED
