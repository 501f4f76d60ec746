"""Ctrl-C in the evaluation commands, wherever it lands.

A Ctrl-C that arrives while a compiled (numba) kernel runs does not come out as a
``KeyboardInterrupt``: the kernel returns with the exception set and Python raises a
``SystemError`` ("returned a result with an exception set") whose cause or context is the
``KeyboardInterrupt``. The commands treat both alike: a stop asked for, exit 130.
"""
from __future__ import annotations

#: Exit status of a command stopped by Ctrl-C (128 + SIGINT, as a shell reports it).
EXIT_INTERRUPTED = 130


def is_interrupt(err: BaseException) -> bool:
    """Whether ``err`` is a Ctrl-C: a ``KeyboardInterrupt`` in its chain of causes."""
    seen = set()
    while err is not None and id(err) not in seen:
        if isinstance(err, KeyboardInterrupt):
            return True
        seen.add(id(err))
        err = err.__cause__ or err.__context__
    return False
