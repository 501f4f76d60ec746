"""The ROS test harness: a graph of nodes spun until a condition holds, and a child process
stopped as Ctrl-C does. Imported by ROS tests only: without rclpy, importing it skips the
importing test module, with the reason (conftest.NO_RCLPY).

The rclpy-free parts (a domain id of its own, a child's environment, polling) are in
conftest and re-exported here for the ROS tests.
"""
import contextlib
import signal
import subprocess
import time

import pytest
from conftest import NO_RCLPY, ros_domain_id, ros_env, wait_until

rclpy = pytest.importorskip('rclpy', reason=NO_RCLPY)

from gnsscam_ros.nodes.camera_node import CameraNode  # noqa: E402
from gnsscam_ros.nodes.fusion_node import FusionNode  # noqa: E402
from gnsscam_ros.nodes.gnss_node import GnssNode  # noqa: E402
from gnsscam_ros.nodes.imu_node import ImuNode  # noqa: E402
from gnsscam_ros.nodes.runtime import stop_process  # noqa: E402  (needs rclpy)
from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402

__all__ = ['RosGraph', 'deserialize_message', 'ros_domain_id', 'ros_env', 'serialize_message',
           'stop', 'wait_until']


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


def stop(proc: subprocess.Popen, timeout_s: float = 20.0) -> int:
    """SIGINT (Ctrl-C, as ros2 run forwards it) and the exit status; a process that does
    not stop within ``timeout_s`` is killed and the test fails."""
    rc = stop_process(proc, timeout_s)
    assert rc != -signal.SIGKILL, f'the process ignored SIGINT for {timeout_s} s'
    return rc


@contextlib.contextmanager
def every_node_in_process():
    """The four nodes with their default parameters in one rclpy context of this process
    (no spinning), by name; destroyed and the context shut down afterwards."""
    ctx = Context()
    rclpy.init(context=ctx, domain_id=ros_domain_id())
    made = []
    try:
        made = [cls(context=ctx) for cls in (GnssNode, CameraNode, ImuNode, FusionNode)]
        yield {node.get_name(): node for node in made}
    finally:
        for node in made:
            node.destroy_node()
        rclpy.shutdown(context=ctx)
