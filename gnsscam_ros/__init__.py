"""gnsscam_ros: GNSS-camera particle filter with integrity risk for ROS 2 Jazzy."""
