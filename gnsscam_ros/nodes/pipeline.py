"""pipeline_node: gnss_node, camera_node, imu_node and fusion_node in one process.

For single-machine use: the four nodes share a multi-threaded executor (each keeps its own
name, parameters and topics, so ``--params-file`` files written for the separate
executables apply unchanged). The filter epoch holds the GIL for most of its run, so on a
loaded machine separate processes can give lower latency.
"""
from __future__ import annotations

import rclpy
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor

from .camera_node import CameraNode
from .fusion_node import FusionNode
from .gnss_node import GnssNode
from .imu_node import ImuNode


def make_nodes(**kwargs) -> list:
    """The four nodes with their default names (``kwargs`` go to every constructor, e.g.
    ``context=``)."""
    return [GnssNode(**kwargs), CameraNode(**kwargs), ImuNode(**kwargs),
            FusionNode(**kwargs)]


def main(args=None) -> None:
    """``ros2 run gnsscam_ros pipeline_node``."""
    rclpy.init(args=args)
    nodes = []
    executor = None
    try:
        nodes = make_nodes()
        executor = MultiThreadedExecutor(num_threads=4)
        for node in nodes:
            executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if executor is not None:
            executor.shutdown()
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
