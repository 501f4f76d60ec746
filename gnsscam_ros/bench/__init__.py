"""Benchmarks: commands that print figures (``gnsscam_bench`` and the ``python -m`` ones).

They time what the nodes run, so they run it as the nodes do: OpenBLAS with one thread
unless the environment says otherwise (``gnsscam_ros.nodes``), set here before the bench
modules import numpy, which reads the variable once. With its default threads, the
yardstick's matrix product leaves a second OpenBLAS thread spinning on a 2-core machine,
and the epoch timed after it took 1.4x as long (N = 10,000: 10.1 against 7.1 ms).
"""
import os

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
