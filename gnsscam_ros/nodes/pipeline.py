"""pipeline_node: gnss_node, camera_node, imu_node and fusion_node in one process.

For single-machine use: each of the four nodes spins its own single-threaded executor on
its own thread (``runtime.NodeSpinner``; each keeps its own name, parameters and topics,
so ``--params-file`` files written for the separate executables apply unchanged). They
share one GIL: the filter epoch holds it for most of its run, so separate processes
(``ros2 run`` each node) use more cores and replay a bag faster.

Exit codes: 0 stopped (Ctrl-C, shutdown), 1 a node failed while running, 2 a parameter
refused at start-up, 3 camera_node's ``database_path`` missing or not a map database (one
line on stderr each; the nodes already started are stopped).
"""
from __future__ import annotations

import sys

import rclpy
from rclpy.executors import ExternalShutdownException

from .camera_node import CameraNode
from .node_base import EXIT_FAILED, EXIT_OK
from .fusion_node import FusionNode
from .gnss_node import GnssNode
from .imu_node import ImuNode
from .memory import configure_node_memory, keep_epoch_memory
from .runtime import (NodeSpinner, failed, init_ros, print_node_help,
                      quiet_interrupted_rclpy_objects, shut_down, start_nodes, wants_help)


def make_nodes(**kwargs) -> list:
    """The four nodes with their default names (``kwargs`` go to every constructor, e.g.
    ``context=``)."""
    return [GnssNode(**kwargs), CameraNode(**kwargs), ImuNode(**kwargs),
            FusionNode(**kwargs)]


def main(args=None) -> int:
    """``ros2 run gnsscam_ros pipeline_node``; the exit code (module docstring)."""
    if wants_help(args):
        print_node_help('pipeline_node', __doc__,
                        ('gnss_node', 'imu_node', 'camera_node', 'fusion_node'))
        return EXIT_OK
    quiet_interrupted_rclpy_objects()
    configure_node_memory()             # before the first participant of the process
    keep_epoch_memory()                 # fusion_node's epochs run in this process too
    nodes, spinner, code = [], None, EXIT_OK
    try:
        try:
            code = init_ros('pipeline_node', args)
            if code != EXIT_OK:
                return code
            nodes, code = start_nodes('pipeline_node',
                                      [GnssNode, CameraNode, ImuNode, FusionNode])
            if nodes:
                spinner = NodeSpinner(nodes)
                spinner.wait()
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        except Exception:
            if rclpy.ok():
                raise                   # a failure while running: traceback, exit 1
            # else: an rclpy call (the executors' construction) failed because Ctrl-C
            # shut the context down under it: a stop
        finally:
            # Judged before the clean-up, and also after Ctrl-C: a node that failed shuts
            # the context down, which ends the wait as a stop would.
            if (spinner is not None and spinner.any_failed) or failed(nodes):
                code = EXIT_FAILED
            shut_down(nodes, spinner)
    except KeyboardInterrupt:
        pass                            # a second Ctrl-C between clean-up steps
    return code


if __name__ == '__main__':
    sys.exit(main())
