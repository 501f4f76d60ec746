"""A Ctrl-C while the kernels compile is not lost.

numba compiles through llvmlite, which calls back into Python through ctypes (its object
cache). A ``KeyboardInterrupt`` raised inside a ctypes callback cannot propagate out of
it: Python prints "Exception ignored on calling ctypes callback function ... Traceback
... KeyboardInterrupt" and drops it, and the compilation goes on for tens of seconds as
if no Ctrl-C had come. :func:`redeliver_dropped_interrupt` hands it back to the main
thread instead, where it stops the process as any other Ctrl-C does: from another thread,
a moment later, because the main thread checks for signals at once and would raise it
inside the unraisable hook itself (and Python would report that as ignored too). Landing
in a callback again repeats this.

The node processes call it from their own unraisable hook (``nodes.runtime``); the
evaluation commands run inside :func:`interrupts_redelivered`. Standard library only, and
outside ``core.kernels`` (whose import loads numba): the light nodes import it too.
"""
from __future__ import annotations

import _thread
import signal
import sys
import threading
from contextlib import contextmanager

#: How long after the hook a dropped Ctrl-C is raised again in the main thread: long
#: enough for the hook to have returned [s].
REDELIVER_AFTER_S = 0.05


def redeliver_dropped_interrupt(unraisable) -> bool:
    """Raise a ``KeyboardInterrupt`` that Python could not raise (``unraisable`` as
    ``sys.unraisablehook`` gets it) again in the main thread; whether it was one."""
    if not isinstance(unraisable.exc_value, KeyboardInterrupt):
        return False
    # Not a daemon (as core.noise's worker): the interpreter joins it before it finalises
    # instead of leaving it to run in a half torn-down one; 50 ms at most.
    threading.Timer(REDELIVER_AFTER_S, _thread.interrupt_main, args=(signal.SIGINT,)).start()
    return True


@contextmanager
def interrupts_redelivered():
    """While inside, :func:`redeliver_dropped_interrupt` sees every unraisable exception
    first; the rest goes to the hook that was in place, which is back on exit."""
    previous = sys.unraisablehook

    def hook(unraisable) -> None:
        if not redeliver_dropped_interrupt(unraisable):
            previous(unraisable)

    sys.unraisablehook = hook
    try:
        yield
    finally:
        sys.unraisablehook = previous
