"""gnsscam_ros: GNSS-camera particle filter with integrity risk for ROS 2 Jazzy.

BLAS threads: the per-particle arithmetic is made of tall, skinny products
((N, 3) @ (3, k)), on which a multithreaded OpenBLAS spends 20-40x longer synchronising
threads than computing (measured: 40 ms vs 1 ms for 100,000 x 12). Run with
``OPENBLAS_NUM_THREADS=1`` in the environment: ``./run`` exports it (unless already set),
and the node processes the package starts itself (``live.replay.replay_through_nodes``,
used by ``./run demo``) get 1 unless it is set. With ``ros2 run`` or a launch file, set it
yourself, e.g.
``OPENBLAS_NUM_THREADS=1 ros2 run gnsscam_ros fusion_node`` or ``SetEnvironmentVariable``
in the launch description. OpenBLAS reads it once, when numpy is first imported, so the
package cannot set it for you without changing the environment of whoever imports it.
"""
