"""gnsscam_ros: GNSS-camera particle filter with integrity risk for ROS 2 Jazzy."""
import os

# The per-particle arithmetic is made of tall, skinny products ((N, 3) @ (3, k)): a
# multithreaded OpenBLAS spends 20-40x longer synchronising threads than computing them on
# this kind of shape (measured: 40 ms vs 1 ms for 100,000 x 12). This runs before numpy is
# first imported through the package; set the variable yourself to override it.
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
