"""pipeline_node: gnss_node, camera_node, imu_node and fusion_node in one process.

For single-machine use: each of the four nodes spins its own single-threaded executor on
its own thread (``common.NodeSpinner``; each keeps its own name, parameters and topics,
so ``--params-file`` files written for the separate executables apply unchanged). They
share one GIL: the filter epoch holds it for most of its run, so separate processes
(``ros2 run`` each node) use more cores and replay a bag faster.
"""
from __future__ import annotations

import rclpy
from rclpy.executors import ExternalShutdownException

from .camera_node import CameraNode
from .common import NodeSpinner, print_node_help, wants_help
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
    if wants_help(args):
        print_node_help('pipeline_node', __doc__,
                        ('gnss_node', 'imu_node', 'camera_node', 'fusion_node'))
        return
    rclpy.init(args=args)
    nodes, spinner = [], None
    try:
        nodes = make_nodes()
        spinner = NodeSpinner(nodes)
        spinner.wait()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if spinner is not None:
            spinner.stop()
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
