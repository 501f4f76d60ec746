"""``gnsscam_record``: record the nodes' outputs into a rosbag2 bag (MCAP), atomically.

Usage::

    gnsscam_record --out RESULT_BAG [TOPIC ...]

Default topics: :data:`DEFAULT_TOPICS`, the outputs that ``gnsscam_eval bag`` evaluates
(``pose``, ``fix``, ``particles``, ``integrity_risk``), ``odometry/global`` (what ROS
consumers use), plus the replayed ground truth and dataset description
(``ground_truth/pose``, ``map/origin``, ``dataset/info``), so that the result bag is
self-contained. ``map/origin`` then holds two messages: the dataset's origin (replayed
first) and fusion_node's map frame origin (at its first fix, or at start-up when it is
given ``map_origin_llh``: then the same origin); the evaluation takes the last one, the
frame of ``pose``. Further topics are given by name; their type is taken from the ROS
graph once a publisher appears, or given as ``name:pkg/msg/Type``.

Messages are received serialised (``raw=True`` subscriptions) and written as they came:
no decoding on the way. The bag time of each message is its reception time (node clock),
as ``ros2 bag record`` does; the evaluation reads the header stamps. Subscriptions are
reliable with deep queues (``transient_local`` for the once-only topics ``map/origin`` and
``dataset/info``, so a recorder started after the replay still gets them).

**Atomic**: the bag is written into a hidden sibling folder (``.NAME.partial-*``) and
renamed to ``RESULT_BAG`` when recording stops cleanly (:meth:`BagRecorder.close`, or
Ctrl-C / SIGTERM in the CLI). An existing ``RESULT_BAG`` is never overwritten; after an
error the partial folder is removed (:meth:`BagRecorder.abort`).

Exit codes of the CLI: 0 recorded (Ctrl-C is the normal way to stop), 2 bad usage (also
a ``name:pkg/msg/Type`` with a type nobody knows, malformed ``--ros-args``), 4 output
exists or cannot be written (a read-only folder, a parent that is a file, a write error
while recording: the message names the path; no bag is left behind).

A recorder killed by SIGKILL leaves its ``.NAME.partial-HOST-PID-*`` folder; the next
``gnsscam_record`` (or ``gnsscam_convert``) writing into that folder removes it when its
writer provably no longer runs, else reports it with the command that removes it
(:mod:`..io.partials`).

On a ROS 2 machine the equivalent is ``ros2 bag record -o RESULT_BAG /pose /fix
/particles /integrity_risk /odometry/global /ground_truth/pose /map/origin``.
"""
from __future__ import annotations

import argparse
import math
import os
import shutil
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosbags.rosbag2 import Writer

from msg_adapters.wire import (INFO, ODOMETRY_GLOBAL, ORIGIN, RECORD_DEPTH,
                               RESULT_BAG_TOPICS, TOPICS, TRUTH)

from ..bags import schema
from ..bags.convert import STORAGES
from ..bags.errors import BagError, BagExistsError, BagTypeError
from ..io.partials import make_partial_dir, sweep_and_report
from .endpoints import NO_SUB_EVENTS, ros_message_class

EXIT_OK, EXIT_USAGE, EXIT_OUTPUT = 0, 2, 4

#: Topics recorded by default, with their types and whether they are once-only (latched),
#: from the topic registry (``msg_adapters.wire.TOPICS``).
DEFAULT_TOPICS: dict[str, tuple[str, bool]] = {
    name: (TOPICS[name].msgtype, TOPICS[name].latched)
    for name in (*RESULT_BAG_TOPICS, ODOMETRY_GLOBAL, TRUTH, ORIGIN, INFO)}


@dataclass
class RecordSummary:
    """What a recorder wrote.

    Attributes:
        path: The bag (final name once closed).
        counts: Messages per qualified topic.
        seconds: Recording time [s].
        bag_bytes: Size on disk [bytes] (after closing).
        pending_topics: Requested topics whose type never became known (not recorded).
    """

    path: Path
    counts: dict[str, int] = field(default_factory=dict)
    seconds: float = 0.0
    bag_bytes: int = 0
    pending_topics: list[str] = field(default_factory=list)

    def as_dict(self) -> dict:
        """JSON-able form."""
        return {'path': str(self.path), 'counts': self.counts, 'seconds': self.seconds,
                'bag_bytes': self.bag_bytes, 'pending_topics': self.pending_topics}


def parse_topic(spec: str) -> tuple[str, str | None]:
    """``'name'`` or ``'name:pkg/msg/Type'`` -> ``(name, type or None)``."""
    if ':' in spec:
        name, msgtype = spec.split(':', 1)
        return name, msgtype
    return spec, DEFAULT_TOPICS.get(spec.lstrip('/'), (None, False))[0]


class BagRecorder(Node):
    """Records topics into a new bag; spin it with any executor, then :meth:`close`.

    Args:
        out: Bag folder to create (must not exist).
        topics: Topic names (relative or qualified; ``name:pkg/msg/Type`` to give the
            type); default :data:`DEFAULT_TOPICS`.
        storage: ``'mcap'`` (default) or ``'sqlite3'``.
        strip_namespace: Write the topics without the node's namespace (``/ns/pose`` is
            stored as ``/pose``), e.g. for nodes run under a private namespace.
        node_name: Node name.
        **kwargs: Forwarded to ``rclpy.node.Node``.

    Raises:
        BagExistsError: ``out`` exists.
        BagTypeError: A given type is unknown to the typestore or to rclpy.
        BagError: The writer could not be opened.
        ValueError: Unknown storage.
    """

    def __init__(self, out: str | Path, topics: list[str] | None = None,
                 storage: str = 'mcap', strip_namespace: bool = False,
                 node_name: str = 'gnsscam_record', **kwargs):
        if storage not in STORAGES:
            raise ValueError(f'unknown storage {storage!r}; use one of {sorted(STORAGES)}')
        self.out = Path(out)
        if self.out.exists() or self.out.is_symlink():
            raise BagExistsError(f'{self.out} exists; not overwriting', path=self.out)
        specs = [parse_topic(t) for t in (topics or list(DEFAULT_TOPICS))]
        store = schema.typestore()
        for name, msgtype in specs:
            if msgtype is not None:
                if msgtype not in store.types:
                    raise BagTypeError(f'{name}: message type {msgtype} unknown to the '
                                       'typestore', topic=name)
                ros_message_class(msgtype)
        # The partial folder first: an output that cannot be written is refused before
        # the node joins the graph. Its name holds this host and pid, so that a later run
        # can tell the leftover of a killed recorder from a running one (io.partials).
        try:
            self.out.parent.mkdir(parents=True, exist_ok=True)
            self._tmp = make_partial_dir(self.out)
        except OSError as err:
            raise BagError(f'{self.out}: cannot write here: {err.strerror or err}',
                           path=self.out) from err
        self._lock = threading.Lock()
        self._writer = None
        self._connections: dict[str, object] = {}
        self.summary = RecordSummary(path=self.out)
        self._started = time.monotonic()
        self._closed = False
        #: The first write error (disk full, I/O error): recording stopped, see main().
        self.failure: BagError | None = None
        try:
            # Woken for every message: no parameter services or QoS event handlers, whose
            # entities rclpy walks at each wake (the recorder has no ROS parameters).
            kwargs.setdefault('start_parameter_services', False)
            super().__init__(node_name, **kwargs)
        except BaseException:
            shutil.rmtree(self._tmp, ignore_errors=True)
            raise
        try:
            # rosbags wants a folder that does not exist yet: write inside the temp dir.
            self._writer = Writer(self._tmp / 'bag', version=9,
                                  storage_plugin=STORAGES[storage])
            self._writer.open()
        except Exception as err:
            shutil.rmtree(self._tmp, ignore_errors=True)
            self.destroy_node()
            raise BagError(f'{self.out}: cannot open the bag writer: {err}',
                           path=self.out) from err
        self._strip = strip_namespace
        self._waiting: dict[str, None] = {}
        for name, msgtype in specs:
            topic = self.resolve_topic_name(name)
            if msgtype is None:
                self._waiting[topic] = None
            else:
                self._subscribe(topic, msgtype)
        if self._waiting:
            self._type_timer = self.create_timer(0.2, self._resolve_types)

    def bag_name(self, topic: str) -> str:
        """The name a resolved topic is written under."""
        ns = self.get_namespace().rstrip('/')
        if self._strip and ns and topic.startswith(ns + '/'):
            return topic[len(ns):]
        return topic

    def _subscribe(self, topic: str, msgtype: str) -> None:
        name = self.bag_name(topic)
        rel = schema.relative(name) or name
        # Latching and queue depth of the registry's topics; a topic outside the graph
        # (given by name and type) is recorded as a volatile stream.
        known = TOPICS.get(rel)
        latched = known is not None and known.latched
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST,
                         depth=RECORD_DEPTH if known is None else known.record_depth,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=(DurabilityPolicy.TRANSIENT_LOCAL if latched
                                     else DurabilityPolicy.VOLATILE))
        with self._lock:
            self._connections[topic] = self._writer.add_connection(
                name, msgtype, typestore=schema.typestore(),
                offered_qos_profiles=[schema.qos(latched)])
            self.summary.counts[name] = 0
        self.create_subscription(ros_message_class(msgtype), topic, self._writer_of(topic),
                                 qos, raw=True, event_callbacks=NO_SUB_EVENTS)

    def _resolve_types(self) -> None:
        """Subscribe to topics given without a type once the graph knows their type."""
        known = dict(self.get_topic_names_and_types())
        for topic in list(self._waiting):
            types = known.get(topic) or []
            if types and types[0] in schema.typestore().types:
                del self._waiting[topic]
                self._subscribe(topic, types[0])
        if not self._waiting:
            self._type_timer.cancel()

    def _writer_of(self, topic: str):
        name = self.bag_name(topic)

        def callback(data: bytes) -> None:
            now = self.get_clock().now().nanoseconds
            with self._lock:
                if self._closed or self.failure is not None:
                    return
                try:
                    self._writer.write(self._connections[topic], now, data)
                except Exception as err:   # disk full, I/O error: stop, main() says so
                    self.failure = BagError(f'{self.out}: writing failed: '
                                            f'{type(err).__name__}: {err}', path=self.out)
                    return
                self.summary.counts[name] += 1
        return callback

    def count(self, name: str) -> int:
        """Messages recorded so far on a topic (relative or qualified name)."""
        with self._lock:
            return self.summary.counts.get(self.bag_name(self.resolve_topic_name(name)), 0)

    def close(self) -> RecordSummary:
        """Stop recording, finish the bag and move it into place.

        Returns:
            What was written.

        Raises:
            BagExistsError: ``out`` appeared meanwhile (the bag stays in the temp folder,
                whose name is in the message).
            BagError: Finishing the bag failed (the partial folder is removed).
        """
        with self._lock:
            if self._closed:
                return self.summary
            self._closed = True
            try:
                self._writer.close()
            except Exception as err:
                shutil.rmtree(self._tmp, ignore_errors=True)
                raise BagError(f'{self.out}: finishing the bag failed: {err}',
                               path=self.out) from err
        self.summary.seconds = time.monotonic() - self._started
        self.summary.pending_topics = sorted(self._waiting)
        if self.out.exists() or self.out.is_symlink():
            # Keep the recording under a name of its own: left in the partial folder, the
            # next run would remove it as the leftover of a dead writer.
            kept = self.out.with_name(f'{self.out.name}.{os.getpid()}')
            where = self._tmp / 'bag'
            if not (kept.exists() or kept.is_symlink()):
                try:
                    where.rename(kept)
                    where = kept
                    shutil.rmtree(self._tmp, ignore_errors=True)
                except OSError:
                    pass
            raise BagExistsError(f'{self.out} appeared while recording; the bag is kept '
                                 f'in {where}', path=self.out)
        try:
            (self._tmp / 'bag').rename(self.out)
        except OSError as err:
            shutil.rmtree(self._tmp, ignore_errors=True)
            raise BagError(f'{self.out}: cannot move the bag into place: '
                           f'{err.strerror or err}', path=self.out) from err
        shutil.rmtree(self._tmp, ignore_errors=True)
        self.summary.bag_bytes = sum(p.stat().st_size for p in self.out.rglob('*')
                                     if p.is_file())
        return self.summary

    def abort(self) -> None:
        """Stop recording and remove the partial bag (after an error)."""
        with self._lock:
            if not self._closed:
                self._closed = True
                try:
                    self._writer.close()
                except Exception:
                    pass
        shutil.rmtree(self._tmp, ignore_errors=True)


def _terminate(signum, frame):
    # SIGTERM stops like Ctrl-C: the bag is finished and kept.
    raise KeyboardInterrupt(f'signal {signum}')


def main(argv: list[str] | None = None) -> int:
    """``gnsscam_record``; returns the exit code (see the module docstring)."""
    args_all = sys.argv[1:] if argv is None else list(argv)
    ros_at = args_all.index('--ros-args') if '--ros-args' in args_all else len(args_all)
    parser = argparse.ArgumentParser(
        prog='gnsscam_record', description='Record the gnsscam_ros outputs (and replayed '
        'ground truth) into a new rosbag2 bag; Ctrl-C stops and keeps the bag.')
    parser.add_argument('topics', nargs='*', metavar='TOPIC',
                        help='topics (name or name:pkg/msg/Type); default: '
                        + ' '.join(DEFAULT_TOPICS))
    parser.add_argument('--out', '-o', type=Path, required=True,
                        help='bag folder to create (must not exist)')
    parser.add_argument('--storage', choices=sorted(STORAGES), default='mcap')
    parser.add_argument('--duration', type=float, default=None, metavar='SECONDS',
                        help='stop after this long (default: until Ctrl-C)')
    args = parser.parse_args(args_all[:ros_at])
    try:
        exists = args.out.exists() or args.out.is_symlink()
    except OSError as err:              # a name the file system refuses (too long, ...)
        print(f'gnsscam_record: cannot write {args.out}: {err.strerror}', file=sys.stderr)
        return EXIT_OUTPUT
    if exists:
        print(f'gnsscam_record: {args.out} exists; not overwriting', file=sys.stderr)
        return EXIT_OUTPUT
    if args.duration is not None and not (args.duration >= 0 and math.isfinite(args.duration)):
        print(f'gnsscam_record: --duration must be finite and >= 0, got {args.duration}',
              file=sys.stderr)
        return EXIT_USAGE
    # The hidden partial bags of killed recordings or conversions beside the output:
    # removed when provably stale, else reported with the command that removes them.
    sweep_and_report(args.out, 'gnsscam_record')
    try:
        rclpy.init(args=['gnsscam_record'] + args_all[ros_at:])
    except Exception as err:            # malformed --ros-args (rcl's own message)
        print(f'gnsscam_record: bad ROS arguments: {str(err).splitlines()[0]}',
              file=sys.stderr)
        return EXIT_USAGE
    previous = signal.signal(signal.SIGTERM, _terminate)
    node = None
    code = EXIT_OK
    try:
        node = BagRecorder(args.out, topics=args.topics or None, storage=args.storage)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        deadline = None if args.duration is None else time.monotonic() + args.duration
        while (rclpy.ok() and node.failure is None
               and (deadline is None or time.monotonic() < deadline)):
            try:
                executor.spin_once(timeout_sec=0.1)
            except (KeyboardInterrupt, ExternalShutdownException):
                raise
            except Exception:
                if rclpy.ok():
                    raise
                break       # Ctrl-C invalidated the context during the wait: a normal stop
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (BagError, ValueError) as err:
        print(f'gnsscam_record: {err}', file=sys.stderr)
        # A type named on the command line that nobody knows is a usage error.
        code = (EXIT_OUTPUT if isinstance(err, BagError)
                and not isinstance(err, BagTypeError) else EXIT_USAGE)
    finally:
        signal.signal(signal.SIGTERM, previous)
    if node is not None:
        if node.failure is not None:
            print(f'gnsscam_record: {node.failure}; no bag written', file=sys.stderr)
            node.abort()
            code = EXIT_OUTPUT
        else:
            try:
                summary = node.close()
                print(f'gnsscam_record: wrote {summary.path}: '
                      + ', '.join(f'{k} {v}' for k, v in summary.counts.items()))
            except BagError as err:
                print(f'gnsscam_record: {err}', file=sys.stderr)
                code = EXIT_OUTPUT
        node.destroy_node()
    rclpy.try_shutdown()
    return code


if __name__ == '__main__':
    sys.exit(main())
