"""What every gnsscam_ros node shares: parameter declaration with descriptors and
validation, rejection/drop counters, processing-time statistics and the ``diagnostics``
report, QoS profiles, and the Jazzy ``main()``."""
from __future__ import annotations

import math
import sys
import threading
import time
from collections import deque
from contextlib import contextmanager
from typing import Callable

import numpy as np
import rclpy
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from diagnostic_msgs.msg import DiagnosticArray
from msg_adapters import OK, WARN, make_diagnostic_array, make_status

# Float ranges need finite ends; this stands for "no upper limit".
BIG = 1e12


def sensor_qos(depth: int) -> QoSProfile:
    """Inputs from sensors: best effort, keep the newest ``depth`` (a late sample is
    worth less than the next one)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=int(depth),
                      reliability=ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.VOLATILE)


def reliable_qos(depth: int = 10) -> QoSProfile:
    """Outputs and node-to-node streams: reliable, keep the newest ``depth``."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=int(depth),
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


#: Topics every node has (not links of the gnsscam_ros graph).
_INFRASTRUCTURE_TOPICS = frozenset({'diagnostics', 'rosout', 'parameter_events',
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


class GnssCamNode(Node):
    """Base of the gnsscam_ros nodes.

    Declares ``diagnostics_period_s``, publishes ``diagnostics`` periodically with the
    node's counters (subclasses add their own state through :meth:`diagnostic_summary`),
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
        self._validators: dict[str, Callable] = {}
        self._all_declared = False
        self._diag_pub = self.create_publisher(DiagnosticArray, 'diagnostics', reliable_qos())
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._post_set_parameters)
        self.declare('diagnostics_period_s', 1.0, 'Period of the diagnostics report [s].',
                     (0.05, 3600.0), read_only=True)
        self._diag_timer = self.create_timer(self.param('diagnostics_period_s'),
                                             self.publish_diagnostics)

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

        Returns:
            The value in force (default or override).

        Raises:
            ValueError: The start-up value is refused by ``validator``.
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
        self.declare_parameter(name, default, desc)
        if validator is not None:
            self._validators[name] = validator
            reason = validator(self.param(name))
            if reason:
                raise ValueError(f'{self.get_name()}: parameter {name}: {reason}')
        return self.param(name)

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

    def publish_diagnostics(self) -> None:
        level, message, extra = self.diagnostic_summary()
        values = {**self.stats.values(), **self.link_counts(), **extra}
        status = make_status(f'{self.get_name()}: status', level, message, values,
                             hardware_id='gnsscam_ros')
        self._diag_pub.publish(make_diagnostic_array(self.now_ns(), [status]))

    def now_ns(self) -> int:
        """Node clock time [ns] (ROS time; simulated time when ``use_sim_time``)."""
        return int(self.get_clock().now().nanoseconds)

    def warn_rejected(self, topic: str, reason: str, detail: str) -> None:
        """Count a refused input message and log it (throttled)."""
        self.stats.reject(reason)
        self.get_logger().warning(f'{topic}: rejected ({reason}): {detail}',
                                  throttle_duration_sec=5.0)


def level_worst(*levels: int) -> int:
    """The most severe of diagnostic levels (OK < WARN < ERROR < STALE)."""
    return max(levels) if levels else OK


__all__ = ['BIG', 'GnssCamNode', 'NodeStats', 'OK', 'WARN', 'level_worst', 'reliable_qos',
           'run_node', 'sensor_qos', 'NodeSpinner', 'stop_process', 'wants_help',
           'print_node_help']


def wants_help(args=None) -> bool:
    """True when ``-h`` or ``--help`` is given before any ``--ros-args`` (``args`` as
    ``rclpy.init`` takes them; None: ``sys.argv``)."""
    argv = list(sys.argv[1:] if args is None else args)
    if '--ros-args' in argv:
        argv = argv[:argv.index('--ros-args')]
    return any(a in ('-h', '--help') for a in argv)


def print_node_help(executable: str, doc: str | None, configs: tuple[str, ...]) -> None:
    """Usage of a node executable: how to pass ROS arguments, what it does, its configs."""
    files = ' '.join(f'--params-file config/{c}.yaml' for c in configs)
    print(f'usage: {executable} [--ros-args [--params-file FILE] [-p NAME:=VALUE] '
          '[-r FROM:=TO] ...]\n')
    print((doc or '').strip())
    print('\nParameters (meaning, unit, default, range) are documented in '
          + ', '.join(f'config/{c}.yaml' for c in configs)
          + ' (installed under share/gnsscam_ros/config).')
    print(f'Example: {executable} --ros-args {files}')


def run_node(node_class, args=None) -> None:
    """The Jazzy ``main()`` of a single-node executable (ros2/demos talker pattern).

    ``-h``/``--help`` (before ``--ros-args``) prints the usage and returns.
    """
    if wants_help(args):
        name = node_class.__module__.rsplit('.', 1)[-1]
        print_node_help(name, sys.modules[node_class.__module__].__doc__, (name,))
        return
    rclpy.init(args=args)
    node = None
    try:
        node = node_class()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


class NodeSpinner:
    """Each node on its own single-threaded executor and thread.

    Several nodes in one process (pipeline_node, in-process replays) are served this way
    rather than by rclpy's ``MultiThreadedExecutor``: in Jazzy that executor re-queues
    callbacks that are submitted but not yet running and wakes up again at once, a busy
    loop that kept a whole core at 100 % and slowed every node (ros2/rclpy#1452; measured
    here: pipeline_node replayed a bag at 1.15x real time, separate processes at 14x). A
    single-threaded executor per node also keeps each node's callbacks serialised, as in
    its own process. A node whose callback raises stops the whole group (the error is
    logged and the context shut down), as its own process would exit.

    The threads spin in short slices and check a stop flag, so that :meth:`stop` joins
    them *before* it shuts the executors down: an executor torn down while its thread is
    still waiting on it can crash the process.
    """

    SLICE_S = 0.1

    def __init__(self, nodes: list, context=None):
        self.context = context
        self._stop = threading.Event()
        self._pairs = []
        for node in nodes:
            executor = SingleThreadedExecutor(context=context)
            executor.add_node(node)
            thread = threading.Thread(target=self._spin, args=(executor, node), daemon=True,
                                      name=f'spin_{node.get_name()}')
            thread.start()
            self._pairs.append((executor, thread))

    def _ok(self) -> bool:
        return self.context.ok() if self.context is not None else rclpy.ok()

    def _spin(self, executor, node) -> None:
        try:
            while not self._stop.is_set() and self._ok():
                executor.spin_once(timeout_sec=self.SLICE_S)
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        except Exception as err:    # noqa: BLE001 - a node failed: stop the group, loudly
            if self._ok():
                node.get_logger().fatal(f'{type(err).__name__}: {err}; shutting down')
                rclpy.try_shutdown(context=self.context)

    def running(self) -> bool:
        """True while every thread spins and the context is up."""
        return self._ok() and all(t.is_alive() for _, t in self._pairs)

    def wait(self) -> None:
        """Block until Ctrl-C, shutdown or a failed node."""
        while self.running():
            time.sleep(self.SLICE_S)

    def stop(self) -> None:
        """Stop the threads, then shut their executors down."""
        self._stop.set()
        for _, thread in self._pairs:
            thread.join(timeout=10 * self.SLICE_S + 5.0)
        for executor, _ in self._pairs:
            executor.shutdown(timeout_sec=1.0)


def stop_process(proc, timeout_s: float = 20.0) -> int:
    """Stop a node's child process as Ctrl-C does (SIGINT), SIGKILL after ``timeout_s``;
    its exit status."""
    import signal
    import subprocess
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        return proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.wait()
