"""The replay node: plays a rosbag2 bag into the nodes, lossless at any speed.

Messages are published in bag order with their original timing scaled by ``R``: the
message stamped ``t`` goes out at ``(t - t_first) / R`` after the first one. The time of a
message is its header stamp (the converter writes bag time = header stamp; for bags
recorded live the header stamp is the time of validity, which is what the filter uses);
messages without a header (``dataset/info``) use the bag time. ``R = 0`` (or any R faster
than the nodes) plays as fast as the nodes keep up. A start offset skips bag time, except
the once-only (``transient_local``) topics ``dataset/info`` and ``map/origin``, which are
always published first. The serialised CDR of the bag is published as it is
(``Publisher.publish(bytes)``): nothing is decoded, converted or re-encoded on the way, so
the nodes see the bytes the converter wrote.

Flow control (:mod:`.flow`) keeps every node queue from overflowing; the replay reports
per epoch whether its ``integrity_risk`` came back (``gnss_epochs_processed``).

**Same input, same order as an offline run** (``evaluation.demo.offline_run``; the tests
check it to 1e-6 m): messages with equal stamps go out in ``msg_adapters.wire.TIE_ORDER``;
the flow rules of :mod:`.flow` make the processing order the publication order; and before
the first message the replay waits for the graph's internal connections (``FlowRule.via``)
and then until the nodes' diagnostics report every link *matched* at both ends
(``GnssCamNode.link_counts``: discovery is not matching, and a message sent before the
match is lost). With a fixed 3.5 s delay instead, one of three demo runs here lost
fusion_node's first dead-reckoning states and differed from the offline run by metres.
Nodes that report no links get ``settle_s`` instead.

A stream whose consumer is absent (no subscriber on the input, or no publisher of its
acknowledging topic after ``wait_s``) is played without flow control.

**Nodes that already ran** (a bag played again into running nodes, or another bag): each
node reports the newest stamp its inputs took (``newest_input_stamp_ns`` on
``diagnostics``). When the bag does not continue it (it starts at or before that stamp, or
more than ``msg_adapters.limits.STAMP_WINDOW_S`` after it), the replay calls every node's
``~/reset`` (``std_srvs/Trigger``) before the first message, so that the nodes take the
bag as a new time base at once: without it they refused the bag's first messages as out
of time, every acknowledgement of the replay timed out and the filter updated a few epochs.
"""
from __future__ import annotations

import math
import threading
import time
import traceback
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray
from std_srvs.srv import Trigger
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from msg_adapters import MessageError, parse_integrity_risk, status_values
from msg_adapters.limits import STAMP_WINDOW_NS
from msg_adapters.wire import DIAGNOSTICS, GNSS, INTEGRITY, TIE_ORDER, header_stamp_ns

from ..bags import schema
from ..bags.errors import BagContentError, BagError, BagReadError, BagTypeError
from ..bags.read import open_bag
from .endpoints import NO_PUB_EVENTS, NO_SUB_EVENTS, ros_message_class
from .flow import GNSS_GRACE_S, FlowControl
from .summary import ReplaySummary

#: Fallback when the nodes do not report their links (not gnsscam_ros nodes): wait this
#: long after the graph is connected, for the endpoints to match [s].
MATCH_SETTLE_S = 0.5
#: How long to wait for the nodes' first link report (diagnostics, once a second) before
#: falling back to a fixed settle time [s].
LINK_REPORT_WAIT_S = 3.0
#: Longest wait for a node's answer to ``~/reset`` [s].
RESET_TIMEOUT_S = 10.0


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
        flow_control: Apply the flow control of :data:`.flow.FLOW_RULES`.
        windows: Per relative topic, a window overriding :data:`.flow.FLOW_RULES`.
        ack_timeout_s: Longest wait for one acknowledgement [s].
        wait_s: Longest wait for the consumers (subscribers and acknowledging publishers)
            to appear before playing [s].
        require_subscribers: Relative topics that must have a subscriber before playing
            (e.g. the ones a recorder records), within ``wait_s``.
        settle_s: Wait after the graph is connected, before the first message [s]; longer
            when finding the subscribers took longer (a loaded machine).
        gnss_grace_s: Pause before a GNSS epoch that follows camera images, once their
            matches are acknowledged (see :meth:`.FlowControl.admit`) [s].
        bag_namespace: Namespace the bag's topics were written under (to recognise them);
            they are published relative to the node's own namespace (``namespace=``).
            None: the node's namespace when the bag has topics under it, else ``/`` (a
            bag converted at the root played into a namespace).
        node_name: Node name.
        **kwargs: Forwarded to ``rclpy.node.Node`` (``context=``, ...).

    Raises:
        BagReadError: The bag is missing or unreadable.
        BagTypeError: A selected topic has a message type rclpy does not know, or a topic
            of the gnsscam_ros graph (:data:`.schema.TOPIC_TYPES`) has another type than
            the nodes use (e.g. ``std_msgs/msg/String`` on ``gnss/pseudoranges``).
        BagContentError: The selected topics hold no message.
        ValueError: Negative rate or start, or a named topic that the bag does not hold.
    """

    def __init__(self, bag: str | Path, rate: float = 1.0, start_s: float = 0.0,
                 topics: list[str] | None = None, flow_control: bool = True,
                 windows: dict[str, int] | None = None, ack_timeout_s: float = 30.0,
                 wait_s: float = 10.0, require_subscribers: tuple[str, ...] = (),
                 settle_s: float = MATCH_SETTLE_S, gnss_grace_s: float = GNSS_GRACE_S,
                 bag_namespace: str | None = '/', node_name: str = 'gnsscam_replay',
                 **kwargs):
        if not (rate >= 0.0 and math.isfinite(rate)):
            raise ValueError(f'rate must be finite and >= 0, got {rate}')
        if not (start_s >= 0.0 and math.isfinite(start_s)):
            raise ValueError(f'start must be finite and >= 0 s, got {start_s}')
        self.bag = Path(bag)
        self.rate = float(rate)
        self.start_s = float(start_s)
        self.ack_timeout_s = float(ack_timeout_s)
        self.wait_s = float(wait_s)
        self.settle_s = float(settle_s)
        self.gnss_grace_s = float(gnss_grace_s)
        self.require_subscribers = tuple(require_subscribers)
        # Read the bag's table of contents before creating the node, so that a bad bag
        # fails fast without touching the ROS graph.
        with open_bag(self.bag) as reader:
            self._connections = list(reader.connections)
            self._bag_start_ns = int(reader.start_time)
        if bag_namespace is None:
            bag_namespace = _bag_namespace(self._connections, kwargs.get('namespace') or '/')
        self.bag_namespace = bag_namespace
        self._select(topics)
        # The executor of this node wakes for every acknowledgement (100 per second of an
        # IMU stream) and rclpy rebuilds its wait set at each wake, at a cost that grows
        # with every service and event handler: the replay has no ROS parameters, so no
        # parameter services, and no QoS event handlers (all its endpoints are reliable,
        # compatible with any subscriber).
        kwargs.setdefault('start_parameter_services', False)
        super().__init__(node_name, **kwargs)
        self.flow = FlowControl(self.ack_timeout_s, self.gnss_grace_s,
                                stopped=self._stopping,
                                warn=self.get_logger().warning)
        self._cond = self.flow.cond         # one lock for the flow and the replay's state
        self._epochs_seen: set[int] = set()
        self._diagnostics: dict[str, dict] = {}
        self._stop = False
        self._start_mode = ''
        #: Nodes reset before playing (they held another time base).
        self.reset_nodes: list[str] = []
        self._bag_pubs: dict[str, object] = {}
        store = self._store = schema.typestore()
        for topic, (msgtype, latched) in self._topics.items():
            cls = ros_message_class(msgtype)
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
                                                          event_callbacks=NO_PUB_EVENTS)
        self._has_header = {
            topic: bool(store.fielddefs.get(msgtype)) and bool(store.fielddefs[msgtype][1])
            and store.fielddefs[msgtype][1][0][0] == 'header'
            and store.fielddefs[msgtype][1][0][1][1] == 'std_msgs/msg/Header'
            for topic, (msgtype, _) in self._topics.items()}
        self._streams = self.flow.streams
        self._ack_subs = []
        if flow_control:
            windows = windows or {}
            for topic in self._topics:
                rel = schema.relative(topic, bag_namespace)
                self.flow.control(topic, rel, windows.get(rel))
            self._subscribe_acks()
        self.create_subscription(DiagnosticArray, DIAGNOSTICS, self._on_diagnostics,
                                 QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                                            reliability=ReliabilityPolicy.RELIABLE),
                                 event_callbacks=NO_SUB_EVENTS)

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
            # A topic the nodes know with another type would reach them as messages they
            # cannot read (or not at all): refuse the bag before publishing anything.
            expected = _graph_type(conn.topic)
            if expected is not None and conn.msgtype != expected:
                raise BagTypeError(f'{self.bag}: topic {conn.topic} has type {conn.msgtype}, '
                                   f'expected {expected} (--topics plays the others)',
                                   path=self.bag, topic=conn.topic)
            previous = self._topics.get(conn.topic)
            if previous is not None and previous[0] != conn.msgtype:
                raise BagTypeError(f'{self.bag}: topic {conn.topic} has two types, '
                                   f'{previous[0]} and {conn.msgtype}', path=self.bag,
                                   topic=conn.topic)
            self._topics[conn.topic] = (conn.msgtype, _latched(conn))
        # An empty bag would "play" in no time and exit 0 as if the data had gone through.
        if not sum(int(getattr(c, 'msgcount', 0) or 0) for c in self._play):
            raise BagContentError(f'{self.bag}: no messages to play'
                                  + (f' on {", ".join(sorted(self._topics))}'
                                     if self._topics else ' (no topics)'), path=self.bag)

    # ------------------------------------------------------------ acknowledgements
    def _subscribe_acks(self) -> None:
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                         reliability=ReliabilityPolicy.RELIABLE)
        ack_topics = {s.rule.ack_topic: s.rule.ack_type for s in self._streams.values()}
        for topic, msgtype in ack_topics.items():
            if topic == INTEGRITY:
                sub = self.create_subscription(DiagnosticArray, topic, self._on_integrity, qos,
                                               event_callbacks=NO_SUB_EVENTS)
            else:
                # Raw: the acknowledging stamp is the header stamp, read from the CDR
                # bytes without decoding the message (100 dead-reckoning states per second).
                sub = self.create_subscription(ros_message_class(msgtype), topic,
                                               self._raw_ack(topic), qos, raw=True,
                                               event_callbacks=NO_SUB_EVENTS)
            self._ack_subs.append((topic, sub))

    def _raw_ack(self, topic: str):
        def callback(data: bytes) -> None:
            try:
                stamp = header_stamp_ns(data)
            except MessageError:
                return
            self.flow.acknowledge(topic, stamp)
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
        self.flow.acknowledge(INTEGRITY, int(risk.epoch_stamp_ns))

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            try:
                values = status_values(status)
            except Exception:           # a foreign diagnostics publisher: not ours to judge
                continue
            with self._cond:
                self._diagnostics[status.name] = values

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

        began = time.monotonic()
        while (absent := missing()) and time.monotonic() < deadline and not self._stopping():
            time.sleep(0.02)
        # The other side matches our publishers about as slowly as we found its
        # subscribers (both learn of each other from the same announcements): on a loaded
        # machine, longer than the fixed settle time. Not known when some never came.
        settle_s = self.settle_s if absent else max(self.settle_s, time.monotonic() - began)
        for topic, stream in self._streams.items():
            if self._bag_pubs[topic].get_subscription_count() == 0:
                stream.enabled, stream.reason = False, 'off: no subscriber'
            elif acks[stream.rule.ack_topic].get_publisher_count() == 0:
                stream.enabled = False
                stream.reason = f'off: nobody publishes {stream.rule.ack_topic}'
        self._start_mode = self._wait_for_links(deadline)
        if self._start_mode in ('', 'fixed settle'):
            time.sleep(settle_s)
        self._reset_nodes_of_another_time_base()
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

        while not self._stopping():
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

    def _nodes_of_another_time_base(self) -> list[str]:
        """Nodes whose inputs took stamps that the bag does not continue (see the module
        docstring), by name, from their latest diagnostics."""
        first_ns = self._bag_start_ns + int(round(self.start_s * 1e9))
        with self._cond:
            reports = dict(self._diagnostics)
        out = []
        for status_name, values in reports.items():
            newest = values.get('newest_input_stamp_ns')
            if newest is None or not status_name.endswith(': status'):
                continue
            try:
                newest_ns = int(newest)
            except ValueError:
                continue
            if not newest_ns < first_ns <= newest_ns + STAMP_WINDOW_NS:
                out.append(status_name[:-len(': status')])
        return out

    def _reset_nodes_of_another_time_base(self) -> None:
        """Call ``~/reset`` of every node that offers it when one of them holds another
        time base (a downstream node would otherwise keep the old one); each answer is
        waited for, at most :data:`RESET_TIMEOUT_S`."""
        if self._stopping() or not self._nodes_of_another_time_base():
            return
        prefix = schema.qualified('', self.get_namespace())
        with self._cond:
            reporting = sorted(k[:-len(': status')] for k in self._diagnostics
                               if k.endswith(': status'))
        offered = {name for name, types in self.get_service_names_and_types()
                   if 'std_srvs/srv/Trigger' in types}
        for node in reporting:
            name = f'{prefix}{node}/reset'
            if name not in offered:
                continue
            client = self.create_client(Trigger, name)
            try:
                client.wait_for_service(timeout_sec=RESET_TIMEOUT_S)
                future = client.call_async(Trigger.Request())
                deadline = time.monotonic() + RESET_TIMEOUT_S
                while (not future.done() and time.monotonic() < deadline
                       and not self._stopping()):
                    time.sleep(0.01)
                answer = future.result() if future.done() else None
            finally:
                self.destroy_client(client)
            if answer is not None and answer.success:
                self.reset_nodes.append(node)
            else:
                self.get_logger().warning(f'{name}: no answer within {RESET_TIMEOUT_S:g} s; '
                                          'the node may refuse the first messages')

    def _stopping(self) -> bool:
        """A stop was asked for, or the context is down (Ctrl-C: rclpy's signal handler
        shuts it down): every wait of the replay ends."""
        return self._stop or not self.context.ok()

    def _sleep_until(self, t_wall: float) -> None:
        while not self._stopping():
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
            waiting = started = time.monotonic()
            try:
                self._discover()
                started = time.monotonic()
                summary.start, summary.start_wait_s = self._start_mode, started - waiting
                summary.reset_nodes = list(self.reset_nodes)
                if not self._stopping():
                    self._publish_all(summary, gnss_stamps)
                    self.flow.drain()
                    summary.undelivered = self._deliver_all()
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
                    for conn, log_ns, raw in reader.messages(connections=latched):
                        raw = bytes(raw)
                        self._check_decodes(conn, log_ns, raw)
                        self._bag_pubs[conn.topic].publish(raw)
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
                    pause = self.flow.admit(conn.topic, stamp)
                    if pause > 0:
                        self._sleep_until(time.monotonic() + pause)
                    if self._stop:
                        break
                    self._bag_pubs[conn.topic].publish(raw)
                    self.flow.published(conn.topic, stamp)
                    summary.published[conn.topic] = summary.published.get(conn.topic, 0) + 1
                    summary.last_stamp_ns = max(summary.last_stamp_ns or stamp, stamp)
                    if schema.relative(conn.topic, self.bag_namespace) == GNSS:
                        gnss_stamps.append(stamp)
        except BagError:
            raise
        except Exception as err:       # storage errors while iterating (truncated file)
            if self._stop or not self.context.ok():
                return                 # Ctrl-C shut the context down during a publish
            raise BagReadError(f'{self.bag}: reading failed: {type(err).__name__}: {err}',
                               path=self.bag) from err

    def _deliver_all(self) -> list[str]:
        """Wait (at most ``ack_timeout_s`` in all) until every reliable subscriber holds
        every message published; the topics where one does not. Leaving before would lose
        the last messages still in flight (a recorder's, a reliable node's)."""
        deadline = time.monotonic() + self.ack_timeout_s
        undelivered = []
        for topic, pub in self._bag_pubs.items():
            left = max(0.0, deadline - time.monotonic())
            if not pub.wait_for_all_acked(Duration(seconds=left)):
                undelivered.append(topic)
        if undelivered:
            self.get_logger().warning(
                f'not every subscriber acknowledged every message within '
                f'{self.ack_timeout_s:g} s on {", ".join(undelivered)}')
        return undelivered

    def _stamped(self, reader, connections, start_ns: int):
        """``(connection, stamp_ns, raw bytes)`` in bag order, equal stamps in
        ``msg_adapters.wire.TIE_ORDER`` (converted bags are written in it; a recorded bag
        has the order its messages arrived in). Only consecutive messages are regrouped
        (bounded look-ahead).
        """
        group: list = []
        for conn, log_ns, raw in reader.messages(connections=connections, start=start_ns):
            raw = bytes(raw)
            self._check_decodes(conn, log_ns, raw)
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

    def _check_decodes(self, conn, log_ns: int, raw: bytes) -> None:
        """Refuse a message that does not decode as its type: the nodes could not read it
        (rmw drops it before any callback), so playing on would report a clean replay of
        data that never arrived. Costs ~20 us per small message, ~0.2 ms per image."""
        try:
            self._store.deserialize_cdr(raw, conn.msgtype)
        except Exception as err:    # rosbags raises plain struct/index/value errors
            raise BagReadError(f'{self.bag}: topic {conn.topic}: message at {log_ns} ns does '
                               f'not decode as {conn.msgtype}: {type(err).__name__}: {err}',
                               path=self.bag, topic=conn.topic) from err

    def _tie_sorted(self, group: list) -> list:
        if len(group) < 2:
            return group
        rank = {t: i for i, t in enumerate(TIE_ORDER)}
        return sorted(group, key=lambda m: rank.get(
            schema.relative(m[0].topic, self.bag_namespace), len(TIE_ORDER)))

    def _summarise(self, summary: ReplaySummary, gnss_stamps: list[int]) -> None:
        with self._cond:
            summary.gnss_epochs = len(gnss_stamps)
            gnss_streams = [s for s in self._streams.values() if s.topic == GNSS]
            # A filter answered, or one was there (its stream's flow control may have gone
            # off after timeouts: then its count is what came back, not "unknown").
            has_filter = (bool(self._epochs_seen) or any(s.enabled for s in gnss_streams)
                          or any(s.timeouts for s in gnss_streams))
            summary.gnss_epochs_processed = (
                sum(1 for s in gnss_stamps if s in self._epochs_seen) if has_filter else None)
            self.flow.report(summary)
            summary.node_diagnostics = {k: dict(v) for k, v in self._diagnostics.items()}


def _graph_type(topic: str) -> str | None:
    """The type the nodes use on ``topic`` when it ends in a topic of the graph (in any
    namespace: ``/a/gnss/pseudoranges`` reaches nodes run under ``/a`` wherever the replay
    runs), else None."""
    name = topic.lstrip('/')
    # Longest first: ground_truth/pose is not pose.
    for known in sorted(schema.TOPIC_TYPES, key=len, reverse=True):
        if name == known or name.endswith('/' + known):
            return schema.TOPIC_TYPES[known]
    return None


def _bag_namespace(connections, namespace: str) -> str:
    """``namespace`` when the bag has topics under it, else ``/`` (see ``bag_namespace``)."""
    prefix = schema.qualified('', namespace)
    if prefix != '/' and any(c.topic.startswith(prefix) for c in connections):
        return namespace
    return '/'


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
