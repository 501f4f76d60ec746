"""Running a command-line tool on one input, the way a user would, and watching what it did.

A tool runs either in this process (its ``main(argv)``: fast; stdout, stderr and the file
descriptor 2 captured; an exception that escapes ``main`` is the traceback a user would
see, exit status 1) or as a subprocess of the same interpreter (``python -c`` calling the
same ``main``; with a timeout).
"""
from __future__ import annotations

import contextlib
import hashlib
import io
import os
import subprocess
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

#: tool -> (program name, module and function of its ``main``, fixed leading arguments).
TOOLS = {
    'replay': ('gnsscam_replay', 'gnsscam_ros.live.replay', []),
    'eval_bag': ('gnsscam_eval', 'gnsscam_ros.evaluation.cli', ['bag']),
    'eval_smartloc': ('gnsscam_eval', 'gnsscam_ros.evaluation.cli', ['smartloc']),
    'convert': ('gnsscam_convert', 'gnsscam_ros.bags.convert_cli', ['smartloc']),
    'mapdb_build': ('gnsscam_mapdb', 'gnsscam_ros.vision.mapdb_cli', ['build']),
    'mapdb_query': ('gnsscam_mapdb', 'gnsscam_ros.vision.mapdb_cli', ['query']),
    'record': ('gnsscam_record', 'gnsscam_ros.live.record', []),
}


@dataclass
class Outcome:
    """What one run of a tool did."""

    code: int | None
    stdout: str = ''
    stderr: str = ''
    traceback: bool = False
    exception: str = ''
    seconds: float = 0.0
    timed_out: bool = False
    notes: list = field(default_factory=list)


def _main(tool: str):
    import importlib
    return importlib.import_module(TOOLS[tool][1]).main


@contextlib.contextmanager
def _captured_fd2():
    """Redirect file descriptor 2 (C-level logging: rcutils, OpenCV) into a temporary
    file; yields a function returning what was written."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile(mode='w+b') as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield lambda: (tmp.seek(0), tmp.read().decode('utf-8', 'replace'))[1]
        finally:
            os.dup2(saved, 2)
            os.close(saved)


def _reset_rclpy() -> None:
    """A tool that failed in this process may leave rclpy's default context up; its next
    run (a new process for a user) must not inherit it."""
    rclpy = sys.modules.get('rclpy')
    if rclpy is not None:
        try:
            rclpy.try_shutdown()
        except Exception:       # noqa: BLE001 - nothing more to clean up
            pass


def run_in_process(tool: str, argv: list[str], env: dict | None = None) -> Outcome:
    """``main(argv)`` of the tool in this process."""
    out, err = io.StringIO(), io.StringIO()
    argv = TOOLS[tool][2] + list(argv)
    saved_env = {k: os.environ.get(k) for k in (env or {})}
    os.environ.update(env or {})
    t0 = time.monotonic()
    code, tb, exc = None, False, ''
    try:
        with _captured_fd2() as c_stderr, contextlib.redirect_stdout(out), \
                contextlib.redirect_stderr(err):
            try:
                code = _main(tool)(argv)
            except SystemExit as stop:
                code = stop.code if isinstance(stop.code, int) else (
                    0 if stop.code is None else 1)
            except BaseException as raised:     # noqa: BLE001 - what a user would see
                if isinstance(raised, KeyboardInterrupt):
                    raise
                tb, code = True, 1
                exc = f'{type(raised).__name__}: {raised}'[:300]
                traceback.print_exc(file=err)
            c_text = c_stderr()
    finally:
        _reset_rclpy()
        for k, v in saved_env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    text = err.getvalue() + c_text
    return Outcome(code=code, stdout=out.getvalue(), stderr=text,
                   traceback=tb or 'Traceback' in text, exception=exc,
                   seconds=time.monotonic() - t0)


def run_subprocess(tool: str, argv: list[str], env: dict | None = None,
                   timeout_s: float = 120.0) -> Outcome:
    """The tool as a child process of the same interpreter."""
    module = TOOLS[tool][1]
    code = f'import sys; from {module} import main; sys.exit(main(sys.argv[1:]))'
    full_env = dict(os.environ, **(env or {}))
    t0 = time.monotonic()
    try:
        proc = subprocess.run([sys.executable, '-c', code, *TOOLS[tool][2], *argv],
                              capture_output=True, text=True, env=full_env,
                              timeout=timeout_s, errors='replace')
    except subprocess.TimeoutExpired as err:
        return Outcome(code=None, stdout=str(err.stdout or ''), stderr=str(err.stderr or ''),
                       timed_out=True, seconds=time.monotonic() - t0)
    return Outcome(code=proc.returncode, stdout=proc.stdout, stderr=proc.stderr,
                   traceback='Traceback' in proc.stderr, seconds=time.monotonic() - t0)


# ------------------------------------------------------------------- file watching
def fingerprint(path: Path) -> tuple | None:
    """Content hash and modification time of a file (a folder: of its files), None when
    absent."""
    path = Path(path)
    if not path.exists():
        return None
    if path.is_dir():
        return tuple(sorted((str(p.relative_to(path)), fingerprint(p))
                            for p in path.rglob('*') if p.is_file()))
    h = hashlib.sha256()
    with path.open('rb') as f:
        for chunk in iter(lambda: f.read(1 << 20), b''):
            h.update(chunk)
    return h.hexdigest(), path.stat().st_mtime_ns


def listing(folder: Path) -> set[str]:
    """Every path under ``folder`` (hidden ones included), relative."""
    folder = Path(folder)
    if not folder.is_dir():
        return set()
    try:
        return {str(p.relative_to(folder)) for p in folder.rglob('*')}
    except OSError:
        return set()
