"""``gnsscam_replay``: play a rosbag2 bag into the nodes, lossless at any speed.

Usage::

    gnsscam_replay BAG [--rate R] [--start S] [--topics T [T ...]]

Messages are published in bag order with their original timing scaled by ``R``: the
message stamped ``t`` goes out at ``(t - t_first) / R`` after the first one. The time of a
message is its header stamp (the converter writes bag time = header stamp; for bags
recorded live the header stamp is the time of validity, which is what the filter uses);
messages without a header (``dataset/info``) use the bag time. ``R = 0`` (or any R faster
than the nodes) plays as fast as the nodes keep up. ``--start S`` skips the first ``S``
seconds (bag time), except the once-only (``transient_local``) topics ``dataset/info`` and
``map/origin``, which are always published first. ``--topics`` plays only the named topics
(relative ``imu/data`` or qualified ``/imu/data``). The serialised CDR of the bag is
published as it is (``Publisher.publish(bytes)``): nothing is decoded, converted or
re-encoded on the way, so the nodes see the bytes the converter wrote.

On a ROS 2 machine ``ros2 bag play BAG`` replays the same bag in real time; it knows
nothing of the nodes' queues, so at high rates it may lose input (see below).

**No loss at any rate (flow control).** The nodes take their sensor inputs best effort
with bounded queues (design.md §3) and drop the oldest message when a queue overflows. The
replay therefore never lets more messages be in flight than the consumer can hold; a
message is *in flight* from its publication until the node graph acknowledges it on an
output topic that it already publishes (no extra protocol):

=====================  ================================  ====================================
input                  acknowledged by                   window (messages in flight)
=====================  ================================  ====================================
``imu/data``,          ``odometry/dead_reckoning`` with  50 per topic (imu_node queues 100)
``odom/twist``         a stamp >= the input's
``camera/image_raw``   ``camera/matches`` with a stamp   2 (camera_node's matcher queue)
                       >= the image's
``gnss/pseudoranges``  ``integrity_risk`` whose          1: an epoch is published once the
                       ``epoch_stamp`` >= the epoch's    filter finished the previous one
=====================  ================================  ====================================

Acknowledgements are monotone in stamp: a later acknowledgement covers every earlier
message. camera_node answers every frame it takes, an unmatched or unmatchable one (no map
database, a refused image) with an empty ``camera/matches`` of the frame's stamp, so a
default camera_node without a database acknowledges images as fast as they come; a frame
lost on the way or dropped from camera_node's queue is covered by the next answer.

With the GNSS window of one epoch, fusion_node's GNSS queue never holds more than one
epoch: **no epoch can be dropped**, and the replay reports per epoch whether its
``integrity_risk`` came back (``gnss_epochs_processed``). The filter runs epoch k while the
replay already feeds the IMU of the next interval, so the replay goes as fast as the
slowest node.

**Same input, same order as an offline run.** So that the nodes compute exactly what an
offline run of the same data computes (``evaluation.demo.offline_run``; the tests check it
to 1e-6 m):

* messages with equal stamps go out in :data:`TIE_ORDER` (odometry before IMU, the dead
  reckoning's own rule; GNSS last, after the motion of its instant);
* the first message of each acknowledged stream goes alone and is acknowledged before the
  next (the dead reckoning starts from whichever source arrives first);
* before a GNSS epoch, every camera image stamped up to it must be acknowledged, then
  :data:`GNSS_GRACE_S` passes (fusion_node serves ``gnss/measurements`` before
  ``camera/matches`` when both are ready, which would run the epoch without the last
  match);
* before the first message the replay waits for the graph's internal connections
  (``FlowRule.via``) and then until the nodes' diagnostics report every link *matched*
  at both ends (``GnssCamNode.link_counts``: discovery is not matching, and a message
  sent before the match is lost). With a fixed 3.5 s delay instead, one of three demo
  runs here lost fusion_node's first dead-reckoning states and differed from the offline
  run by metres. Nodes that report no links get ``settle_s`` instead.

A stream whose consumer is absent (no subscriber on the input, or no publisher of its
acknowledging topic after ``--wait``) is played without flow control. An acknowledgement
that does not come within ``--ack-timeout`` seconds is counted as unacknowledged; after
three in a row on one stream its flow control is switched off with a warning (e.g. a
camera node that never answers).

**Node parameters for replay.** Some node timeouts are in wall time, which a replay at
``R != 1`` does not follow, and fusion_node's ``camera/matches`` queue (10) is shorter than
the matches that arrive while it runs a slow epoch. :data:`REPLAY_NODE_PARAMETERS` lifts
them (imu_node's ``source_timeout_s``: otherwise a pause of the odometry stream longer than
0.5 s while the filter runs a slow epoch would switch the dead reckoning to the IMU-only
source for a moment; fusion_node's ``odometry_wait_s``, ``odometry_timeout_s``,
``gnss_timeout_s`` and ``input_queue_depth``). With them, a replay at ``R = 0`` gives the
nodes the same input in the same order whatever the speed. :func:`write_params_file`
writes them as a ``--params-file``.

:func:`replay_through_nodes` runs the whole chain (nodes as processes or threads, replay,
recorder) under a private namespace, so that concurrent runs on one machine never mix.

**Large messages.** With Fast DDS's default transports a camera image (0.9 MB) does not fit
the shared-memory segment and travels as UDP fragments, and a best-effort subscriber
(camera_node) loses most images sent from another process. The CLI therefore starts with
:data:`DDS_PROFILE` (a 32 MB shared-memory segment; only the publishing process needs it)
unless ``FASTRTPS_DEFAULT_PROFILES_FILE`` is set or ``--no-dds-profile`` is given.

Exit codes of the CLI: 0 done (also on Ctrl-C: the replay stops after the current
message), 2 bad usage, 3 the bag is missing, unreadable or has an unknown message type.

``python -m gnsscam_ros.bench.replay`` measures replay through the nodes at 10,000
particles (speed as a multiple of real time, dropped GNSS epochs).
"""
from __future__ import annotations

import argparse
import importlib
import itertools
import math
import os
import sys
import threading
import time
import traceback
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.context import Context
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from msg_adapters import MessageError, parse_integrity_risk, status_values
from msg_adapters.wire import header_stamp_ns

from ..nodes.common import NodeSpinner, stop_process
from ..bags import schema
from ..bags.errors import BagError, BagReadError, BagTypeError
from ..bags.read import open_bag

EXIT_OK, EXIT_USAGE, EXIT_INPUT = 0, 2, 3
_NO_PUB_EVENTS = PublisherEventCallbacks(use_default_callbacks=False)
_NO_SUB_EVENTS = SubscriptionEventCallbacks(use_default_callbacks=False)

DEAD_RECKONING = 'odometry/dead_reckoning'
MATCHES = 'camera/matches'


@dataclass(frozen=True)
class FlowRule:
    """Flow control of one input topic.

    Attributes:
        ack_topic: Relative output topic whose stamps acknowledge the input.
        ack_type: Its message type (``pkg/msg/Type``).
        window: Messages of the input allowed in flight (published, not acknowledged).
        via: ``(topic, subscribers)`` inside the graph that must be connected before
            playing: a publisher and at least that many subscribers (the replay counts
            itself where it listens), so that nothing is lost between two nodes that
            have not discovered each other yet.
    """

    ack_topic: str
    ack_type: str
    window: int
    via: tuple = ()


#: Flow control per relative input topic (the gnsscam_ros node graph; see module doc).
FLOW_RULES: dict[str, FlowRule] = {
    schema.IMU: FlowRule(DEAD_RECKONING, 'nav_msgs/msg/Odometry', 50,
                         ((DEAD_RECKONING, 2),)),
    schema.TWIST: FlowRule(DEAD_RECKONING, 'nav_msgs/msg/Odometry', 50,
                           ((DEAD_RECKONING, 2),)),
    schema.IMAGE: FlowRule(MATCHES, schema.POINTCLOUD2, 2, ((MATCHES, 2),)),
    schema.GNSS: FlowRule(schema.INTEGRITY, schema.DIAGNOSTIC_ARRAY, 1,
                          (('gnss/measurements', 1),)),
}
#: Publication order of messages with equal stamps (others after, in bag order).
TIE_ORDER = (schema.TWIST, schema.IMU, schema.IMAGE, schema.GNSS)
#: Fallback when the nodes do not report their links (not gnsscam_ros nodes): wait this
#: long after the graph is connected, for the endpoints to match [s].
MATCH_SETTLE_S = 0.5
#: The same for node processes started together with the replay: two participants that
#: miss each other's first announcements meet at the next periodic one (Fast DDS: every
#: 3 s).
FRESH_PROCESSES_SETTLE_S = 3.5
#: Pause before a GNSS epoch whose interval had camera images [s] (see BagReplayer._flow).
GNSS_GRACE_S = 0.02
#: Streams that must be acknowledged up to a GNSS epoch's stamp before it is published.
GNSS_BARRIER = (schema.IMAGE,)
_MAX_TIMEOUTS = 3              # consecutive ack timeouts before a stream's control goes off
#: How long to wait for the nodes' first link report (diagnostics, once a second) before
#: falling back to a fixed settle time [s].
LINK_REPORT_WAIT_S = 3.0

#: Node parameters for a replay whose time is not wall time (see module doc). The waits stay
#: finite so that an epoch after the last odometry sample is still processed at the end.
REPLAY_NODE_PARAMETERS: dict[str, dict] = {
    'imu_node': {'source_timeout_s': 3600.0},
    'fusion_node': {'odometry_wait_s': 10.0, 'odometry_timeout_s': 10.0,
                    'gnss_timeout_s': 3600.0, 'input_queue_depth': 200},
}


def write_params_file(path: str | Path, parameters: dict[str, dict]) -> Path:
    """Write ``{node: {name: value}}`` as a ROS 2 ``--params-file`` (YAML).

    Args:
        path: File to write (replaced if present: it is a generated input, not a result).
        parameters: Parameters by node name.

    Returns:
        The path.
    """
    import yaml
    path = Path(path)
    data = {node: {'ros__parameters': dict(values)} for node, values in parameters.items()}
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding='utf-8')
    return path


def merge_parameters(*layers: dict[str, dict]) -> dict[str, dict]:
    """Merge ``{node: {name: value}}`` dictionaries, later layers winning per key."""
    out: dict[str, dict] = {}
    for layer in layers:
        for node, values in (layer or {}).items():
            out.setdefault(node, {}).update(values)
    return out


def message_class(msgtype: str):
    """The rclpy message class of ``pkg/msg/Type``.

    Raises:
        BagTypeError: The package or type is not installed.
    """
    try:
        pkg, kind, name = msgtype.split('/')
        return getattr(importlib.import_module(f'{pkg}.{kind}'), name)
    except (ValueError, ImportError, AttributeError) as err:
        raise BagTypeError(f'message type {msgtype} is not available to rclpy: {err}') from err


@dataclass
class ReplaySummary:
    """What a replay did.

    Attributes:
        bag: The bag played.
        rate: Rate factor (0 = as fast as the nodes keep up).
        published: Messages published per qualified topic.
        first_stamp_ns: Stamp of the first timed message published [ns].
        last_stamp_ns: Stamp of the last timed message published [ns].
        wall_s: Wall time from the first to the last message and the final
            acknowledgements [s].
        gnss_epochs: GNSS epochs published.
        gnss_epochs_processed: Of those, epochs whose ``integrity_risk`` came back
            (None: nobody publishes ``integrity_risk``).
        unacknowledged: Per relative topic, messages whose acknowledgement timed out.
        flow_control: Per relative topic, ``'on'``, ``'off: ...'`` with the reason.
        ack_wait_s: Per relative topic, wall time spent waiting for acknowledgements [s].
        interrupted: Stopped early (Ctrl-C or shutdown).
        cpu_s: CPU time [s] by process (``replay`` = this process during the replay, with
            any in-process nodes; child node processes by name, start-up included), when
            measured by :func:`replay_through_nodes`.
        node_diagnostics: The newest ``diagnostics`` values per status name seen during the
            replay (the nodes' counters: ``dropped_epochs``, ``dropped_frames``, ...).
        start: How the replay knew the graph was ready: ``'links matched'`` (the nodes
            reported every link), ``'links not matched'`` (they did not within ``wait``),
            ``'fixed settle'`` (no link reports) or ``''`` (no flow-controlled stream).
        start_wait_s: Wall time from the replay's start to its first message [s].
    """

    bag: Path
    rate: float
    published: dict[str, int] = field(default_factory=dict)
    first_stamp_ns: int | None = None
    last_stamp_ns: int | None = None
    wall_s: float = 0.0
    gnss_epochs: int = 0
    gnss_epochs_processed: int | None = None
    unacknowledged: dict[str, int] = field(default_factory=dict)
    flow_control: dict[str, str] = field(default_factory=dict)
    ack_wait_s: dict[str, float] = field(default_factory=dict)
    interrupted: bool = False
    cpu_s: dict[str, float] = field(default_factory=dict)
    node_diagnostics: dict[str, dict] = field(default_factory=dict)
    start: str = ''
    start_wait_s: float = 0.0

    @property
    def bag_span_s(self) -> float:
        """Bag time covered by the published messages [s]."""
        if self.first_stamp_ns is None or self.last_stamp_ns is None:
            return 0.0
        return (self.last_stamp_ns - self.first_stamp_ns) / 1e9

    @property
    def speed(self) -> float:
        """Replay speed as a multiple of real time (bag span / wall time)."""
        return self.bag_span_s / self.wall_s if self.wall_s > 0 else math.nan

    @property
    def dropped_gnss_epochs(self) -> int | None:
        """GNSS epochs published without an ``integrity_risk`` back (None: no filter)."""
        if self.gnss_epochs_processed is None:
            return None
        return self.gnss_epochs - self.gnss_epochs_processed

    def as_dict(self) -> dict:
        """JSON-able form."""
        return {'bag': str(self.bag), 'rate': self.rate, 'published': self.published,
                'messages': sum(self.published.values()), 'bag_span_s': self.bag_span_s,
                'wall_s': self.wall_s, 'speed_x_real_time': self.speed,
                'gnss_epochs': self.gnss_epochs,
                'gnss_epochs_processed': self.gnss_epochs_processed,
                'dropped_gnss_epochs': self.dropped_gnss_epochs,
                'unacknowledged': self.unacknowledged, 'flow_control': self.flow_control,
                'ack_wait_s': self.ack_wait_s, 'interrupted': self.interrupted,
                'cpu_s': self.cpu_s, 'node_diagnostics': self.node_diagnostics,
                'start': self.start, 'start_wait_s': self.start_wait_s}

    def text(self) -> str:
        """Readable one-paragraph summary."""
        lines = [f'replayed {sum(self.published.values())} messages, '
                 f'{self.bag_span_s:.1f} s of bag time in {self.wall_s:.1f} s '
                 f'({self.speed:.1f}x real time, rate {self.rate:g})']
        if self.gnss_epochs:
            processed = ('?' if self.gnss_epochs_processed is None
                         else self.gnss_epochs_processed)
            lines.append(f'GNSS epochs: {self.gnss_epochs} published, {processed} processed '
                         f'by the filter, dropped {self.dropped_gnss_epochs}')
        lost = {k: v for k, v in self.unacknowledged.items() if v}
        if lost:
            lines.append(f'unacknowledged: {lost}')
        off = {k: v for k, v in self.flow_control.items() if v != 'on'}
        if off:
            lines.append(f'flow control off: {off}')
        if self.start and self.start != 'links matched':
            lines.append(f'started on {self.start}')
        if self.interrupted:
            lines.append('interrupted')
        return '\n'.join(lines)


class _Stream:
    """Flow-control state of one input topic (guarded by the replayer's condition)."""

    def __init__(self, topic: str, rule: FlowRule):
        self.topic = topic
        self.rule = rule
        self.pending: deque = deque()      # stamps published, not yet acknowledged
        self.enabled = True
        self.reason = 'on'
        self.timeouts = 0
        self.consecutive_timeouts = 0
        self.wait_s = 0.0


class BagReplayer(Node):
    """Publishes a bag's messages (serialised CDR) with scaled timing and flow control.

    The replayer spins itself: :meth:`play` runs a private executor for this node on a
    background thread (do not add the node to another executor).

    Args:
        bag: rosbag2 bag folder (or a bare ``.mcap``/``.db3`` file).
        rate: Time scale R (2 = twice as fast as recorded); 0 = as fast as the nodes keep
            up.
        start_s: Skip this much bag time from the start [s].
        topics: Topics to play (relative or qualified names); None = all.
        flow_control: Apply the flow control of :data:`FLOW_RULES`.
        windows: Per relative topic, a window overriding :data:`FLOW_RULES`.
        ack_timeout_s: Longest wait for one acknowledgement [s].
        wait_s: Longest wait for the consumers (subscribers and acknowledging publishers)
            to appear before playing [s].
        require_subscribers: Relative topics that must have a subscriber before playing
            (e.g. the ones a recorder records), within ``wait_s``.
        settle_s: Wait after the graph is connected, before the first message [s].
        gnss_grace_s: Pause before a GNSS epoch that follows camera images, once their
            matches are acknowledged (see :meth:`_flow`) [s].
        bag_namespace: Namespace the bag's topics were written under (to recognise them);
            they are published relative to the node's own namespace (``namespace=``).
        node_name: Node name.
        **kwargs: Forwarded to ``rclpy.node.Node`` (``context=``, ...).

    Raises:
        BagReadError: The bag is missing or unreadable.
        BagTypeError: A selected topic has a message type rclpy does not know.
        ValueError: Negative rate or start, or a named topic that the bag does not hold.
    """

    def __init__(self, bag: str | Path, rate: float = 1.0, start_s: float = 0.0,
                 topics: list[str] | None = None, flow_control: bool = True,
                 windows: dict[str, int] | None = None, ack_timeout_s: float = 30.0,
                 wait_s: float = 10.0, require_subscribers: tuple[str, ...] = (),
                 settle_s: float = MATCH_SETTLE_S, gnss_grace_s: float = GNSS_GRACE_S,
                 bag_namespace: str = '/', node_name: str = 'gnsscam_replay', **kwargs):
        if not (rate >= 0.0 and math.isfinite(rate)):
            raise ValueError(f'rate must be finite and >= 0, got {rate}')
        if not (start_s >= 0.0 and math.isfinite(start_s)):
            raise ValueError(f'start must be finite and >= 0 s, got {start_s}')
        self.bag = Path(bag)
        self.rate = float(rate)
        self.start_s = float(start_s)
        self.bag_namespace = bag_namespace
        self.ack_timeout_s = float(ack_timeout_s)
        self.wait_s = float(wait_s)
        self.settle_s = float(settle_s)
        self.gnss_grace_s = float(gnss_grace_s)
        self._matched_since_gnss = False
        self.require_subscribers = tuple(require_subscribers)
        # Read the bag's table of contents before creating the node, so that a bad bag
        # fails fast without touching the ROS graph.
        with open_bag(self.bag) as reader:
            self._connections = list(reader.connections)
            self._bag_start_ns = int(reader.start_time)
        self._select(topics)
        # The executor of this node wakes for every acknowledgement (100 per second of an
        # IMU stream) and rclpy rebuilds its wait set at each wake, at a cost that grows
        # with every service and event handler: the replay has no ROS parameters, so no
        # parameter services, and no QoS event handlers (all its endpoints are reliable,
        # compatible with any subscriber).
        kwargs.setdefault('start_parameter_services', False)
        super().__init__(node_name, **kwargs)
        self._cond = threading.Condition()
        self._ack_newest: dict[str, int] = {}
        self._epochs_seen: set[int] = set()
        self._diagnostics: dict[str, dict] = {}
        self._stop = False
        self._start_mode = ''
        self._bag_pubs: dict[str, object] = {}
        store = schema.typestore()
        for topic, (msgtype, latched) in self._topics.items():
            cls = message_class(msgtype)
            if latched:
                qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                                 reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.TRANSIENT_LOCAL)
            else:
                # Reliable, so that reliable subscribers (a recorder) lose nothing; a
                # shallow history for images (~1 MB each), deeper for small messages.
                depth = 10 if msgtype == schema.IMAGE_TYPE else 200
                qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                                 reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.VOLATILE)
            # Topics of the bag's namespace are published relative to this node's, so
            # that a replayer in a namespace feeds nodes in the same namespace.
            name = schema.relative(topic, bag_namespace) or topic
            self._bag_pubs[topic] = self.create_publisher(cls, name, qos,
                                                          event_callbacks=_NO_PUB_EVENTS)
        self._has_header = {
            topic: bool(store.fielddefs.get(msgtype)) and bool(store.fielddefs[msgtype][1])
            and store.fielddefs[msgtype][1][0][0] == 'header'
            and store.fielddefs[msgtype][1][0][1][1] == 'std_msgs/msg/Header'
            for topic, (msgtype, _) in self._topics.items()}
        self._streams: dict[str, _Stream] = {}
        self._ack_subs = []
        if flow_control:
            windows = windows or {}
            for topic in self._topics:
                rel = schema.relative(topic, bag_namespace)
                rule = FLOW_RULES.get(rel)
                if rule is None:
                    continue
                window = int(windows.get(rel, rule.window))
                if window < 1:
                    raise ValueError(f'flow-control window of {rel} must be >= 1, got {window}')
                self._streams[topic] = _Stream(rel, FlowRule(rule.ack_topic, rule.ack_type,
                                                             window, rule.via))
            self._subscribe_acks()
        self.create_subscription(DiagnosticArray, 'diagnostics', self._on_diagnostics,
                                 QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                                            reliability=ReliabilityPolicy.RELIABLE),
                                 event_callbacks=_NO_SUB_EVENTS)

    # ----------------------------------------------------------------- selection
    def _select(self, topics: list[str] | None) -> None:
        """Pick the connections to play; ``self._topics = {topic: (type, latched)}``."""
        names = {c.topic for c in self._connections}
        chosen = set(names)
        if topics:
            chosen = set()
            for want in topics:
                hits = {n for n in names if n == want or n == schema.qualified(
                    want, self.bag_namespace) or schema.relative(n, self.bag_namespace) == want}
                if not hits:
                    raise ValueError(f'{self.bag}: no topic {want!r} in the bag (it has '
                                     f'{", ".join(sorted(names))})')
                chosen |= hits
        self._play = [c for c in self._connections if c.topic in chosen]
        self._topics: dict[str, tuple[str, bool]] = {}
        store = schema.typestore()
        for conn in self._play:
            if conn.msgtype not in store.types:
                raise BagTypeError(f'{self.bag}: topic {conn.topic} has a message type '
                                   f'unknown to the typestore: {conn.msgtype}',
                                   path=self.bag, topic=conn.topic)
            previous = self._topics.get(conn.topic)
            if previous is not None and previous[0] != conn.msgtype:
                raise BagTypeError(f'{self.bag}: topic {conn.topic} has two types, '
                                   f'{previous[0]} and {conn.msgtype}', path=self.bag,
                                   topic=conn.topic)
            self._topics[conn.topic] = (conn.msgtype, _latched(conn))

    # ------------------------------------------------------------ acknowledgements
    def _subscribe_acks(self) -> None:
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                         reliability=ReliabilityPolicy.RELIABLE)
        ack_topics = {s.rule.ack_topic: s.rule.ack_type for s in self._streams.values()}
        for topic, msgtype in ack_topics.items():
            if topic == schema.INTEGRITY:
                sub = self.create_subscription(DiagnosticArray, topic, self._on_integrity, qos,
                                               event_callbacks=_NO_SUB_EVENTS)
            else:
                # Raw: the acknowledging stamp is the header stamp, read from the CDR
                # bytes without decoding the message (100 dead-reckoning states per second).
                sub = self.create_subscription(message_class(msgtype), topic,
                                               self._raw_ack(topic), qos, raw=True,
                                               event_callbacks=_NO_SUB_EVENTS)
            self._ack_subs.append((topic, sub))

    def _raw_ack(self, topic: str):
        def callback(data: bytes) -> None:
            try:
                stamp = header_stamp_ns(data)
            except MessageError:
                return
            self._acknowledge(topic, stamp)
        return callback

    def _on_integrity(self, msg: DiagnosticArray) -> None:
        try:
            risk = parse_integrity_risk(msg)
        except MessageError:
            return
        # Periodic STALE reports without GNSS repeat the last epoch: not a new epoch.
        if risk.epoch_stamp_ns is None or risk.epoch_status is None:
            return
        with self._cond:
            self._epochs_seen.add(int(risk.epoch_stamp_ns))
        self._acknowledge(schema.INTEGRITY, int(risk.epoch_stamp_ns))

    def _acknowledge(self, topic: str, stamp_ns: int) -> None:
        with self._cond:
            if stamp_ns > self._ack_newest.get(topic, -1):
                self._ack_newest[topic] = stamp_ns
                self._cond.notify_all()

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            try:
                values = status_values(status)
            except Exception:           # a foreign diagnostics publisher: not ours to judge
                continue
            with self._cond:
                self._diagnostics[status.name] = values

    def _settle(self, stream: _Stream) -> int:
        """Drop acknowledged stamps from ``stream.pending``; the number left (locked)."""
        newest = self._ack_newest.get(stream.rule.ack_topic, -1)
        while stream.pending and stream.pending[0] <= newest:
            stream.pending.popleft()
        return len(stream.pending)

    def _wait(self, stream: _Stream, done, what: str) -> None:
        """Wait (locked) until ``done()``; on timeout count the pending messages as lost."""
        if not stream.enabled or done():
            return
        start = time.monotonic()
        deadline = start + self.ack_timeout_s
        while not done():
            if self._stop or not self.context.ok():
                break
            now = time.monotonic()
            if now >= deadline:
                lost = len(stream.pending)
                stream.timeouts += lost
                stream.pending.clear()
                stream.consecutive_timeouts += 1
                self.get_logger().warning(
                    f'{stream.topic}: no {stream.rule.ack_topic} for {what} within '
                    f'{self.ack_timeout_s:g} s; {lost} message(s) unacknowledged')
                if stream.consecutive_timeouts >= _MAX_TIMEOUTS:
                    stream.enabled = False
                    stream.reason = (f'off: {_MAX_TIMEOUTS} acknowledgement timeouts on '
                                     f'{stream.rule.ack_topic}')
                    self.get_logger().warning(f'{stream.topic}: flow control {stream.reason}')
                break
            # Short slices: Ctrl-C in the main thread is handled between them.
            self._cond.wait(min(0.05, deadline - now))
        else:
            stream.consecutive_timeouts = 0
        stream.wait_s += time.monotonic() - start

    def _flow(self, topic: str, stamp_ns: int) -> None:
        """Block until ``topic``'s message stamped ``stamp_ns`` may be published."""
        stream = self._streams.get(topic)
        if stream is None:
            return
        with self._cond:
            if stream.topic == schema.GNSS:
                for other in self._streams.values():
                    if other.topic in GNSS_BARRIER:
                        self._wait(other, lambda o=other: self._settle(o) == 0
                                   or o.pending[0] > stamp_ns,
                                   f'the images up to the GNSS epoch at {stamp_ns} ns')
            # The first message of an acknowledging topic goes alone: a node initialises
            # from its first input (the dead reckoning starts from whichever source comes
            # first), and only an acknowledgement makes the processing order the
            # publication order. Afterwards the window applies.
            group = [s for s in self._streams.values()
                     if s.rule.ack_topic == stream.rule.ack_topic and s.enabled]
            if stream.rule.ack_topic not in self._ack_newest:
                for other in group:
                    self._wait(other, lambda o=other: self._settle(o) == 0,
                               f'the first message on {other.topic}')
            self._wait(stream, lambda: self._settle(stream) < stream.rule.window,
                       f'the message at {stream.pending[0] if stream.pending else 0} ns')
            grace = stream.topic == schema.GNSS and self._matched_since_gnss
            if stream.topic == schema.GNSS:
                self._matched_since_gnss = False
        if grace and self.gnss_grace_s > 0:
            # The replay has the camera matches of the interval, but fusion_node may not
            # have taken them yet: its executor serves ready subscriptions in creation
            # order, gnss/measurements before camera/matches, so an epoch that becomes
            # ready together with a match would run without it. A short pause before the
            # epoch lets the match be taken first (measured: 1 match in ~50 epochs was
            # missed without it on a loaded two-core machine).
            self._sleep_until(time.monotonic() + self.gnss_grace_s)

    # ---------------------------------------------------------------------- playing
    def _discover(self) -> None:
        """Wait (at most ``wait_s``) for consumers; streams without one play uncontrolled."""
        deadline = time.monotonic() + self.wait_s
        acks = dict(self._ack_subs)

        def missing() -> list[str]:
            out = []
            for topic, stream in self._streams.items():
                if self._bag_pubs[topic].get_subscription_count() == 0:
                    out.append(f'a subscriber on {topic}')
                elif acks[stream.rule.ack_topic].get_publisher_count() == 0:
                    out.append(f'a publisher of {stream.rule.ack_topic}')
                for via, subscribers in stream.rule.via:
                    if (self.count_publishers(via) == 0
                            or self.count_subscribers(via) < subscribers):
                        out.append(f'the connection {via}')
            for rel in self.require_subscribers:
                for topic in self._bag_pubs:
                    if (schema.relative(topic, self.bag_namespace) == rel
                            and self._bag_pubs[topic].get_subscription_count() == 0):
                        out.append(f'a subscriber on {topic}')
            return out

        while missing() and time.monotonic() < deadline and not self._stop:
            time.sleep(0.02)
        for topic, stream in self._streams.items():
            if self._bag_pubs[topic].get_subscription_count() == 0:
                stream.enabled, stream.reason = False, 'off: no subscriber'
            elif acks[stream.rule.ack_topic].get_publisher_count() == 0:
                stream.enabled = False
                stream.reason = f'off: nobody publishes {stream.rule.ack_topic}'
        self._start_mode = self._wait_for_links(deadline)
        if self._start_mode in ('', 'fixed settle'):
            time.sleep(self.settle_s)
        left = missing()
        if left:
            self.get_logger().warning(f'playing without {", ".join(left)} '
                                      f'(waited {self.wait_s:g} s)')

    def _link_requirements(self) -> list[tuple[str, int]]:
        """``(diagnostics key, minimum)`` of every link the flow control relies on.

        Each input must be matched at its consumer (``publishers_<input>``), each internal
        link (``FlowRule.via``) at both ends, and each acknowledging output must reach
        this node (``subscribers_<ack topic>``); see ``GnssCamNode.link_counts``.
        """
        out = []
        for stream in self._streams.values():
            if not stream.enabled:
                continue
            out.append((f'publishers_{stream.topic}', 1))
            out.append((f'subscribers_{stream.rule.ack_topic}', 1))
            for via, subscribers in stream.rule.via:
                out += [(f'publishers_{via}', 1), (f'subscribers_{via}', subscribers)]
        return sorted(set(out))

    def _wait_for_links(self, deadline: float) -> str:
        """Wait until the nodes' diagnostics report every link matched.

        Returns:
            ``'links matched'``; ``'links not matched'`` at the deadline; ``'fixed
            settle'`` when no node reports its links within :data:`LINK_REPORT_WAIT_S`
            (nodes that are not gnsscam_ros's: the caller sleeps ``settle_s``); ``''``
            when no stream is flow-controlled (the caller sleeps ``settle_s`` too).
        """
        wanted = self._link_requirements()
        if not wanted:
            return ''
        first_report = time.monotonic() + LINK_REPORT_WAIT_S

        def unmet() -> list[str] | None:
            with self._cond:
                reports = [v for v in self._diagnostics.values()
                           if any(k.startswith(('publishers_', 'subscribers_')) for k in v)]
            if not reports:
                return None
            return [f'{key} >= {least}' for key, least in wanted
                    if max(_as_int(r.get(key)) for r in reports) < least]

        while not self._stop:
            left = unmet()
            now = time.monotonic()
            if left == []:
                return 'links matched'
            if left is None and now >= first_report:
                return 'fixed settle'
            if now >= deadline:
                self.get_logger().warning('links not matched after '
                                          f'{self.wait_s:g} s: {", ".join(left or [])}')
                return 'links not matched'
            time.sleep(0.05)
        return ''

    def _sleep_until(self, t_wall: float) -> None:
        while not self._stop:
            left = t_wall - time.monotonic()
            if left <= 0:
                return
            time.sleep(min(left, 0.05))

    def stop(self) -> None:
        """Ask a running :meth:`play` to stop after the current message (thread-safe)."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()

    def play(self) -> ReplaySummary:
        """Play the bag (blocking) and return what was done.

        Raises:
            BagReadError: The bag fails while reading.
        """
        executor = SingleThreadedExecutor(context=self.context)
        executor.add_node(self)
        spinner = threading.Thread(target=_spin, args=(executor,), daemon=True,
                                   name='gnsscam_replay_spin')
        spinner.start()
        summary = ReplaySummary(bag=self.bag, rate=self.rate)
        gnss_stamps: list[int] = []
        try:
            waiting = time.monotonic()
            self._discover()
            started = time.monotonic()
            summary.start, summary.start_wait_s = self._start_mode, started - waiting
            try:
                self._publish_all(summary, gnss_stamps)
                self._drain()
            except (KeyboardInterrupt, ExternalShutdownException):
                # Ctrl-C: stop after the current message and report what was played.
                summary.interrupted = True
            finally:
                summary.wall_s = time.monotonic() - started
                summary.interrupted = (summary.interrupted or self._stop
                                       or not self.context.ok())
                self._summarise(summary, gnss_stamps)
        finally:
            executor.shutdown(timeout_sec=1.0)
            spinner.join(timeout=2.0)
            executor.remove_node(self)
        return summary

    def _publish_all(self, summary: ReplaySummary, gnss_stamps: list[int]) -> None:
        start_ns = self._bag_start_ns + int(round(self.start_s * 1e9))
        latched = [c for c in self._play if self._topics[c.topic][1]]
        timed = [c for c in self._play if not self._topics[c.topic][1]]
        try:
            with open_bag(self.bag) as reader:
                # Once-only topics first, whatever --start says: they describe the data.
                if latched:
                    for conn, _, raw in reader.messages(connections=latched):
                        self._bag_pubs[conn.topic].publish(bytes(raw))
                        summary.published[conn.topic] = summary.published.get(conn.topic,
                                                                              0) + 1
                if not timed:
                    return
                t0_stamp = t0_wall = None
                previous_target = 0.0
                for conn, stamp, raw in self._stamped(reader, timed, start_ns):
                    if self._stop or not self.context.ok():
                        break
                    if t0_stamp is None:
                        t0_stamp, t0_wall = stamp, time.monotonic()
                        summary.first_stamp_ns = stamp
                    if self.rate > 0:
                        # Original timing scaled by R; never backwards (stamps of
                        # different topics may interleave out of order).
                        previous_target = max(previous_target,
                                              t0_wall + (stamp - t0_stamp) / 1e9 / self.rate)
                        self._sleep_until(previous_target)
                    self._flow(conn.topic, stamp)
                    if self._stop:
                        break
                    self._bag_pubs[conn.topic].publish(raw)
                    stream = self._streams.get(conn.topic)
                    if stream is not None and stream.enabled:
                        with self._cond:
                            stream.pending.append(stamp)
                            if stream.topic in GNSS_BARRIER:
                                self._matched_since_gnss = True
                    summary.published[conn.topic] = summary.published.get(conn.topic, 0) + 1
                    summary.last_stamp_ns = max(summary.last_stamp_ns or stamp, stamp)
                    if schema.relative(conn.topic, self.bag_namespace) == schema.GNSS:
                        gnss_stamps.append(stamp)
        except BagError:
            raise
        except Exception as err:       # storage errors while iterating (truncated file)
            if self._stop or not self.context.ok():
                return                 # Ctrl-C shut the context down during a publish
            raise BagReadError(f'{self.bag}: reading failed: {type(err).__name__}: {err}',
                               path=self.bag) from err

    def _stamped(self, reader, connections, start_ns: int):
        """``(connection, stamp_ns, raw bytes)`` in bag order, equal stamps in TIE_ORDER.

        Messages with the same stamp have no order of their own (a live system receives
        them in any order); they are published in a fixed one, the dead reckoning's rule
        (``core.motion.DR_SOURCES``: odometry before IMU at equal stamps), then camera and
        GNSS after the motion of their instant, as a receiver delivers an epoch after its
        time of validity. Only consecutive messages are regrouped (bounded look-ahead).
        """
        group: list = []
        for conn, log_ns, raw in reader.messages(connections=connections, start=start_ns):
            raw = bytes(raw)
            stamp = log_ns
            if self._has_header[conn.topic]:
                try:
                    stamp = header_stamp_ns(raw)
                except MessageError as err:
                    raise BagReadError(f'{self.bag}: topic {conn.topic}: message at '
                                       f'{log_ns} ns: {err}', path=self.bag,
                                       topic=conn.topic) from err
            if group and stamp != group[0][1]:
                yield from self._tie_sorted(group)
                group = []
            group.append((conn, stamp, raw))
        yield from self._tie_sorted(group)

    def _tie_sorted(self, group: list) -> list:
        if len(group) < 2:
            return group
        rank = {t: i for i, t in enumerate(TIE_ORDER)}
        return sorted(group, key=lambda m: rank.get(
            schema.relative(m[0].topic, self.bag_namespace), len(TIE_ORDER)))

    def _drain(self) -> None:
        """Wait for the acknowledgements of the last GNSS epochs and images.

        The IMU and odometry streams are not waited for: the dead reckoning only passes a
        stamp once every source has, so the last samples of one source may never be
        acknowledged.
        """
        with self._cond:
            for stream in self._streams.values():
                if stream.topic in (schema.GNSS, schema.IMAGE):
                    self._wait(stream, lambda s=stream: self._settle(s) == 0,
                               'the last messages')

    def _summarise(self, summary: ReplaySummary, gnss_stamps: list[int]) -> None:
        with self._cond:
            summary.gnss_epochs = len(gnss_stamps)
            gnss_streams = [s for s in self._streams.values() if s.topic == schema.GNSS]
            has_filter = bool(self._epochs_seen) or any(
                s.enabled for s in gnss_streams)
            summary.gnss_epochs_processed = (
                sum(1 for s in gnss_stamps if s in self._epochs_seen) if has_filter else None)
            for stream in self._streams.values():
                self._settle(stream)
                summary.unacknowledged[stream.topic] = stream.timeouts
                summary.flow_control[stream.topic] = stream.reason
                summary.ack_wait_s[stream.topic] = stream.wait_s
            summary.node_diagnostics = {k: dict(v) for k, v in self._diagnostics.items()}


def _as_int(value) -> int:
    try:
        return int(value)
    except (TypeError, ValueError):
        return 0


def _latched(conn) -> bool:
    """True when the bag offers the topic ``transient_local`` (recorded once)."""
    ext = getattr(conn, 'ext', None)
    for qos in getattr(ext, 'offered_qos_profiles', None) or ():
        durability = getattr(qos, 'durability', None)
        if durability is not None and 'TRANSIENT_LOCAL' in str(durability).upper():
            return True
    return False


def _spin(executor) -> None:
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        if executor.context.ok():      # a callback failed (not a shutdown): say so, the
            traceback.print_exc()      # acknowledgements will time out with a warning


# ================================================================ through the nodes
_runs = itertools.count()


def default_domain_id() -> int:
    """``$ROS_DOMAIN_ID``, else a domain in 220-232 (apart from the tests' ids) that
    changes with the process and with every call, so that concurrent runs on one machine
    do not see each other's topics and a run does not match the endpoints of a previous
    run's nodes that the discovery has not forgotten yet."""
    env = os.environ.get('ROS_DOMAIN_ID')
    if env and env.isdigit():
        return int(env)
    return 220 + (os.getpid() + next(_runs)) % 13


def _overrides(values: dict) -> list:
    from rclpy.parameter import Parameter
    return [Parameter(name, value=value) for name, value in values.items()]


#: Fast DDS profile for large messages between processes on one machine. With the default
#: transports a 640x480 bgr8 image (0.9 MB) does not fit the 512 kB shared-memory segment
#: and travels as UDP fragments; a best-effort reader (camera_node takes images with sensor
#: QoS) drops the whole image when one fragment is lost, which loopback socket buffers
#: make common: measured here, 17 of 50 images paced at 10 Hz arrived. A 32 MB segment
#: carries whole images (50 of 50), and the GNSS epochs no longer compete with them for it.
DDS_PROFILE = """<?xml version="1.0" encoding="UTF-8" ?>
<!-- gnsscam_ros: shared memory large enough for camera images (see live/replay.py). -->
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <transport_descriptors>
    <transport_descriptor>
      <transport_id>gnsscam_shm</transport_id>
      <type>SHM</type>
      <segment_size>33554432</segment_size>
      <port_queue_capacity>1024</port_queue_capacity>
      <maxMessageSize>4194304</maxMessageSize>
    </transport_descriptor>
    <transport_descriptor>
      <transport_id>gnsscam_udp</transport_id>
      <type>UDPv4</type>
    </transport_descriptor>
  </transport_descriptors>
  <participant profile_name="gnsscam_participant" is_default_profile="true">
    <rtps>
      <userTransports>
        <transport_id>gnsscam_shm</transport_id>
        <transport_id>gnsscam_udp</transport_id>
      </userTransports>
      <useBuiltinTransports>false</useBuiltinTransports>
    </rtps>
  </participant>
</profiles>
"""
PROFILE_ENV = 'FASTRTPS_DEFAULT_PROFILES_FILE'


def write_dds_profile(path: str | Path) -> Path:
    """Write :data:`DDS_PROFILE` (use it with ``FASTRTPS_DEFAULT_PROFILES_FILE=path`` in
    every process of the graph, before it starts)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(DDS_PROFILE, encoding='utf-8')
    return path


def use_dds_profile(folder: str | Path) -> str | None:
    """Point ``FASTRTPS_DEFAULT_PROFILES_FILE`` at :data:`DDS_PROFILE` (written into
    ``folder``) unless the user set one or another RMW is used.

    Fast DDS reads the file when a process creates its first participant, so call this
    before the first ``rclpy.init`` of the process; child processes inherit it.

    Returns:
        The profile file in force (None: not Fast DDS).
    """
    rmw = os.environ.get('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
    if not rmw.startswith('rmw_fastrtps'):
        return None
    if not os.environ.get(PROFILE_ENV):
        os.environ[PROFILE_ENV] = str(write_dds_profile(Path(folder) / 'fastdds_profile.xml'))
    return os.environ[PROFILE_ENV]


#: Where :func:`replay_through_nodes` runs the nodes (see there).
LAYOUTS = ('threads', 'processes', 'pipeline')
NODE_MODULES = {'gnss_node': 'gnss_node', 'camera_node': 'camera_node',
                'imu_node': 'imu_node', 'fusion_node': 'fusion_node'}


def replay_through_nodes(bag: str | Path, result_bag: str | Path | None = None, *,
                         rate: float = 0.0, start_s: float = 0.0,
                         topics: list[str] | None = None,
                         parameters: dict[str, dict] | None = None, database=None,
                         layout: str = 'processes', domain_id: int | None = None,
                         record_topics: list[str] | None = None, settle_s: float = 0.5,
                         wait_s: float = 60.0, log_dir: str | Path | None = None,
                         windows: dict[str, int] | None = None, namespace: str | None = None
                         ) -> tuple[ReplaySummary, object]:
    """Replay a bag through the four nodes and record their outputs (one call).

    Layouts:

    * ``'processes'`` (default, fastest): each node is its own executable in a child
      process (``python -m gnsscam_ros.nodes.<node>``, as ``ros2 run`` starts them) with a
      generated ``--params-file``; the replay and the recorder run in this process. The
      nodes then run in parallel on separate cores and each spins a small executor.
    * ``'threads'``: the nodes in this process, one single-threaded executor per node on
      its own thread (an rclpy executor rebuilds its wait set on every wake-up, at a cost
      that grows with the number of entities it serves: per-node executors keep it
      small). All share one GIL with the replay. ``database`` can pass a loaded map
      database to camera_node.
    * ``'pipeline'``: ``pipeline_node`` (the four nodes in one process, one executor
      thread each) in a child process.

    :data:`REPLAY_NODE_PARAMETERS` are applied under ``parameters``.

    Args:
        bag: The dataset bag.
        result_bag: Bag to record the outputs into (must not exist); None: no recording.
        rate: Replay rate (0 = as fast as the nodes keep up).
        start_s: Skip this much of the bag [s].
        topics: Topics to replay (None: all).
        parameters: Node parameters ``{node name: {name: value}}``.
        database: A loaded map database for camera_node (``'threads'`` only; child
            processes need ``camera_node.database_path``).
        layout: One of :data:`LAYOUTS`.
        domain_id: ROS domain (default :func:`default_domain_id`).
        record_topics: Topics to record (default ``record.DEFAULT_TOPICS``).
        settle_s: After the replay, wait until the recorder saw nothing new for this
            long [s].
        wait_s: Longest wait for the nodes to come up [s].
        log_dir: Folder for the child processes' ROS logs and stderr (default: a new
            temporary folder).
        windows: Flow-control windows overriding :data:`FLOW_RULES` (by relative topic).
        namespace: ROS namespace of the nodes, the replay and the recorder (default: a
            private one per run, ``/gnsscam_<pid>_<n>``, so that other graphs on the
            machine, in the same domain or not, never mix with this one). The result bag
            stores the topics without it (``/pose``).

    Returns:
        ``(replay summary, record summary or None)``.

    Raises:
        BagError: Unreadable bag or result bag problems.
        RuntimeError: A child process died during the replay.
        ValueError: Unknown layout.
    """
    from .record import BagRecorder
    if layout not in LAYOUTS:
        raise ValueError(f'unknown layout {layout!r}; use one of {LAYOUTS}')
    params = merge_parameters(REPLAY_NODE_PARAMETERS, parameters or {})
    domain = default_domain_id() if domain_id is None else int(domain_id)
    if layout != 'threads':
        import tempfile
        use_dds_profile(log_dir if log_dir is not None else tempfile.mkdtemp(
            prefix='gnsscam_dds_'))
    ns = namespace or f'/gnsscam_{os.getpid()}_{next(_runs)}'
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    nodes: list = []
    procs: list = []
    recorder = None
    spinner = None
    record_summary = None
    try:
        if layout == 'threads':
            from ..nodes.camera_node import CameraNode
            from ..nodes.fusion_node import FusionNode
            from ..nodes.gnss_node import GnssNode
            from ..nodes.imu_node import ImuNode

            def kwargs(node: str) -> dict:
                return {'context': ctx, 'namespace': ns,
                        'parameter_overrides': _overrides(params.get(node, {}))}

            nodes = [GnssNode(**kwargs('gnss_node')),
                     CameraNode(database=database, **kwargs('camera_node')),
                     ImuNode(**kwargs('imu_node')), FusionNode(**kwargs('fusion_node'))]
        else:
            procs = _start_node_processes(params, domain, log_dir, layout == 'pipeline', ns)
        if result_bag is not None:
            recorder = BagRecorder(result_bag, topics=record_topics, context=ctx,
                                   namespace=ns, strip_namespace=True)
        spinner = NodeSpinner(nodes + ([recorder] if recorder is not None else []), ctx)
        required = ()
        if recorder is not None:
            wanted = [schema.relative(t.split(':')[0]) for t in (record_topics or [
                schema.TRUTH, schema.ORIGIN, schema.INFO])]
            required = tuple(t for t in wanted if t in (schema.TRUTH, schema.ORIGIN,
                                                        schema.INFO))
        replayer = BagReplayer(bag, rate=rate, start_s=start_s, topics=topics,
                               windows=windows, wait_s=wait_s, context=ctx, namespace=ns,
                               require_subscribers=required,
                               settle_s=MATCH_SETTLE_S if layout == 'threads'
                               else FRESH_PROCESSES_SETTLE_S)
        cpu0 = _own_cpu_s()
        try:
            summary = replayer.play()
        finally:
            replayer.destroy_node()
        summary.cpu_s['replay'] = _own_cpu_s() - cpu0
        for proc, name in procs:
            summary.cpu_s[name] = _process_cpu_s(proc.pid)
        for proc, name in procs:
            if proc.poll() is not None:
                raise RuntimeError(f'{name} exited with status {proc.returncode} during '
                                   'the replay')
        if recorder is not None:
            last, quiet_since = -1, time.monotonic()
            deadline = time.monotonic() + max(10.0, 4 * settle_s)
            while time.monotonic() - quiet_since < settle_s and time.monotonic() < deadline:
                total = sum(recorder.summary.counts.values())
                if total != last:
                    last, quiet_since = total, time.monotonic()
                time.sleep(0.05)
            record_summary = recorder.close()
        return summary, record_summary
    except BaseException:
        if recorder is not None:
            recorder.abort()
        raise
    finally:
        if spinner is not None:
            spinner.stop()
        for node in nodes + ([recorder] if recorder is not None else []):
            node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        for proc, _ in procs:
            stop_process(proc)


def _start_node_processes(params: dict[str, dict], domain: int,
                          log_dir: str | Path | None, pipeline: bool, namespace: str) -> list:
    """Start the nodes as child processes: ``[(Popen, name)]``."""
    import subprocess
    import tempfile
    folder = Path(log_dir) if log_dir is not None else Path(
        tempfile.mkdtemp(prefix='gnsscam_replay_'))
    folder.mkdir(parents=True, exist_ok=True)
    # Keys with the namespace: a bare node name only matches nodes in the root namespace.
    params_file = write_params_file(folder / 'replay_params.yaml', {
        f'{namespace.rstrip("/")}/{node}': values for node, values in params.items()})
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=str(domain), ROS_LOG_DIR=str(folder / 'ros_log'),
               ROS_AUTOMATIC_DISCOVERY_RANGE=env.get('ROS_AUTOMATIC_DISCOVERY_RANGE',
                                                     'LOCALHOST'),
               OPENBLAS_NUM_THREADS=env.get('OPENBLAS_NUM_THREADS', '1'))
    modules = {'pipeline_node': 'pipeline'} if pipeline else NODE_MODULES
    procs = []
    try:
        for name, module in modules.items():
            stderr = (folder / f'{name}.stderr.txt').open('w')
            procs.append((subprocess.Popen(
                [sys.executable, '-m', f'gnsscam_ros.nodes.{module}', '--ros-args',
                 '-r', f'__ns:={namespace}', '--params-file', str(params_file)], env=env,
                stdout=subprocess.DEVNULL, stderr=stderr), name))
            stderr.close()
    except BaseException:
        for proc, _ in procs:
            stop_process(proc)
        raise
    return procs


def _own_cpu_s() -> float:
    """CPU time of this process so far (all threads) [s]."""
    return time.process_time()


def _process_cpu_s(pid: int) -> float:
    """CPU time (user + system) of a running child process [s] (NaN when unknown)."""
    try:
        fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')
    except (OSError, ValueError, IndexError):
        return math.nan


# ============================================================================ CLI
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='gnsscam_replay',
        description='Play a rosbag2 bag into the gnsscam_ros nodes with its original timing '
        'scaled by --rate, lossless (flow control on the nodes\' outputs). Alternative on '
        'a ROS 2 machine: ros2 bag play BAG.')
    parser.add_argument('bag', type=Path, help='bag folder (or .mcap / .db3 file)')
    parser.add_argument('--rate', type=float, default=1.0,
                        help='time scale: 2 = twice as fast; 0 = as fast as the nodes keep '
                        'up (default %(default)s)')
    parser.add_argument('--start', type=float, default=0.0, metavar='S',
                        help='skip the first S seconds of the bag (default 0)')
    parser.add_argument('--topics', nargs='+', metavar='TOPIC',
                        help='play only these topics (default: all)')
    parser.add_argument('--no-flow-control', action='store_true',
                        help='publish on time only, never wait for the nodes (may lose '
                        'input at high rates)')
    parser.add_argument('--ack-timeout', type=float, default=30.0, metavar='SECONDS',
                        help='longest wait for one acknowledgement (default %(default)s)')
    parser.add_argument('--wait', type=float, default=10.0, metavar='SECONDS',
                        help='longest wait for the nodes to appear (default %(default)s)')
    parser.add_argument('--namespace', default='/',
                        help='namespace the bag topics were written under (default /)')
    parser.add_argument('--no-dds-profile', action='store_true',
                        help='keep Fast DDS\'s default transports (by default the replay '
                        'uses a shared-memory segment large enough for camera images, unless '
                        'FASTRTPS_DEFAULT_PROFILES_FILE is set)')
    parser.add_argument('--json', type=Path, help='write the summary as JSON')
    return parser


def main(argv: list[str] | None = None) -> int:
    """``gnsscam_replay``; returns the exit code (see the module docstring)."""
    args_all = sys.argv[1:] if argv is None else list(argv)
    # --ros-args ... belongs to rclpy (remaps, parameters); the rest is ours.
    ros_at = args_all.index('--ros-args') if '--ros-args' in args_all else len(args_all)
    parser = build_parser()
    args = parser.parse_args(args_all[:ros_at])
    if args.json is not None and args.json.exists():
        print(f'gnsscam_replay: {args.json} exists; not overwriting', file=sys.stderr)
        return EXIT_USAGE
    if not args.no_dds_profile:
        import tempfile
        use_dds_profile(Path(tempfile.gettempdir()) / f'gnsscam_replay_{os.getuid()}')
    rclpy.init(args=['gnsscam_replay'] + args_all[ros_at:])
    node = None
    summary = None
    code = EXIT_OK
    try:
        node = BagReplayer(args.bag, rate=args.rate, start_s=args.start, topics=args.topics,
                           flow_control=not args.no_flow_control,
                           ack_timeout_s=args.ack_timeout, wait_s=args.wait,
                           bag_namespace=args.namespace)
        summary = node.play()
    except (BagError, ValueError) as err:
        print(f'gnsscam_replay: {err}', file=sys.stderr)
        code = EXIT_INPUT if isinstance(err, BagError) else EXIT_USAGE
    except (KeyboardInterrupt, ExternalShutdownException):
        print('gnsscam_replay: interrupted', file=sys.stderr)
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    if summary is not None:
        print(summary.text())
        if args.json is not None:
            from ..io.atomic import write_json_atomic
            write_json_atomic(args.json, summary.as_dict())
    return code


if __name__ == '__main__':
    sys.exit(main())
