"""Filter core: numpy/scipy only, nothing of the project outside core. Never import rclpy
here: the nodes, the offline evaluation and the benches all run this code."""
