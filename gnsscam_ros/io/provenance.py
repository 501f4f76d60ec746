"""Where a result came from: the date, the machine and the command line that wrote it.

Every tool that writes a result JSON (``gnsscam_eval``, ``gnsscam_bench``, the demo) adds
these fields at the top level of its file, so that ``docs/results.md`` can say when, where
and how each figure was made (``python -m gnsscam_ros.evaluation.docs``).
"""
from __future__ import annotations

import datetime
import os
import platform
import shlex
import socket


def provenance(program: str, argv) -> dict:
    """When, where and how a result was made.

    Args:
        program: The command as a user types it (``gnsscam_eval``,
            ``python -m gnsscam_ros.evaluation.demo``), written as it is.
        argv: Its arguments (without the program).

    Returns:
        ``date`` (UTC, ISO 8601), ``machine`` (host name, platform, processor, CPU count,
        Python version and the load average at the start: a timing figure measured under
        load says so) and ``command_line`` (shell-quoted).
    """
    load = os.getloadavg() if hasattr(os, 'getloadavg') else None
    return {'date': datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds'),
            'machine': {'hostname': socket.gethostname(), 'platform': platform.platform(),
                        'processor': platform.machine(), 'cpus': os.cpu_count(),
                        'python': platform.python_version(),
                        'load_average_at_start': list(load) if load else None},
            'command_line': ' '.join([program, shlex.join([str(a) for a in argv])]).strip()}
