"""The ROS side of the campaigns: node processes, the probe node, the nodes' counters.

* :class:`NodeProcess`: one node executable (or pipeline_node) as a child process in its
  own ROS domain (``ROS_DOMAIN_ID``, ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``,
  ``OPENBLAS_NUM_THREADS=1``), its stderr in a file, its resident memory from
  ``/proc/<pid>/status`` (VmRSS);
* :class:`Probe`: a node in this process that publishes the valid stream and the faults
  on every input topic (messages, or raw CDR bytes) and listens to ``integrity_risk``,
  ``fix`` and ``diagnostics``;
* :class:`Counters`: the newest ``diagnostics`` values of each node, parsed to numbers,
  with the sums the accounting needs (received per input link, rejected, drops).
"""
from __future__ import annotations

import math
import os
import re
import resource
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TwistWithCovarianceStamped
from nav_msgs.msg import Odometry
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image, Imu, NavSatFix, PointCloud2

import msg_adapters as ma
from gnsscam_ros.live.launch import write_params_file
from gnsscam_ros.nodes.runtime import stop_process
from msg_adapters import wire

NODE_NAMES = ('gnss_node', 'imu_node', 'camera_node', 'fusion_node')
TOPIC_TYPES = {wire.GNSS: PointCloud2, wire.GNSS_MEASUREMENTS: PointCloud2,
               wire.IMU: Imu, wire.TWIST: TwistWithCovarianceStamped, wire.IMAGE: Image,
               wire.DEAD_RECKONING: Odometry, wire.MATCHES: PointCloud2}

#: Input link -> (node that takes it, its ``received_*`` counter, the node that publishes
#: it in the graph and that node's ``published_*`` counter, or None for a sensor input).
LINKS = {
    wire.GNSS: ('gnss_node', 'received_pseudoranges', None, None),
    wire.IMU: ('imu_node', 'received_imu', None, None),
    wire.TWIST: ('imu_node', 'received_odom_twist', None, None),
    wire.IMAGE: ('camera_node', 'received_images', None, None),
    wire.GNSS_MEASUREMENTS: ('fusion_node', 'received_measurements', 'gnss_node',
                             'published_measurements'),
    wire.DEAD_RECKONING: ('fusion_node', 'received_dead_reckoning', 'imu_node',
                          'published_dead_reckoning'),
    wire.MATCHES: ('fusion_node', 'received_matches', 'camera_node', 'published_matches'),
}
#: Counters that count messages a node lost or dropped (queue overflows, undecodable
#: messages, QoS events): such a loss is counted, not silent. Matched by name.
LOSS_COUNTER = re.compile(r'(^|_)(dropped|lost|overflow|undecodable|discarded)(_|$)')
#: Counters of messages a node received and then did not use, saying so, other than
#: rejections: camera_node's full matcher queue drops its oldest frame, fusion_node's
#: engine drops its oldest queued epoch or refuses an input its own checks find wrong.
DROP_COUNTERS = {wire.IMAGE: ('dropped_frames',),
                 wire.GNSS_MEASUREMENTS: ('dropped_epochs', 'refused_gnss'),
                 wire.DEAD_RECKONING: ('refused_dead_reckoning',),
                 wire.MATCHES: ('refused_camera',)}
SATELLITE_COUNTER = re.compile(r'^satellites_rejected_')
#: How long a node's ``received_*`` counts must stay still before what it has not
#: received counts as lost [s] (a few of the kits' 0.05 s diagnostics periods: a
#: best-effort message can reach a reader late on a loaded machine).
DRAINED_QUIET_S = 0.5

RELIABLE = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                      reliability=ReliabilityPolicy.RELIABLE)


def _received_counts(values: dict[str, float]) -> dict[str, float]:
    return {k: v for k, v in values.items() if k.startswith('received_')}


def rss_mb(pid: int) -> float:
    """Resident memory of a process [MB] (VmRSS of /proc; NaN once it is gone)."""
    try:
        for line in Path(f'/proc/{pid}/status').read_text().splitlines():
            if line.startswith('VmRSS:'):
                return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return math.nan


def node_env(domain: int, log_dir: Path) -> dict:
    """Environment of a node process on ``domain``."""
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               ROS_LOG_DIR=str(log_dir / 'ros_log'), OPENBLAS_NUM_THREADS='1',
               PYTHONUNBUFFERED='1')
    return env


class NodeProcess:
    """A node executable (``module`` of ``gnsscam_ros.nodes``) as a child process.

    The machine is shared: a fault that makes a node allocate without bound must not take
    it down. The child's address space is capped (``RLIMIT_AS``: ``memory_limit_mb`` plus
    the ~2 GB a node reserves without using), so a huge allocation fails inside it, and a
    watchdog thread kills it (SIGKILL) when its resident memory passes
    ``memory_limit_mb``; both end as a crash of the node, the second one marked
    :attr:`killed_for_memory`. The watchdog also keeps the peak RSS.

    Args:
        module: ``pipeline``, ``gnss_node``, ``imu_node``, ``camera_node``, ``fusion_node``.
        params_file: Its ``--params-file``.
        domain: ROS domain id.
        log_dir: Folder for its stderr (``<module>-<n>.stderr.txt``) and ROS logs.
        memory_limit_mb: Resident memory at which the kit kills it [MB].
    """

    def __init__(self, module: str, params_file: Path, domain: int, log_dir: Path,
                 memory_limit_mb: float = 4096.0):
        self.module = module
        self.log_dir = Path(log_dir)
        self.params_file = params_file
        self.domain = domain
        self.memory_limit_mb = float(memory_limit_mb)
        self.starts = 0
        self.proc: subprocess.Popen | None = None
        self.stderr_path: Path | None = None
        self.started_at = math.nan
        self.peak_rss_mb = 0.0
        self.killed_for_memory = False
        self._watch_stop = threading.Event()

    def _limit(self) -> None:
        cap = int((self.memory_limit_mb + 2560.0) * 2**20)
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))

    def _watch(self, proc: subprocess.Popen, stop: threading.Event) -> None:
        while not stop.is_set() and proc.poll() is None:
            rss = rss_mb(proc.pid)
            if math.isfinite(rss):
                self.peak_rss_mb = max(self.peak_rss_mb, rss)
                if rss > self.memory_limit_mb:
                    self.killed_for_memory = True
                    proc.send_signal(signal.SIGKILL)
                    return
            stop.wait(0.05)

    def start(self) -> 'NodeProcess':
        self.starts += 1
        self.killed_for_memory = False
        self.stderr_path = self.log_dir / f'{self.module}-{self.starts}.stderr.txt'
        with self.stderr_path.open('w') as err:
            self.proc = subprocess.Popen(
                [sys.executable, '-m', f'gnsscam_ros.nodes.{self.module}', '--ros-args',
                 '--params-file', str(self.params_file)],
                env=node_env(self.domain, self.log_dir), stdout=subprocess.DEVNULL,
                stderr=err, preexec_fn=self._limit)
        self.started_at = time.monotonic()
        self._watch_stop.set()
        self._watch_stop = threading.Event()
        threading.Thread(target=self._watch, args=(self.proc, self._watch_stop),
                         daemon=True, name=f'watch_{self.module}').start()
        return self

    @property
    def pid(self) -> int:
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def exit_code(self) -> int | None:
        return None if self.proc is None else self.proc.poll()

    def rss_mb(self) -> float:
        return rss_mb(self.proc.pid) if self.alive() else math.nan

    def kill(self) -> int:
        """SIGKILL; the exit status."""
        self.proc.send_signal(signal.SIGKILL)
        return self.proc.wait()

    def stop(self) -> int | None:
        """Ctrl-C as a user stops it (SIGKILL after 20 s); the exit status."""
        return None if self.proc is None else stop_process(self.proc, 20.0)

    def failure(self, lines: int = 3) -> str:
        """The last error lines of its stderr (the cause of a crash)."""
        if self.killed_for_memory:
            return (f'killed by the fault-injection kit: resident memory above '
                    f'{self.memory_limit_mb:.0f} MB (peak {self.peak_rss_mb:.0f} MB)')
        try:
            text = self.stderr_path.read_text(errors='replace').splitlines()
        except OSError:
            return ''
        keep = [t.strip() for t in text if re.search(
            r'(Error|Exception|FATAL|fatal|Traceback|Killed)', t)]
        return ' | '.join(keep[-lines:])[-400:]


def write_params(path: Path, params: dict[str, dict]) -> Path:
    """The ``--params-file`` of the nodes (``{node: {name: value}}``)."""
    return write_params_file(path, params)


@dataclass
class Verdict:
    """One ``integrity_risk`` message as the probe received it."""

    received_s: float
    level: int
    epoch_stamp_ns: int | None
    epoch_status: str | None
    protection_level_m: float | None
    message: str
    motion_unknown_s: float = 0.0


class Counters:
    """The newest ``diagnostics`` values of each node (numbers where they parse).

    Updated from the probe's callback thread; every reading works on a copy.
    """

    def __init__(self):
        self._lock = threading.Lock()
        self._values: dict[str, dict[str, float]] = {}
        self._previous: dict[str, dict[str, float]] = {}
        self._stamps: dict[str, tuple[int, int]] = {}
        #: Stamp of the node's first report with its current ``received_*`` counts.
        self._counts_since: dict[str, int] = {}
        self.seq: dict[str, int] = {}

    def update(self, msg: DiagnosticArray) -> None:
        stamp = ma.stamp_to_ns(msg.header.stamp)
        for status in msg.status:
            node, _, what = status.name.partition(': ')
            if what != 'status' or node not in NODE_NAMES:
                continue
            parsed = {}
            for key, value in ma.status_values(status).items():
                try:
                    parsed[key] = float(value)
                except ValueError:
                    continue
            with self._lock:
                previous = self._values.get(node, {})
                if _received_counts(parsed) != _received_counts(previous):
                    self._counts_since[node] = stamp
                self._previous[node] = previous
                self._values[node] = parsed
                self._stamps[node] = (self._stamps.get(node, (0, 0))[1], stamp)
                self.seq[node] = self.seq.get(node, 0) + 1

    @property
    def values(self) -> dict[str, dict[str, float]]:
        with self._lock:
            return dict(self._values)

    def reset(self, nodes=NODE_NAMES) -> None:
        """Forget restarted nodes' counters (they start again at 0)."""
        with self._lock:
            for node in nodes:
                self._values.pop(node, None)
                self._previous.pop(node, None)
                self._stamps.pop(node, None)
                self._counts_since.pop(node, None)

    def reported_since(self, node: str, wall_ns: int) -> bool:
        """The node's last two reports were made after ``wall_ns`` (its clock is this
        machine's: the header stamp is when it counted)."""
        with self._lock:
            older, newer = self._stamps.get(node, (0, 0))
        return older > wall_ns and newer > wall_ns

    def drained(self, node: str, quiet_s: float = DRAINED_QUIET_S) -> bool:
        """The node's reports show the same ``received_*`` counts for ``quiet_s`` (its
        clock) and, for camera_node, nothing waiting for the matcher: it has taken every
        message that was waiting for it. (A node's executor serves every ready
        subscription between two runs of its diagnostics timer, but a best-effort
        message can reach the reader a while after it was published when the machine
        is loaded: two reports one period apart are not enough to call it lost.)"""
        with self._lock:
            new, old = self._values.get(node), self._previous.get(node)
            since = self._counts_since.get(node)
            newest = self._stamps.get(node, (0, 0))[1]
        if not new or old is None or since is None:
            return False
        return (newest - since >= quiet_s * 1e9 and new.get('queue_length', 0.0) == 0.0)

    def reading(self) -> 'Reading':
        """The figures of one copy of the newest reports (a report arriving meanwhile
        cannot mix its counts with an older one's)."""
        return Reading(self.values)

    def get(self, node: str, key: str) -> float:
        return self.reading().get(node, key)

    def has(self, node: str, key: str) -> bool:
        return self.reading().has(node, key)

    def received(self, topic: str) -> float:
        return self.reading().received(topic)

    def upstream(self, topic: str) -> float:
        return self.reading().upstream(topic)

    def snapshot(self) -> dict:
        return self.reading().snapshot()


class Reading:
    """Figures from one set of reports (``Counters.values``)."""

    def __init__(self, values: dict[str, dict[str, float]]):
        self.values = values

    def get(self, node: str, key: str) -> float:
        return self.values.get(node, {}).get(key, 0.0)

    def has(self, node: str, key: str) -> bool:
        return key in self.values.get(node, {})

    def received(self, topic: str) -> float:
        node, key, _, _ = LINKS[topic]
        return self.get(node, key)

    def upstream(self, topic: str) -> float:
        """Messages the graph's own publisher of a link sent on it."""
        _, _, node, key = LINKS[topic]
        return 0.0 if node is None else self.get(node, key)

    def rejected(self) -> float:
        return sum(v.get('rejected_total', 0.0) for v in self.values.values())

    def rejected_by_reason(self) -> dict[str, float]:
        out: dict[str, float] = {}
        for node, vals in self.values.items():
            for key, value in vals.items():
                if key.startswith('rejected_') and key != 'rejected_total':
                    out[f'{node}.{key[9:]}'] = value
        return out

    def losses(self) -> float:
        """Messages the nodes say they lost or dropped (any counter named so)."""
        return sum(value for vals in self.values.values() for key, value in vals.items()
                   if LOSS_COUNTER.search(key))

    def lost(self, topic: str) -> float:
        """Messages of ``topic`` its taking node counted as lost before its callback
        (``lost_<topic>``; ``qos_message_lost_<topic>`` counts the same losses when the
        middleware reports them: the larger of the two)."""
        node = LINKS[topic][0]
        return max(self.get(node, f'lost_{topic}'), self.get(node, f'qos_message_lost_{topic}'))

    def dropped(self, topic: str) -> float:
        """Messages of ``topic`` received and then dropped or refused by counters other
        than the rejections (:data:`DROP_COUNTERS`)."""
        node = LINKS[topic][0]
        return sum(self.get(node, key) for key in DROP_COUNTERS.get(topic, ()))

    def satellites_dropped(self) -> float:
        return sum(value for vals in self.values.values() for key, value in vals.items()
                   if SATELLITE_COUNTER.search(key))

    def snapshot(self) -> dict:
        return {'rejected': self.rejected(), 'losses': self.losses(),
                'satellites': self.satellites_dropped(),
                'received': {t: self.received(t) for t in LINKS},
                'lost': {t: self.lost(t) for t in LINKS},
                'dropped': {t: self.dropped(t) for t in LINKS},
                'upstream': {t: self.upstream(t) for t in LINKS},
                'by_reason': self.rejected_by_reason()}


class Probe:
    """The campaigns' own node: publishers on every input topic, listeners on the outputs.

    Args:
        domain: ROS domain id (the nodes' one).
        name: Node name.
    """

    def __init__(self, domain: int, name: str = 'fuzz_probe'):
        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=domain)
        self.node = rclpy.create_node(name, context=self.ctx)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.pubs = {topic: self.node.create_publisher(cls, topic, RELIABLE)
                     for topic, cls in TOPIC_TYPES.items()}
        self.counters = Counters()
        self.verdicts: list[Verdict] = []
        self.fixes: dict[int, tuple[float, float, float]] = {}
        self.bad_outputs = 0
        self.node.create_subscription(DiagnosticArray, wire.DIAGNOSTICS,
                                      self.counters.update, RELIABLE)
        self.node.create_subscription(DiagnosticArray, wire.INTEGRITY, self._on_risk,
                                      RELIABLE)
        self.node.create_subscription(NavSatFix, wire.FIX, self._on_fix, RELIABLE)
        # Callbacks on their own thread: a verdict is timed when it arrives, also while
        # this thread builds or publishes a large fault.
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name='fuzz_probe_spin',
                                        daemon=True)
        self._thread.start()

    def _on_risk(self, msg) -> None:
        try:
            risk = ma.parse_integrity_risk(msg)
        except ma.MessageError:
            self.bad_outputs += 1
            return
        try:
            unknown = float(risk.extra.get('motion_unknown_s', 0.0))
        except ValueError:
            unknown = math.nan
        self.verdicts.append(Verdict(time.monotonic(), risk.level, risk.epoch_stamp_ns,
                                     risk.epoch_status, risk.protection_level_m,
                                     risk.message, unknown))

    def _on_fix(self, msg) -> None:
        self.fixes[ma.stamp_to_ns(msg.header.stamp)] = (msg.latitude, msg.longitude,
                                                        msg.altitude)

    def publish(self, topic: str, msg) -> bool:
        """Publish a message or raw bytes; False when rclpy refuses it here (a value
        that cannot be serialised never leaves this process)."""
        try:
            self.pubs[topic].publish(msg)
        except Exception:       # noqa: BLE001 - rclpy's conversion errors vary by field
            return False
        return True

    def acknowledged(self, topic: str, timeout_s: float) -> bool:
        """Wait until every reliable subscriber of ``topic`` acknowledged what the probe
        published (it is in the subscriber's queue: a large message is sent in fragments
        after ``publish`` returns); True at once for best-effort ones."""
        try:
            return bool(self.pubs[topic].wait_for_all_acked(
                Duration(nanoseconds=int(timeout_s * 1e9))))
        except Exception:   # noqa: BLE001 - the context went down (a crashed graph)
            return False

    def _spin(self) -> None:
        while not self._stop.is_set() and self.ctx.ok():
            try:
                self.executor.spin_once(timeout_sec=0.01)
            except Exception:   # noqa: BLE001 - the context went down under it (close)
                if not self._stop.is_set():
                    raise

    def spin_until(self, condition, timeout_s: float) -> bool:
        """Wait until ``condition()`` holds (True) or ``timeout_s`` passes (False); the
        probe's callbacks run on their own thread meanwhile."""
        deadline = time.monotonic() + timeout_s
        while not condition():
            if time.monotonic() > deadline:
                return False
            time.sleep(0.002)
        return True

    def wait(self, seconds: float) -> None:
        time.sleep(max(0.0, seconds))

    def connected(self, topics, timeout_s: float) -> bool:
        """Every publisher of ``topics`` matched by a subscriber, and every node's
        diagnostics heard."""
        return self.spin_until(lambda: all(self.pubs[t].get_subscription_count() > 0
                                           for t in topics), timeout_s)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)
