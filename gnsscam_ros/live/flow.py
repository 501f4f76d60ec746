"""Flow control of a replay: which input message may be published when, so that no node
queue overflows at any replay rate.

The nodes take their sensor inputs best effort with bounded queues and drop
the oldest message when a queue overflows. The replay therefore never lets more messages
be in flight than the consumer can hold; a message is *in flight* from its publication
until the node graph acknowledges it on an output topic that it already publishes (no
extra protocol), :data:`FLOW_RULES`:

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
epoch: **no epoch can be dropped**. The filter runs epoch k while the replay already feeds
the IMU of the next interval, so the replay goes as fast as the slowest node.

So that the nodes compute exactly what an offline run of the same data computes:

* the first message of each acknowledged stream goes alone and is acknowledged before the
  next (the dead reckoning starts from whichever source arrives first);
* before a GNSS epoch, every camera image stamped up to it must be acknowledged
  (:data:`GNSS_BARRIER`), then :data:`GNSS_GRACE_S` passes (fusion_node serves
  ``gnss/measurements`` before ``camera/matches`` when both are ready, which would run the
  epoch without the last match).

An acknowledgement that does not come within the timeout is counted as unacknowledged;
after :data:`MAX_TIMEOUTS` in a row on one stream its flow control is switched off with a
warning (e.g. a camera node that never answers).
"""
from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable

from msg_adapters.wire import (DEAD_RECKONING, GNSS, GNSS_MEASUREMENTS, IMAGE, IMU, INTEGRITY,
                               MATCHES, TWIST)

from ..bags import schema
from .summary import ReplaySummary


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
    IMU: FlowRule(DEAD_RECKONING, schema.ODOMETRY, 50, ((DEAD_RECKONING, 2),)),
    TWIST: FlowRule(DEAD_RECKONING, schema.ODOMETRY, 50, ((DEAD_RECKONING, 2),)),
    IMAGE: FlowRule(MATCHES, schema.POINTCLOUD2, 2, ((MATCHES, 2),)),
    GNSS: FlowRule(INTEGRITY, schema.DIAGNOSTIC_ARRAY, 1, ((GNSS_MEASUREMENTS, 1),)),
}
#: Pause before a GNSS epoch whose interval had camera images [s] (see
#: :meth:`FlowControl.admit`).
GNSS_GRACE_S = 0.02
#: Streams that must be acknowledged up to a GNSS epoch's stamp before it is published.
GNSS_BARRIER = (IMAGE,)
#: Consecutive acknowledgement timeouts before a stream's flow control goes off.
MAX_TIMEOUTS = 3


class Stream:
    """Flow-control state of one input topic (guarded by :attr:`FlowControl.cond`)."""

    def __init__(self, topic: str, rule: FlowRule):
        self.topic = topic
        self.rule = rule
        self.pending: deque = deque()      # stamps published, not yet acknowledged
        self.enabled = True
        self.reason = 'on'
        self.timeouts = 0
        self.consecutive_timeouts = 0
        self.wait_s = 0.0


class FlowControl:
    """The acknowledgement state of the flow-controlled streams of one replay.

    Thread-safe: the publishing thread waits in :meth:`admit` and :meth:`drain` while the
    executor thread delivers acknowledgements (:meth:`acknowledge`); :attr:`cond` guards
    the state (the replayer guards its own shared state with it too).

    Args:
        ack_timeout_s: Longest wait for one acknowledgement [s].
        gnss_grace_s: Pause before a GNSS epoch that follows camera images, once their
            matches are acknowledged [s].
        stopped: True when waiting must end (stop requested, context shut down).
        warn: Logs a warning.
    """

    def __init__(self, ack_timeout_s: float, gnss_grace_s: float,
                 stopped: Callable[[], bool], warn: Callable[[str], None]):
        self.cond = threading.Condition()
        self.ack_timeout_s = float(ack_timeout_s)
        self.gnss_grace_s = float(gnss_grace_s)
        self.streams: dict[str, Stream] = {}      # by bag topic
        self.ack_newest: dict[str, int] = {}      # by relative acknowledging topic
        self._matched_since_gnss = False
        self._stopped = stopped
        self._warn = warn

    def control(self, topic: str, rel: str, window: int | None = None) -> bool:
        """Put bag topic ``topic`` (relative name ``rel``) under its rule in
        :data:`FLOW_RULES`, with ``window`` in place of the rule's (None: the rule's).

        Returns:
            False when no rule applies to ``rel``.

        Raises:
            ValueError: A window < 1.
        """
        rule = FLOW_RULES.get(rel)
        if rule is None:
            return False
        window = int(rule.window if window is None else window)
        if window < 1:
            raise ValueError(f'flow-control window of {rel} must be >= 1, got {window}')
        self.streams[topic] = Stream(rel, FlowRule(rule.ack_topic, rule.ack_type, window,
                                                   rule.via))
        return True

    def acknowledge(self, ack_topic: str, stamp_ns: int) -> None:
        """``ack_topic`` answered up to ``stamp_ns``."""
        with self.cond:
            if stamp_ns > self.ack_newest.get(ack_topic, -1):
                self.ack_newest[ack_topic] = stamp_ns
                self.cond.notify_all()

    def settle(self, stream: Stream) -> int:
        """Drop acknowledged stamps from ``stream.pending``; the number left (locked)."""
        newest = self.ack_newest.get(stream.rule.ack_topic, -1)
        while stream.pending and stream.pending[0] <= newest:
            stream.pending.popleft()
        return len(stream.pending)

    def wait(self, stream: Stream, done, what: str) -> None:
        """Wait (locked) until ``done()``; on timeout count the pending messages as lost."""
        if not stream.enabled or done():
            return
        start = time.monotonic()
        deadline = start + self.ack_timeout_s
        while not done():
            if self._stopped():
                break
            now = time.monotonic()
            if now >= deadline:
                lost = len(stream.pending)
                stream.timeouts += lost
                stream.pending.clear()
                stream.consecutive_timeouts += 1
                self._warn(f'{stream.topic}: no {stream.rule.ack_topic} for {what} within '
                           f'{self.ack_timeout_s:g} s; {lost} message(s) unacknowledged')
                if stream.consecutive_timeouts >= MAX_TIMEOUTS:
                    stream.enabled = False
                    stream.reason = (f'off: {MAX_TIMEOUTS} acknowledgement timeouts on '
                                     f'{stream.rule.ack_topic}')
                    self._warn(f'{stream.topic}: flow control {stream.reason}')
                break
            # Short slices: Ctrl-C in the main thread is handled between them.
            self.cond.wait(min(0.05, deadline - now))
        else:
            stream.consecutive_timeouts = 0
        stream.wait_s += time.monotonic() - start

    def admit(self, topic: str, stamp_ns: int) -> float:
        """Block until ``topic``'s message stamped ``stamp_ns`` may be published.

        Returns:
            A pause [s] to make before publishing it (the GNSS grace, else 0).
        """
        stream = self.streams.get(topic)
        if stream is None:
            return 0.0
        with self.cond:
            if stream.topic == GNSS:
                for other in self.streams.values():
                    if other.topic in GNSS_BARRIER:
                        self.wait(other, lambda o=other: self.settle(o) == 0
                                  or o.pending[0] > stamp_ns,
                                  f'the images up to the GNSS epoch at {stamp_ns} ns')
            # The first message of an acknowledging topic goes alone: a node initialises
            # from its first input (the dead reckoning starts from whichever source comes
            # first), and only an acknowledgement makes the processing order the
            # publication order. Afterwards the window applies.
            group = [s for s in self.streams.values()
                     if s.rule.ack_topic == stream.rule.ack_topic and s.enabled]
            if stream.rule.ack_topic not in self.ack_newest:
                for other in group:
                    self.wait(other, lambda o=other: self.settle(o) == 0,
                              f'the first message on {other.topic}')
            self.wait(stream, lambda: self.settle(stream) < stream.rule.window,
                      f'the message at {stream.pending[0] if stream.pending else 0} ns')
            grace = stream.topic == GNSS and self._matched_since_gnss
            if stream.topic == GNSS:
                self._matched_since_gnss = False
        # The replay has the camera matches of the interval, but fusion_node may not have
        # taken them yet: its executor serves ready subscriptions in creation order,
        # gnss/measurements before camera/matches, so an epoch that becomes ready together
        # with a match would run without it. A short pause before the epoch lets the match
        # be taken first (measured: 1 match in ~50 epochs was missed without it on a loaded
        # two-core machine).
        return self.gnss_grace_s if grace and self.gnss_grace_s > 0 else 0.0

    def published(self, topic: str, stamp_ns: int) -> None:
        """``topic``'s message stamped ``stamp_ns`` went out: in flight until answered."""
        stream = self.streams.get(topic)
        if stream is not None and stream.enabled:
            with self.cond:
                stream.pending.append(stamp_ns)
                if stream.topic in GNSS_BARRIER:
                    self._matched_since_gnss = True

    def drain(self) -> None:
        """Wait for the acknowledgements of the last GNSS epochs and images.

        The IMU and odometry streams are not waited for: the dead reckoning only passes a
        stamp once every source has, so the last samples of one source may never be
        acknowledged.
        """
        with self.cond:
            for stream in self.streams.values():
                if stream.topic in (GNSS, IMAGE):
                    self.wait(stream, lambda s=stream: self.settle(s) == 0,
                              'the last messages')

    def report(self, summary: ReplaySummary) -> None:
        """Per stream: unacknowledged messages, flow-control state, time waited (locked)."""
        for stream in self.streams.values():
            self.settle(stream)
            summary.unacknowledged[stream.topic] = stream.timeouts
            summary.flow_control[stream.topic] = stream.reason
            summary.ack_wait_s[stream.topic] = stream.wait_s
