"""Thin rclpy nodes: parse with ``msg_adapters``, call ``gnsscam_ros.core``, publish.

One module per executable (gnss_node, camera_node, imu_node, fusion_node) plus
``pipeline`` (all four in one process) and ``bench``. Only this subpackage imports rclpy.
"""
