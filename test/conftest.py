"""Shared fixtures, and the parts of the ROS test harness that need no rclpy (the rest is
test/ros_harness.py, imported by ROS tests only). Tests never read ../shared: fixtures
live in test/data.

Without rclpy (a platform tier without ROS 2, docs/development.md "Platform tiers") the
core, vision, dataset and evaluation tests run; tests marked ``ros`` or using the ``graph``
fixture are skipped, and so are the modules that import ros_harness.
"""
import importlib.util
import itertools
import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

DATA = Path(__file__).parent / 'data'
SMARTLOC_EXCERPT = DATA / 'smartloc_excerpt'
#: Whether ROS 2's rclpy is importable here (a sourced ROS 2, or the PyPI Jazzy wheels).
HAVE_RCLPY = importlib.util.find_spec('rclpy') is not None
#: Why a ROS test is skipped where rclpy is not.
NO_RCLPY = ('needs rclpy (ROS 2 Jazzy), not installed in this environment (e.g. the '
            'ubuntu-noble tier on CPython 3.12: PyPI has Jazzy wheels for 3.11 only)')


def pytest_configure(config):
    # The tiers: `pytest -m "not slow"` is the quick one (core maths, adapters, the fast
    # node tests; seconds); the default run is everything (the README's test command).
    config.addinivalue_line('markers', 'slow: takes a second or more (long drives, bags, '
                                       'node processes); left out by -m "not slow"')
    config.addinivalue_line('markers', 'ros: needs rclpy (runs ROS nodes or serialises ROS '
                                       'messages); skipped where rclpy is not installed')


def pytest_collection_modifyitems(config, items):
    """Skip the ROS tests, with the reason, where rclpy is not installed."""
    if HAVE_RCLPY:
        return
    skip = pytest.mark.skip(reason=NO_RCLPY)
    for item in items:
        if 'ros' in item.keywords or 'graph' in getattr(item, 'fixturenames', ()):
            item.add_marker(skip)


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


def pytest_sessionstart(session):
    """Compile the epoch kernels once, into numba's disk cache, before any test starts a
    node process (each would compile them itself otherwise, all at once)."""
    from gnsscam_ros.core.warmup import warm_up_kernels
    warm_up_kernels()


@pytest.fixture(scope='session')
def smartloc_excerpt():
    from gnsscam_ros.datasets.smartloc import discover_files, load_smartloc
    return load_smartloc(*discover_files(SMARTLOC_EXCERPT))


# ====================================================================== ROS harness
# One place for what every ROS test needs: a domain of its own, a graph to spin until a
# condition holds (never a fixed sleep; ros_harness.RosGraph), and a child process stopped
# as Ctrl-C does (ros_harness.stop).
_domains = itertools.count()
# Under pytest-xdist (`-n 2`) each worker takes every n-th id of the run's sequence, so
# two workers never share a domain; the run's base is the controller's process id.
_WORKER = os.environ.get('PYTEST_XDIST_WORKER', '')
_WORKERS = int(os.environ.get('PYTEST_XDIST_WORKER_COUNT', '1')) if _WORKER else 1
_WORKER_INDEX = int(_WORKER[2:]) if _WORKER.startswith('gw') else 0
_RUN_BASE = 7 * (os.getppid() if _WORKER else os.getpid())
_DOMAIN_SPAN = 209 - 209 % _WORKERS


def ros_domain_id() -> int:
    """A ROS domain id no other test of this run uses (1-209; the replay's own default
    range, 220-232, stays free)."""
    return 1 + (_RUN_BASE + _WORKERS * next(_domains) + _WORKER_INDEX) % _DOMAIN_SPAN


def ros_env(tmp_path, domain: int, base: dict | None = None) -> dict:
    """Environment of a child process on ``domain`` (logs under ``tmp_path``)."""
    env = dict(os.environ if base is None else base)
    env.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               ROS_LOG_DIR=str(Path(tmp_path) / 'ros_log'), OPENBLAS_NUM_THREADS='1',
               PYTHONUNBUFFERED='1')
    return env


@pytest.fixture
def graph():
    """A fresh :class:`ros_harness.RosGraph`, closed after the test (a test asking for it
    is a ROS test: skipped without rclpy before this runs)."""
    from ros_harness import RosGraph       # imports rclpy: only where a test asks for it
    g = RosGraph()
    yield g
    g.close()


def wait_until(condition, timeout_s: float, what: str) -> None:
    """Poll ``condition`` (something another thread or process advances) until it holds;
    fail after ``timeout_s`` naming ``what``."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f'timed out after {timeout_s} s: {what}'
        time.sleep(0.05)


def stop_child(proc: subprocess.Popen, timeout_s: float = 20.0) -> int:
    """SIGINT, then SIGKILL after ``timeout_s``; the exit status (a process that is no ROS
    node; ros_harness.stop stops nodes with the nodes' own helper and fails on SIGKILL)."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        return proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.wait()
