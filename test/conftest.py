"""Shared fixtures and the ROS test harness. Tests never read ../shared: fixtures live in
test/data."""
import itertools
import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from gnsscam_ros.nodes.runtime import stop_process
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

DATA = Path(__file__).parent / 'data'
SMARTLOC_EXCERPT = DATA / 'smartloc_excerpt'


def pytest_configure(config):
    # The tiers: `pytest -m "not slow"` is the quick one (core maths, adapters, the fast
    # node tests; seconds); the default run is everything (the README's test command).
    config.addinivalue_line('markers', 'slow: takes a second or more (long drives, bags, '
                                       'node processes); left out by -m "not slow"')
    config.addinivalue_line('markers', 'ros: runs ROS nodes in a graph of its own')


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


def pytest_sessionstart(session):
    """Compile the epoch kernels once, into numba's disk cache, before any test starts a
    node process (each would compile them itself otherwise, all at once)."""
    from gnsscam_ros.core.warmup import warm_up_kernels
    warm_up_kernels()


@pytest.fixture(scope='session')
def smartloc_excerpt():
    from gnsscam_ros.datasets.smartloc import discover_files, load_smartloc
    return load_smartloc(*discover_files(SMARTLOC_EXCERPT))


# ====================================================================== ROS harness
# One place for what every ROS test needs: a domain of its own, a graph to spin until a
# condition holds (never a fixed sleep), and a child process stopped as Ctrl-C does.
_domains = itertools.count()


def ros_domain_id() -> int:
    """A ROS domain id no other test of this run uses (1-209; the replay's own default
    range, 220-232, stays free)."""
    return 1 + (os.getpid() * 7 + next(_domains)) % 209


def ros_env(tmp_path, domain: int, base: dict | None = None) -> dict:
    """Environment of a child process on ``domain`` (logs under ``tmp_path``)."""
    env = dict(os.environ if base is None else base)
    env.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               ROS_LOG_DIR=str(Path(tmp_path) / 'ros_log'), OPENBLAS_NUM_THREADS='1',
               PYTHONUNBUFFERED='1')
    return env


class RosGraph:
    """Nodes, a probe node and a single-threaded executor in a fresh context.

    Args:
        domain: ROS domain id (default: a fresh one).
        args: ROS arguments of the context (``--ros-args ...``).
    """

    def __init__(self, domain: int | None = None, args=None):
        self.domain = ros_domain_id() if domain is None else domain
        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=self.domain, args=args)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.nodes = []
        self.probe = rclpy.create_node('probe', context=self.ctx)
        self.executor.add_node(self.probe)
        self.qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                              reliability=ReliabilityPolicy.RELIABLE)

    def add(self, node):
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def publisher(self, msg_type, topic):
        return self.probe.create_publisher(msg_type, topic, self.qos)

    def collect(self, msg_type, topic) -> list:
        box = []
        self.probe.create_subscription(msg_type, topic, box.append, self.qos)
        return box

    def spin_until(self, condition, timeout_s=20.0, what='condition'):
        deadline = time.monotonic() + timeout_s
        while not condition():
            assert time.monotonic() < deadline, f'timed out after {timeout_s} s: {what}'
            self.executor.spin_once(timeout_sec=0.01)

    def spin_for(self, seconds):
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.01)

    def connect(self, *publishers):
        for pub in publishers:
            self.spin_until(lambda: pub.get_subscription_count() > 0, 10.0,
                            f'a subscriber on {pub.topic_name}')

    def node_names(self) -> set:
        return set(self.probe.get_node_names())

    def close(self):
        self.executor.shutdown()
        for node in self.nodes:
            node.destroy_node()
        self.probe.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


@pytest.fixture
def graph():
    g = RosGraph()
    yield g
    g.close()


def wait_until(condition, timeout_s: float, what: str) -> None:
    """Poll ``condition`` (something another thread or process advances) until it holds;
    fail after ``timeout_s`` naming ``what``."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f'timed out after {timeout_s} s: {what}'
        time.sleep(0.05)


def stop(proc: subprocess.Popen, timeout_s: float = 20.0) -> int:
    """SIGINT (Ctrl-C, as ros2 run forwards it) and the exit status; a process that does
    not stop within ``timeout_s`` is killed and the test fails."""
    rc = stop_process(proc, timeout_s)
    assert rc != -signal.SIGKILL, f'the process ignored SIGINT for {timeout_s} s'
    return rc
