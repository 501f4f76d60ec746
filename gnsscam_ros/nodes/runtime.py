"""The process around the nodes: ``main()`` with its exit codes (:mod:`.node_base`), help,
starting and spinning one or several nodes, a clean stop on Ctrl-C or a failure, and
stopping a node's child process as Ctrl-C does."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from typing import Callable

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

from gnsscam_ros.core.interrupts import redeliver_dropped_interrupt

from .node_base import EXIT_FAILED, EXIT_OK, EXIT_PARAMETER, StartupError
from .memory import configure_node_memory, freeze_start_up_objects


def wants_help(args=None) -> bool:
    """True when ``-h`` or ``--help`` is given before any ``--ros-args`` (``args`` as
    ``rclpy.init`` takes them; None: ``sys.argv``)."""
    argv = list(sys.argv[1:] if args is None else args)
    if '--ros-args' in argv:
        argv = argv[:argv.index('--ros-args')]
    return any(a in ('-h', '--help') for a in argv)


def print_node_help(executable: str, doc: str | None, configs: tuple[str, ...]) -> None:
    """Usage of a node executable: how to pass ROS arguments, what it does, its configs."""
    files = ' '.join(f'--params-file config/{c}.yaml' for c in configs)
    print(f'usage: {executable} [--ros-args [--params-file FILE] [-p NAME:=VALUE] '
          '[-r FROM:=TO] ...]\n')
    print((doc or '').strip())
    print('\nParameters (meaning, unit, default, range) are documented in '
          + ', '.join(f'config/{c}.yaml' for c in configs)
          + ' (installed under share/gnsscam_ros/config).')
    print(f'Example: {executable} --ros-args {files}')


def params_file_problem(args=None) -> str | None:
    """What is wrong with a ``--params-file FILE`` of the ROS arguments (``args`` as
    ``rclpy.init`` takes them; None: ``sys.argv``): ``'FILE: no such file'``, ``'FILE: not
    a file'`` or ``'FILE: <reason>'`` when it cannot be read; None when every one can.

    Checked before ``rclpy.init``, whose own report of a missing file is one line that names
    no file (``[ERROR] [rcl]: Failed to parse global arguments``).
    """
    argv = list(sys.argv if args is None else args)
    inside = False
    for i, arg in enumerate(argv):
        if arg == '--ros-args':
            inside = True
        elif arg == '--':
            inside = False
        elif inside and arg == '--params-file' and i + 1 < len(argv):
            path = argv[i + 1]
            if not os.path.exists(path):
                return f'{path}: no such file'
            if not os.path.isfile(path):
                return f'{path}: not a file'
            try:
                with open(path, 'rb'):
                    pass
            except OSError as err:
                return f'{path}: {err.strerror or err}'
    return None


def init_ros(executable: str, args=None) -> int:
    """``rclpy.init(args=args)`` for a node executable; ROS arguments it cannot use (a
    missing ``--params-file``, a malformed one, a bad remap) become one line on stderr
    naming the argument and :data:`EXIT_PARAMETER` instead of rcl's anonymous error line
    and exit 0.

    Returns:
        :data:`EXIT_OK` when rclpy is initialised, else :data:`EXIT_PARAMETER`.
    """
    problem = params_file_problem(args)
    if problem is not None:
        print(f'{executable}: --params-file {problem}', file=sys.stderr)
        return EXIT_PARAMETER
    try:
        rclpy.init(args=args)
    except (KeyboardInterrupt, ExternalShutdownException):
        raise
    except Exception as err:            # RCLError: rcl could not parse the ROS arguments
        text = str(err).splitlines()[0] if str(err) else type(err).__name__
        print(f'{executable}: bad ROS arguments: {text.split(", at ")[0]}', file=sys.stderr)
        return EXIT_PARAMETER
    return EXIT_OK


def start_nodes(executable: str, constructors: list[Callable], context=None
                ) -> tuple[list, int]:
    """Construct a process's nodes, one after the other; a configuration one of them
    refuses becomes one line on stderr (``<executable>: <what is wrong>``) instead of a
    traceback, and the nodes already constructed are destroyed. Once all are constructed
    each logs its ready line (:meth:`GnssCamNode.ready_line`).

    Ctrl-C during construction shuts the context down under the constructor (the next
    endpoint it creates fails: ``RCLError: ... context is invalid``): that is a stop, not a
    failure.

    Returns:
        ``(nodes, EXIT_OK)``, or ``([], exit code)`` when a node refused to start, or
        ``([], EXIT_OK)`` when the process was stopped while they started.
    """
    nodes: list = []
    try:
        for construct in constructors:
            nodes.append(construct())
        # What the process built to start lives until it exits: out of the collector's
        # full collections, which would otherwise pause an epoch for tens of ms (memory).
        freeze_start_up_objects()
        for node in nodes:
            node.get_logger().info(node.ready_line())
        return nodes, EXIT_OK
    except StartupError as err:
        text = str(err)      # the node's errors start with its name
        print(text if text.startswith(f'{executable}:') else f'{executable}: {text}',
              file=sys.stderr)
        code = err.exit_code
    except Exception:
        if rclpy.ok(context=context):
            raise
        code = EXIT_OK
    for node in nodes:
        quietly(node.destroy_node)
    return [], code


def spin_node(node, executor=None) -> None:
    """Spin ``node`` until Ctrl-C or shutdown (on ``executor``; None: rclpy's global one).

    Ctrl-C shuts the context down from rclpy's signal handler, concurrently with the
    executor: when it lands between the executor's ``context.ok()`` check and its next
    wait, that wait fails (``RCLError: failed to initialize wait set: the given context
    is not valid``; 1 stop in 12 here). An error raised once the context is down is that
    stop, not a failure; one raised while it is up is a failure and propagates.
    """
    try:
        rclpy.spin(node, executor)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        if node.context.ok():
            raise


def _quiet_unraisable(unraisable) -> None:
    """``sys.unraisablehook`` of the node processes.

    - An rclpy object whose constructor a Ctrl-C interrupted (an executor built while
      rclpy's signal handler shuts the context down fails creating its guard condition)
      fails again in its ``__del__`` ("Exception ignored in: Executor.__del__ ...
      AttributeError: ... '_sigint_gc'", 3 stops in 20 here): that is the stop, not an
      error worth a traceback on stderr.
    - The same for llvmlite's objects while numba compiles the kernels at start-up: one
      whose constructor the Ctrl-C interrupted before it held its pointer fails in
      ``ObjectRef.__del__`` ("AttributeError: 'PassBuilder' object has no attribute
      '_as_parameter_'", 1 CI run in about 10).
    - A Ctrl-C that lands inside a ctypes callback (llvmlite's object-cache callbacks
      while numba compiles the kernels at start-up) is raised again in the main thread
      (``core.interrupts``), where it stops the start-up as any other Ctrl-C.

    Everything else goes to Python's hook."""
    if redeliver_dropped_interrupt(unraisable):
        return
    where = getattr(unraisable.object, '__module__', None) or ''
    if (where.startswith(('rclpy', 'llvmlite')) and not rclpy.ok()
            and isinstance(unraisable.exc_value, AttributeError)):
        return
    sys.__unraisablehook__(unraisable)


def quiet_interrupted_rclpy_objects() -> None:
    """Install :func:`_quiet_unraisable` (node process entry points)."""
    sys.unraisablehook = _quiet_unraisable


def quietly(action) -> None:
    """Run a clean-up step of a stopping process: a second Ctrl-C during it, or an error
    of rclpy about the context that is already shut down (``RCLError: ... context is not
    valid`` from an executor or a node torn down after it), does not end in a traceback
    and a non-zero status. Failures while running are judged before the clean-up."""
    try:
        action()
    except (KeyboardInterrupt, Exception):      # noqa: BLE001 - see the docstring
        pass


def failed(nodes) -> bool:
    """True when a node reported a fatal error (:meth:`GnssCamNode.fail`)."""
    return any(getattr(node, 'fatal_error', None) for node in nodes)


def run_node(node_class, args=None) -> int:
    """The Jazzy ``main()`` of a single-node executable (ros2/demos talker pattern).

    ``-h``/``--help`` (before ``--ros-args``) prints the usage and returns.

    Returns:
        The exit code (module docstring): 0 after Ctrl-C or shutdown, 2 for a refused
        parameter or ROS argument (a ``--params-file`` that does not exist or does not
        parse), 3 for an unusable input file (one line on stderr each).
    """
    name = node_class.__module__.rsplit('.', 1)[-1]
    if name == '__main__':              # python -m gnsscam_ros.nodes.<name>
        name = os.path.splitext(os.path.basename(sys.argv[0]))[0]
    if wants_help(args):
        print_node_help(name, sys.modules[node_class.__module__].__doc__, (name,))
        return EXIT_OK
    quiet_interrupted_rclpy_objects()
    configure_node_memory()             # before the first participant of the process
    nodes: list = []
    executor = None
    code = EXIT_OK
    try:
        try:
            code = init_ros(name, args)
            if code != EXIT_OK:
                return code
            # Built before the node logs its ready line: a stop right after the line does
            # not interrupt the executor's construction (see _quiet_unraisable).
            executor = SingleThreadedExecutor()
            nodes, code = start_nodes(name, [node_class])
            if nodes:
                spin_node(nodes[0], executor)
        except (KeyboardInterrupt, ExternalShutdownException):
            pass                        # Ctrl-C during start-up
        except Exception:
            if rclpy.ok():
                raise                   # a failure while running: traceback, exit 1
            # else: an rclpy call failed because Ctrl-C shut the context down under it
        finally:
            # A node that failed shut the context down itself: that stop is a failure.
            if failed(nodes):
                code = EXIT_FAILED
            shut_down(nodes, executor=executor)
    except KeyboardInterrupt:
        pass                            # a second Ctrl-C between clean-up steps
    return code


def shut_down(nodes, spinner: 'NodeSpinner | None' = None, executor=None,
              context=None) -> None:
    """Clean-up of a node process: the spinner or executor, the nodes, the context (each
    step :func:`quietly`). Further Ctrl-C is ignored from here on: the process is stopping, and
    one landing while Python finalises (which resets SIGINT to its default action) killed
    the process with -SIGINT instead of exit 0."""
    _ignore_sigint()
    if spinner is not None:
        quietly(spinner.stop)
    if executor is not None:
        quietly(executor.shutdown)
    for node in nodes:
        quietly(node.destroy_node)
    quietly(lambda: rclpy.try_shutdown(context=context))
    _ignore_sigint()                     # rclpy restored its predecessor's handler


def _ignore_sigint() -> None:
    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    except ValueError:
        pass                             # not the main thread (a test calling main())


class NodeSpinner:
    """Each node on its own single-threaded executor and thread.

    Several nodes in one process (pipeline_node, in-process replays) are served this way
    rather than by rclpy's ``MultiThreadedExecutor``: in Jazzy that executor re-queues
    callbacks that are submitted but not yet running and wakes up again at once, a busy
    loop that kept a whole core at 100 % and slowed every node (ros2/rclpy#1452; measured
    here: pipeline_node replayed a bag at 1.15x real time, separate processes at 14x). A
    single-threaded executor per node also keeps each node's callbacks serialised, as in
    its own process. A node whose callback raises stops the whole group (the error is
    logged and the context shut down), as its own process would exit.

    The threads spin in short slices and check a stop flag, so that :meth:`stop` joins
    them *before* it shuts the executors down: an executor torn down while its thread is
    still waiting on it can crash the process.
    """

    SLICE_S = 0.1

    def __init__(self, nodes: list, context=None):
        self.context = context
        self.failed = False              # a node's callback raised while running
        self._nodes = list(nodes)
        self._stop = threading.Event()
        self._pairs = []
        # Every executor first: when one cannot be built (Ctrl-C shut the context down
        # meanwhile), no thread is left spinning.
        executors = [SingleThreadedExecutor(context=context) for _ in nodes]
        for node, executor in zip(nodes, executors):
            executor.add_node(node)
            thread = threading.Thread(target=self._spin, args=(executor, node), daemon=True,
                                      name=f'spin_{node.get_name()}')
            thread.start()
            self._pairs.append((executor, thread))

    def _ok(self) -> bool:
        return self.context.ok() if self.context is not None else rclpy.ok()

    def _spin(self, executor, node) -> None:
        try:
            while not self._stop.is_set() and self._ok():
                executor.spin_once(timeout_sec=self.SLICE_S)
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        except Exception as err:    # noqa: BLE001 - a node failed: stop the group, loudly
            if self._ok():          # else: the context went down under it (Ctrl-C)
                self.failed = True
                node.get_logger().fatal(f'{type(err).__name__}: {err}; shutting down')
                rclpy.try_shutdown(context=self.context)

    @property
    def any_failed(self) -> bool:
        """A node's callback raised, or a node reported a fatal error itself
        (:meth:`GnssCamNode.fail`, e.g. from a worker thread)."""
        return self.failed or failed(self._nodes)

    def running(self) -> bool:
        """True while every thread spins and the context is up."""
        return self._ok() and all(t.is_alive() for _, t in self._pairs)

    def wait(self) -> None:
        """Block until Ctrl-C, shutdown or a failed node."""
        while self.running():
            time.sleep(self.SLICE_S)

    def stop(self) -> None:
        """Stop the threads, then shut their executors down."""
        self._stop.set()
        for _, thread in self._pairs:
            thread.join(timeout=10 * self.SLICE_S + 5.0)
        for executor, _ in self._pairs:
            executor.shutdown(timeout_sec=1.0)


def stop_process(proc, timeout_s: float = 20.0) -> int:
    """Stop a node's child process as Ctrl-C does (SIGINT), SIGKILL after ``timeout_s``;
    its exit status."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        return proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.wait()
