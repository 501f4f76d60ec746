"""Filter core: numpy/scipy only. Never import rclpy here (see design.md §2)."""
