"""What every gnsscam_ros node shares: parameter declaration with descriptors and
validation, rejection/drop counters, processing-time statistics and the ``diagnostics``
report, QoS profiles and the ready line; the process around the nodes (``main()``, spinning,
stopping) is :mod:`.runtime`.

Exit codes of the node executables (:func:`.runtime.run_node`, pipeline_node):

* 0 (:data:`EXIT_OK`): stopped by Ctrl-C (SIGINT), SIGTERM or a ROS shutdown;
* 1 (:data:`EXIT_FAILED`): the node failed while running (a traceback on stderr, or a
  fatal log line when a node's worker failed: :meth:`GnssCamNode.fail`), also when the
  failure shut the context down as a stop does;
* 2 (:data:`EXIT_PARAMETER`): a parameter refused at start-up (wrong type, out of range,
  refused by the node's checks), or ROS arguments that cannot be used (a ``--params-file``
  that does not exist or does not parse), one line on stderr naming it;
* 3 (:data:`EXIT_INPUT`): an input file named by a parameter cannot be used
  (camera_node ``database_path`` missing or not a map database), one line on stderr.
"""
from __future__ import annotations

import math
import threading
import time
from collections import deque
from contextlib import contextmanager
from typing import Callable

import numpy as np
import rclpy
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
from rclpy.event_handler import SubscriptionEventCallbacks, qos_policy_name_from_kind
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message

from std_srvs.srv import Trigger

from msg_adapters import (NEW_BASE, OK, WARN, MessageError, StampGate, make_diagnostic_array,
                          make_status)
from msg_adapters.message_classes import message_class
from msg_adapters.wire import (BEST_EFFORT, DIAGNOSTICS, RELIABLE, TOPICS, TRANSIENT_LOCAL,
                               Topic)

from ..core.parameters import ParameterSpec
from .parameters import BIG, EVERY_NODE, Groups


EXIT_OK, EXIT_FAILED, EXIT_PARAMETER, EXIT_INPUT = 0, 1, 2, 3


class StartupError(Exception):
    """A node cannot start with its configuration; :func:`run_node` prints the message on
    one line and exits with :attr:`exit_code`."""

    exit_code = EXIT_FAILED


class ParameterError(StartupError, ValueError):
    """A parameter value refused at start-up (type, range or the node's own checks)."""

    exit_code = EXIT_PARAMETER


class InputFileError(StartupError):
    """A file named by a parameter cannot be used (missing, unreadable, wrong content)."""

    exit_code = EXIT_INPUT


def _coerced(param: Parameter, expected: int) -> Parameter:
    """An INTEGER value given for a DOUBLE parameter as that DOUBLE (``-p x:=16`` and
    ``x: 16`` in YAML mean 16.0); anything else unchanged."""
    if (param.type_ == Parameter.Type.INTEGER
            and expected == Parameter.Type.DOUBLE.value):
        return Parameter(param.name, Parameter.Type.DOUBLE, float(param.value))
    return param


_RELIABILITY = {RELIABLE: ReliabilityPolicy.RELIABLE,
                BEST_EFFORT: ReliabilityPolicy.BEST_EFFORT}


def topic_qos(topic: Topic, depth: int | None = None,
              reliability: str | None = None) -> QoSProfile:
    """The QoS of a registry topic (``msg_adapters.wire.TOPICS``): its reliability,
    durability and ``KEEP_LAST`` depth, the last two overridable (a node parameter).

    Sensor inputs are best effort (a late sample is worth less than the next one),
    node-to-node streams and outputs reliable, once-only outputs (``map/origin``)
    transient local, so that a subscriber that comes later still receives the last one.
    """
    return QoSProfile(history=HistoryPolicy.KEEP_LAST,
                      depth=int(topic.depth if depth is None else depth),
                      reliability=_RELIABILITY[reliability or topic.reliability],
                      durability=(DurabilityPolicy.TRANSIENT_LOCAL
                                  if topic.durability == TRANSIENT_LOCAL
                                  else DurabilityPolicy.VOLATILE))


#: Topics every node has (not links of the gnsscam_ros graph).
_INFRASTRUCTURE_TOPICS = frozenset({DIAGNOSTICS, 'rosout', 'parameter_events',
                                    '/rosout', '/parameter_events'})


class NodeStats:
    """Counters and processing times of one node (thread-safe).

    ``counters`` holds ``received_<topic>``, ``published_<topic>``, ``dropped`` and the
    like; ``rejected`` holds ``{reason: count}`` of input messages refused.
    """

    def __init__(self, window: int = 500):
        self._lock = threading.Lock()
        self.counters: dict[str, int] = {}
        self.rejected: dict[str, int] = {}
        self._times_s: deque = deque(maxlen=window)

    def count(self, key: str, n: int = 1) -> None:
        with self._lock:
            self.counters[key] = self.counters.get(key, 0) + n

    def reject(self, reason: str, n: int = 1) -> None:
        with self._lock:
            self.rejected[reason] = self.rejected.get(reason, 0) + n

    @property
    def rejected_total(self) -> int:
        with self._lock:
            return sum(self.rejected.values())

    def get(self, key: str) -> int:
        with self._lock:
            return self.counters.get(key, 0)

    @contextmanager
    def timed(self):
        """Record the wall time of the enclosed processing."""
        start = time.perf_counter()
        try:
            yield
        finally:
            with self._lock:
                self._times_s.append(time.perf_counter() - start)

    def add_time(self, seconds: float) -> None:
        with self._lock:
            self._times_s.append(seconds)

    def values(self) -> dict:
        """Counters, rejections (``rejected_<reason>``) and processing-time statistics."""
        with self._lock:
            out: dict = dict(sorted(self.counters.items()))
            out['rejected_total'] = sum(self.rejected.values())
            out.update({f'rejected_{k}': v for k, v in sorted(self.rejected.items())})
            times = np.array(self._times_s) * 1e3
        out['processing_count'] = int(times.size)
        out['processing_mean_ms'] = float(times.mean()) if times.size else math.nan
        out['processing_p50_ms'] = float(np.median(times)) if times.size else math.nan
        out['processing_max_ms'] = float(times.max()) if times.size else math.nan
        return out


class SequenceGaps:
    """Messages of a topic lost before its callback, from the gaps in the publishers'
    sequence numbers (``publication_sequence_number`` of the message info).

    Fast DDS raises no ``message_lost`` event when a KEEP_LAST subscription queue
    overwrites a message that the executor did not take in time (checked with rclpy
    Jazzy), nor for samples a KEEP_LAST writer replaced before delivering them; both show
    as a gap in the writer's sequence numbers. The message info does not name the
    publisher, so each message is attributed to the tracked stream whose newest number is
    the closest below its own; a number below all of them starts a new stream (another
    publisher, or one restarted). With one publisher per topic, as in the gnsscam_ros
    graph, the count is exact; with several whose numbers interleave closely it is an
    estimate. Messages published before the subscription matched are not counted.

    Args:
        streams: Publishers tracked at once (the least recently seen is forgotten).
    """

    def __init__(self, streams: int = 8):
        self._newest: list[int] = []         # per stream, most recently seen last
        self._streams = int(streams)
        #: The last message observed began a stream beside others already tracked (a
        #: publisher new to the topic, or one restarted).
        self.new_stream = False

    def observe(self, sequence_number) -> int:
        """Messages lost just before this one (0 when unknown)."""
        self.new_stream = False
        if not sequence_number or sequence_number < 0:
            return 0                     # not reported by this middleware
        seq = int(sequence_number)
        below = [i for i, newest in enumerate(self._newest) if newest < seq]
        if not below:
            self.new_stream = bool(self._newest)
            self._newest.append(seq)
            del self._newest[:-self._streams]
            return 0
        i = max(below, key=self._newest.__getitem__)
        gap = seq - self._newest.pop(i) - 1
        self._newest.append(seq)
        return gap


class InputTopic:
    """One subscribed input topic of a node: decoding, limits before decoding, losses,
    middleware events and the stamp gate, counted in the node's stats.

    The subscription takes the serialised message (``raw``) and decodes it here: rclpy
    drops a message that fails to deserialise before any callback (only rcutils noise on
    stderr), so decoding here is the one way to count it (``rejected_undecodable``); and
    the sizes in the header fields of images and clouds are checked before the arrays are
    copied out of the buffer (``check_raw``).

    Counters (``NodeStats``): ``received_<name>`` every message; ``lost_<topic>``
    messages lost before the callback (:class:`SequenceGaps`: queue overwrites,
    transport); ``qos_message_lost_<topic>`` what the middleware reports as lost (the
    ``message_lost`` event; may overlap ``lost_<topic>``); ``qos_incompatible_<topic>``
    and ``type_incompatible_<topic>``: publishers that cannot be matched;
    ``time_base_changed``: new time bases adopted by the stamp gate. Rejections by reason.
    """

    def __init__(self, node: 'GnssCamNode', msg_type, topic: str, callback: Callable,
                 qos: QoSProfile, received: str, check_raw: Callable | None = None):
        self.node = node
        self.msg_type = msg_type
        self.topic = topic
        self.callback = callback
        self.received = received
        self.check_raw = check_raw
        self.gate = StampGate(what=topic)
        self.gaps = SequenceGaps()
        stats = node.stats
        events = SubscriptionEventCallbacks(
            message_lost=lambda e: stats.count(f'qos_message_lost_{topic}',
                                               int(e.total_count_change)),
            incompatible_qos=self._incompatible_qos,
            incompatible_type=self._incompatible_type)
        self.subscription = node.create_subscription(msg_type, topic, self.on_raw, qos,
                                                     event_callbacks=events, raw=True)

    def on_raw(self, raw: bytes, info) -> None:
        """Count, check the sizes, decode, and hand the message to the node."""
        stats = self.node.stats
        stats.count(self.received)
        lost = self.gaps.observe(info.get('publication_sequence_number')
                                 if isinstance(info, dict) else None)
        if lost > 0:
            stats.count(f'lost_{self.topic}', lost)
        try:
            if self.check_raw is not None:
                self.check_raw(raw, self.topic)
        except MessageError as err:
            self.node.warn_rejected(self.topic, err.reason, str(err))
            return
        try:
            msg = deserialize_message(raw, self.msg_type)
        except Exception as err:    # noqa: BLE001 - rclpy raises RMWError and others
            self.node.warn_rejected(self.topic, 'undecodable',
                                    f'{len(raw)} bytes: {type(err).__name__}: {err}')
            return
        self.callback(msg)

    def _incompatible_qos(self, event) -> None:
        self.node.stats.count(f'qos_incompatible_{self.topic}')
        self.node.get_logger().warning(
            f'{self.topic}: a publisher offers an incompatible QoS (policy '
            f'{qos_policy_name_from_kind(event.last_policy_kind)}); its messages never arrive',
            throttle_duration_sec=5.0)

    def _incompatible_type(self, event) -> None:
        self.node.stats.count(f'type_incompatible_{self.topic}')
        self.node.get_logger().warning(
            f'{self.topic}: a publisher of another message type; its messages never arrive',
            throttle_duration_sec=5.0)


class GnssCamNode(Node):
    """Base of the gnsscam_ros nodes.

    Declares ``diagnostics_period_s``, publishes ``diagnostics`` periodically with the
    node's counters and ``newest_input_stamp_ns`` (the newest stamp its inputs accepted;
    subclasses add their own state through :meth:`diagnostic_summary`), offers ``~/reset``
    (``std_srvs/Trigger``: forget the inputs' time base and the state built on it,
    :meth:`reset_time_base_now`),
    and validates parameter updates: each declared parameter may carry a validator and a
    read-only flag; :meth:`validate_parameters` sees the whole update and may refuse it with
    a reason (the old values stay); :meth:`apply_parameters` applies accepted ones.

    Args:
        node_name: Node name.
        **kwargs: Forwarded to ``rclpy.node.Node`` (``context``, ``parameter_overrides``,
            ``namespace``, ...).
    """

    def __init__(self, node_name: str, **kwargs):
        super().__init__(node_name, **kwargs)
        self.stats = NodeStats()
        self.inputs: dict[str, InputTopic] = {}
        #: Why the node failed while running (None: it did not); see :meth:`fail`.
        self.fatal_error: str | None = None
        self._validators: dict[str, Callable] = {}
        self._all_declared = False
        self._diag_pub = self.publisher(DIAGNOSTICS)
        # Run-time updates (`ros2 param set n x 16`): an integer for a float parameter is
        # that float. Start-up overrides are coerced in declare().
        self.add_pre_set_parameters_callback(self._coerce_types)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._post_set_parameters)
        for spec in EVERY_NODE:
            self.declare_spec(spec, 'every node')
        self._diag_timer = self.create_timer(self.param('diagnostics_period_s'),
                                             self.publish_diagnostics)
        self._reset_service = self.create_service(Trigger, '~/reset', self._on_reset)

    # ------------------------------------------------------------------ parameters
    def declare(self, name: str, default, description: str, value_range=None,
                read_only: bool = False, validator: Callable | None = None):
        """Declare a parameter with a descriptor (description, range, read-only).

        Args:
            name: Parameter name.
            default: Default value (its type is the parameter's type).
            description: Meaning and unit.
            value_range: ``(low, high)`` inclusive, for int and float parameters.
            read_only: Refuse changes after start-up.
            validator: ``f(value) -> str | None``; a string refuses the value with that
                reason (checked at start-up too).

        An integer override of a float parameter (``-p alert_limit_m:=16``, ``16`` in a
        params file) is taken as that float.

        Returns:
            The value in force (default or override).

        Raises:
            ParameterError: The start-up value has the wrong type, is out of range or is
                refused by ``validator`` (the message names the parameter).
        """
        desc = ParameterDescriptor(name=name, description=description, read_only=read_only)
        if value_range is not None:
            low, high = value_range
            if isinstance(default, bool):
                pass
            elif isinstance(default, int):
                desc.integer_range = [IntegerRange(from_value=int(low), to_value=int(high),
                                                   step=0)]
            elif isinstance(default, float):
                desc.floating_point_range = [FloatingPointRange(
                    from_value=float(low), to_value=float(high), step=0.0)]
        # rclpy keeps the command-line, params-file and constructor overrides here and
        # offers no hook before it checks their type on declaration.
        overrides = self._parameter_overrides
        if name in overrides and isinstance(default, float):
            overrides[name] = _coerced(overrides[name], Parameter.Type.DOUBLE.value)
        try:
            self.declare_parameter(name, default, desc)
        except InvalidParameterTypeException as err:
            given = overrides[name].value if name in overrides else None
            raise ParameterError(f'{self.get_name()}: parameter {name}: expected '
                                 f'{_type_name(default)}, got {given!r}') from err
        except InvalidParameterValueException as err:
            given = overrides[name].value if name in overrides else None
            reason = str(err).split('Reason: ', 1)[-1].rsplit(f': {name}', 1)[0]
            if value_range is not None and 'out of range' in reason:
                reason = f'out of range [{value_range[0]}, {value_range[1]}]'
            raise ParameterError(f'{self.get_name()}: parameter {name} = {given!r} refused: '
                                 f'{reason}') from err
        if validator is not None:
            self._validators[name] = validator
            reason = validator(self.param(name))
            if reason:
                raise ParameterError(f'{self.get_name()}: parameter {name} = '
                                     f'{self.param(name)!r} refused: {reason}')
        return self.param(name)

    def declare_spec(self, spec: ParameterSpec, where: str,
                     validator: Callable | None = None):
        """Declare the parameter of ``spec`` (``core.parameters``): its default, its
        description (meaning, unit, admissible values, ``where`` it is declared), its range
        (open bounds are checked by the configuration it belongs to) and read-only flag.

        Returns:
            The value in force (:meth:`declare`).
        """
        about = f' Admissible: {spec.constraint}.' if spec.constraint else ''
        default = list(spec.default) if isinstance(spec.default, tuple) else spec.default
        return self.declare(spec.name, default, f'{spec.description}{about} ({where})',
                            None if spec.range is None else spec.range.closed(BIG),
                            read_only=spec.read_only, validator=validator)

    def declare_node_parameters(self, groups: Groups, validators: dict | None = None) -> None:
        """Declare every parameter of a node's ``groups`` (``nodes.parameters``) but the
        ones every node has (declared by this base); ``validators`` maps names to further
        checks (``f(value) -> reason or None``)."""
        validators = validators or {}
        for where, specs in groups:
            for spec in specs:
                if spec not in EVERY_NODE:
                    self.declare_spec(spec, where, validators.get(spec.name))

    def _coerce_types(self, params: list) -> list:
        out = []
        for p in params:
            expected = (self.describe_parameter(p.name).type
                        if self.has_parameter(p.name) else None)
            out.append(_coerced(p, expected))
        return out

    def param(self, name: str):
        """Current value of a declared parameter."""
        return self.get_parameter(name).value

    def validate_parameters(self, changes: dict) -> str | None:
        """Whole-update check (override); return a reason to refuse."""
        return None

    def apply_parameters(self, changes: dict) -> None:
        """Apply an accepted update (override)."""

    def _on_set_parameters(self, params) -> SetParametersResult:
        changes = {p.name: p.value for p in params}
        for name, value in changes.items():
            check = self._validators.get(name)
            reason = check(value) if check is not None else None
            if reason:
                return SetParametersResult(successful=False, reason=f'{name}: {reason}')
        # declare_parameter() runs these callbacks too; whole-update checks wait until
        # every parameter is declared (the constructor then validates the whole set).
        reason = self.validate_parameters(changes) if self._all_declared else None
        if reason:
            return SetParametersResult(successful=False, reason=reason)
        return SetParametersResult(successful=True)

    def _post_set_parameters(self, params) -> None:
        if self._all_declared:
            self.apply_parameters({p.name: p.value for p in params})

    def parameters_declared(self) -> None:
        """Subclasses call this at the end of their constructor: from then on updates
        are checked and applied as a whole."""
        self._all_declared = True

    # ------------------------------------------------------------------- ready line
    def ready_settings(self) -> dict:
        """The key settings for the ready line (override)."""
        return {}

    def ready_line(self) -> str:
        """One line: what the node subscribes and publishes, and its key settings (logged by
        :func:`start_nodes` once every node of the process is constructed)."""
        prefix = self.get_namespace().rstrip('/') + '/'

        def names(endpoints):
            rel = {e.topic_name[len(prefix):] if e.topic_name.startswith(prefix)
                   else e.topic_name for e in endpoints}
            return ', '.join(sorted(rel - _INFRASTRUCTURE_TOPICS)) or 'nothing'
        settings = ', '.join(f'{k}={v}' for k, v in self.ready_settings().items())
        return (f'ready: subscribes {names(self.subscriptions)}; publishes '
                f'{names(self.publishers)} (+ diagnostics)'
                + (f'; {settings}' if settings else ''))

    # ----------------------------------------------------------------- diagnostics
    def diagnostic_summary(self) -> tuple[int, str, dict]:
        """``(level, message, extra values)`` of the node's own state (override)."""
        return OK, 'running', {}

    def link_counts(self) -> dict[str, int]:
        """Matched endpoints of the node's topics, relative to its namespace:
        ``publishers_<input>`` (publishers a subscription is connected to) and
        ``subscribers_<output>`` (subscribers a publisher reaches).

        Graph discovery (a node sees another's endpoint) comes before matching (the two
        endpoints connected); only matching means a message gets through. Another process
        cannot observe it, so the nodes report it: a bag replay starts once every link of
        the graph is matched instead of guessing a delay.
        """
        prefix = self.get_namespace().rstrip('/') + '/'
        out = {}
        for kind, endpoints, count in (
                ('publishers', self.subscriptions, lambda e: e.get_publisher_count()),
                ('subscribers', self.publishers, lambda e: e.get_subscription_count())):
            for endpoint in endpoints:
                name = endpoint.topic_name
                rel = name[len(prefix):] if name.startswith(prefix) else name
                if rel not in _INFRASTRUCTURE_TOPICS:
                    out[f'{kind}_{rel}'] = int(count(endpoint))
        return out

    def extra_statuses(self) -> list:
        """Further DiagnosticStatus entries of the ``diagnostics`` report (override)."""
        return []

    def publish_diagnostics(self) -> None:
        if not self.context.ok():
            return          # shutting down: a timer that fires now has nowhere to publish
        level, message, extra = self.diagnostic_summary()
        values = {**self.stats.values(), **self.link_counts(), **extra}
        newest = [h.gate.newest_ns for h in self.inputs.values() if h.gate.newest_ns is not None]
        if newest:
            # A replay compares its bag's start with it: a bag that does not continue
            # the nodes' time base resets them first (live.player).
            values['newest_input_stamp_ns'] = max(newest)
        status = make_status(f'{self.get_name()}: status', level, message, values,
                             hardware_id='gnsscam_ros')
        self._diag_pub.publish(make_diagnostic_array(self.now_ns(),
                                                     [status, *self.extra_statuses()]))

    def now_ns(self) -> int:
        """Node clock time [ns] (ROS time; simulated time when ``use_sim_time``)."""
        return int(self.get_clock().now().nanoseconds)

    def warn_rejected(self, topic: str, reason: str, detail: str) -> None:
        """Count a refused input message and log it (throttled)."""
        self.stats.reject(reason)
        self.get_logger().warning(f'{topic}: rejected ({reason}): {detail}',
                                  throttle_duration_sec=5.0)

    # ------------------------------------------------------------ inputs, outputs
    def publisher(self, topic: str, depth: int | None = None):
        """A publisher of the registry topic ``topic`` (``msg_adapters.wire.TOPICS``):
        its message type and QoS from there, ``depth`` overriding the registry's."""
        spec = TOPICS[topic]
        return self.create_publisher(message_class(spec.msgtype), topic,
                                     topic_qos(spec, depth))

    def subscribe_input(self, topic: str, callback: Callable, received: str,
                        check_raw: Callable | None = None, depth: int | None = None,
                        reliability: str | None = None) -> InputTopic:
        """Subscribe the registry topic ``topic`` through :class:`InputTopic` (decoded
        and counted here; ``callback`` gets the message), with its message type and QoS
        from ``msg_adapters.wire.TOPICS`` (``depth`` and ``reliability`` override them).
        ``check_raw(raw, topic)`` may refuse the serialised message before it is decoded
        (``MessageError``)."""
        spec = TOPICS[topic]
        handler = InputTopic(self, message_class(spec.msgtype), topic, callback,
                             topic_qos(spec, depth, reliability), received, check_raw)
        self.inputs[topic] = handler
        return handler

    def admit_stamp(self, topic: str, stamp_ns: int) -> str | None:
        """Pass a stamp through the topic's :class:`StampGate`.

        Returns:
            The gate's verdict (``ADVANCE``, ``BEHIND``, ``NEW_BASE``), or None when the
            message is refused (counted as ``stamp_jump``). On ``NEW_BASE`` the other
            inputs' gates forget their streams (a replay rewinds every topic together;
            each would otherwise reset the node once more) and :meth:`on_time_base_changed`
            resets what the node keeps of the old time base.
        """
        handler = self.inputs[topic]
        gate = handler.gate
        refused = None
        try:
            # A publisher new to the topic whose stamps go back: a bag played again.
            verdict = gate.admit(stamp_ns, time.monotonic(),
                                 new_publisher=handler.gaps.new_stream)
        except MessageError as err:
            verdict, refused = None, err
        if verdict != NEW_BASE and self._rewound_together(gate, stamp_ns):
            verdict, refused = gate.adopt(stamp_ns), None
        if refused is not None:
            self.warn_rejected(topic, refused.reason, str(refused))
            return None
        if verdict == NEW_BASE:
            for other in self.inputs.values():
                if other.gate is not gate:
                    other.gate.reset()
            self.stats.count('time_base_changed')
            how = ('a new publisher going back in time' if handler.gaps.new_stream else
                   f'{gate.confirm} consistent messages over {gate.span_s:g} s away from the '
                   'stream before')
            self.get_logger().warning(
                f'{topic}: new time base adopted at {stamp_ns} ns ({how}): state of the old '
                'one reset')
            self.on_time_base_changed(topic, stamp_ns)
        return verdict

    #: The inputs come from nodes that publish in stamp order (fusion_node's come from
    #: gnss_node, imu_node and camera_node): two of them going back in time together can
    #: only be a new time base upstream, taken at once (see :meth:`_rewound_together`).
    ordered_inputs = False

    def _rewound_together(self, gate: StampGate, stamp_ns: int) -> bool:
        """With :attr:`ordered_inputs`: ``stamp_ns`` goes back on its input while another
        input's recent messages went back to the same time (within the stamp window).

        A bag played again reaches such a node through nodes that took it as a new time
        base at once (its stream comes from a new publisher); their outputs go back from
        the same publishers, so without this the node would wait for
        ``NEW_TIME_BASE_MESSAGES`` of one input over ``NEW_TIME_BASE_SPAN_S``.
        """
        if not self.ordered_inputs or gate.rewinding_ns != stamp_ns:
            return False
        return any(other.gate is not gate and other.gate.rewinding_ns is not None
                   and abs(other.gate.rewinding_ns - stamp_ns) <= gate.window_ns
                   for other in self.inputs.values())

    def on_time_base_changed(self, topic: str, stamp_ns: int) -> None:
        """Forget what the node keeps of the old time base (override)."""

    def reset_time_base_now(self, reason: str) -> None:
        """Start afresh on request: every input forgets its stream (the next stamp of each
        is taken as its start) and :meth:`on_reset` drops the state built on the old time
        base. Counted ``resets``."""
        for handler in self.inputs.values():
            handler.gate.reset()
        self.stats.count('resets')
        self.get_logger().warning(f'reset ({reason}): inputs take their next stamps as a new '
                                  'time base')
        self.on_reset(reason)

    def on_reset(self, reason: str) -> None:
        """Drop the state of the old time base after a reset (override; default: as for a
        new time base an input adopted)."""
        self.on_time_base_changed('~/reset', 0)

    def _on_reset(self, request, response):
        # Served by the node's executor, between its input callbacks: no input is halfway.
        self.reset_time_base_now('requested on ~/reset')
        response.success = True
        response.message = f'{self.get_name()}: time base and state reset'
        return response

    # ---------------------------------------------------------------------- failure
    def fail(self, what: str) -> None:
        """The node cannot go on (a worker thread died, ...): log it, remember it for the
        exit code (:data:`EXIT_FAILED`) and shut the context down, as an exception in a
        callback would."""
        if self.fatal_error is None:
            self.fatal_error = what
        self.get_logger().fatal(f'{what}; shutting down')
        rclpy.try_shutdown(context=self.context)


def _type_name(default) -> str:
    if isinstance(default, bool):
        return 'a boolean (true/false)'
    if isinstance(default, int):
        return 'an integer'
    if isinstance(default, float):
        return 'a number'
    if isinstance(default, str):
        return 'a string'
    if isinstance(default, (list, tuple)) and default and isinstance(default[0], float):
        return 'a list of numbers, e.g. [1.0, 2.0, 3.0]'
    return f'a value of type {type(default).__name__}'


__all__ = ['BIG', 'EXIT_FAILED', 'EXIT_INPUT', 'EXIT_OK', 'EXIT_PARAMETER', 'GnssCamNode',
           'InputFileError', 'InputTopic', 'NodeStats', 'OK', 'ParameterError',
           'SequenceGaps', 'StartupError', 'WARN', 'topic_qos']
