"""Thin rclpy nodes: parse with ``msg_adapters``, call ``gnsscam_ros.core``, publish.

One module per executable (gnss_node, camera_node, imu_node, fusion_node) plus
``pipeline`` (all four in one process). Only this subpackage and ``live`` import rclpy.

The node executables are processes of this package, so this package (not the library
one) asks OpenBLAS for one thread unless the environment says otherwise: the
per-particle products are tall and skinny, where threads cost 20-40x more than they
save. It runs before the node modules import numpy, which reads the variable once.
"""
import os

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
