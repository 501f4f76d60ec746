"""gnsscam_ros: GNSS-camera particle filter with integrity risk for ROS 2 Jazzy.

BLAS threads: the per-particle arithmetic is made of tall, skinny products
((N, 3) @ (3, k)), on which a multithreaded OpenBLAS spends 20-40x longer synchronising
threads than computing (measured: 40 ms vs 1 ms for 100,000 x 12). Run with
``OPENBLAS_NUM_THREADS=1`` in the environment: ``./run`` exports it (unless already set),
and the node executables (``ros2 run gnsscam_ros <node>``) set it to 1 unless it is set
(``gnsscam_ros.nodes``). OpenBLAS reads it once, when numpy is first imported; importing
the library (``gnsscam_ros.core``, ...) leaves your environment alone.
"""
