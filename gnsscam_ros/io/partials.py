"""Hidden partial outputs (``.NAME.partial-*``) and the leftovers of killed writers.

``gnsscam_convert`` and ``gnsscam_record`` write a bag into a hidden sibling folder, and the
atomic JSON/CSV/npz writers (:mod:`.atomic`) and the map database a hidden sibling file,
renamed into place at the end; an error or Ctrl-C removes it, but SIGKILL (or a power cut)
cannot, and a bag folder may hold hundreds of MB. The name says who wrote it,
``.NAME.partial-HOST-PID-XXXXXXXX``, so that the next run can tell a leftover from the
work of a writer that still runs:

* it is **stale** (:func:`sweep_partials` removes it) when it was written on this host and
  its writer cannot be running: no process with that pid exists, or the process that has
  the pid now started after the folder was last written to (the pid was reused);
* it is **in use** when its writer provably runs (the process with that pid started before
  the folder was last written): left alone and not reported;
* anything else (another host, an older name without a pid, a running pid whose start
  time is unknown, a folder that cannot be removed) is **reported** with the command that
  removes it, never touched: deleting the bag of a writer that still runs would lose data.
"""
from __future__ import annotations

import errno
import os
import re
import secrets
import shlex
import shutil
import socket
import sys
from dataclasses import dataclass
from pathlib import Path

#: Marker between the output's name and the writer's identity.
MARK = '.partial-'
#: ``.NAME.partial-HOST-PID-RANDOM``: the random part has no '-' (hex digits; that of
#: older versions, mkdtemp's: letters, digits, '_'), the host is sanitised to letters,
#: digits, '_' and '.', so the pid is the last number between dashes.
_OWNED = re.compile(r'^\.(?P<name>.+)\.partial-(?P<host>[A-Za-z0-9_.]+)-(?P<pid>\d+)-'
                    r'(?P<rand>[A-Za-z0-9_]+)$')
#: Names written before the pid was part of them: ``.NAME.partial-RANDOM``.
_LEGACY = re.compile(r'^\.(?P<name>.+)\.partial-(?P<rand>[A-Za-z0-9_]+)$')
#: Modes of a new partial file and folder, less the process's umask as for any ``open``
#: or ``mkdir``: the finished output has the permissions of the user's other files.
#: (``tempfile.mkstemp`` and ``mkdtemp`` make private 0600 / 0700 temporaries, and the
#: rename carried that into the output: a bag or a result that another account, a ROS
#: launch user or a container, could not read.)
FILE_MODE, DIR_MODE = 0o666, 0o777
#: Random names tried before giving up (8 hex digits each: a clash is already rare).
_NAME_ATTEMPTS = 100
#: Seconds of slack between a process's start time (1/100 s ticks, boot time in whole
#: seconds) and a file's modification time.
_CLOCK_SLACK_S = 2.0


def _host() -> str:
    return re.sub(r'[^A-Za-z0-9_.]', '_', socket.gethostname()) or 'host'


def partial_prefix(out: str | os.PathLike, pid: int | None = None) -> str:
    """The name prefix of the partial output for ``out`` of this process (or of ``pid`` on
    this host)."""
    return f'.{Path(out).name}{MARK}{_host()}-{os.getpid() if pid is None else pid}-'


def _create_partial(out: str | os.PathLike, create, what: str):
    """``create(path)`` at a fresh hidden partial name of ``out`` (a random hex suffix,
    tried again on the rare clash); its result."""
    out = Path(out)
    for _ in range(_NAME_ATTEMPTS):
        name = out.parent / (partial_prefix(out) + secrets.token_hex(4))
        try:
            return create(name)
        except FileExistsError:
            continue
    raise FileExistsError(errno.EEXIST, f'no free name for a partial {what}', str(out))


def make_partial_file(out: str | os.PathLike) -> tuple[int, Path]:
    """Create the hidden partial file of ``out`` beside it (the parent must exist), with
    the mode a new file of this process gets (``FILE_MODE`` less the umask).

    Returns:
        (an open descriptor for reading and writing; its path).

    Raises:
        OSError: The file cannot be created (read-only or missing parent, ...).
    """
    flags = os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, 'O_CLOEXEC', 0)
    return _create_partial(out, lambda name: (os.open(name, flags, FILE_MODE), name), 'file')


def make_partial_dir(out: str | os.PathLike) -> Path:
    """Create the hidden partial folder of ``out`` beside it (the parent must exist), with
    the mode a new folder of this process gets (``DIR_MODE`` less the umask).

    Raises:
        OSError: The folder cannot be created (read-only or missing parent, ...).
    """
    def mkdir(name: Path) -> Path:
        os.mkdir(name, DIR_MODE)
        return name
    return _create_partial(out, mkdir, 'folder')


@dataclass(frozen=True)
class Leftover:
    """A partial output found beside an output.

    Attributes:
        path: The hidden folder (or file).
        removed: True when it was provably stale and has been removed.
        reason: Why it was removed, or why it was kept.
        in_use: Its writer provably runs (not a leftover: nothing to report).
    """

    path: Path
    removed: bool
    reason: str
    in_use: bool = False

    @property
    def remove_command(self) -> str:
        """The shell command that removes it."""
        return f'rm -rf -- {shlex.quote(str(self.path))}'

    def message(self) -> str:
        """One line for the user."""
        if self.removed:
            return f'removed the leftover partial output {self.path} ({self.reason})'
        return (f'leftover partial output {self.path} ({self.reason}); if no other run '
                f'writes it, remove it with: {self.remove_command}')


def _boot_time_s() -> float | None:
    try:
        for line in Path('/proc/stat').read_text().splitlines():
            if line.startswith('btime '):
                return float(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return None


def _process_start_s(pid: int) -> float | None:
    """Wall-clock start time of a running process (None: unknown, e.g. not Linux)."""
    boot = _boot_time_s()
    if boot is None:
        return None
    try:
        stat = Path(f'/proc/{pid}/stat').read_text()
        ticks = int(stat.rsplit(')', 1)[1].split()[19])
        return boot + ticks / os.sysconf('SC_CLK_TCK')
    except (OSError, ValueError, IndexError):
        return None


def _pid_runs(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, OSError):
        return True            # exists (another user's), or unknowable: assume it runs
    return True


def _last_write_s(path: Path) -> float:
    """Latest modification time in a tree (the writer was alive then)."""
    latest = path.lstat().st_mtime
    if path.is_dir() and not path.is_symlink():
        for root, dirs, files in os.walk(path):
            for name in dirs + files:
                try:
                    latest = max(latest, os.lstat(os.path.join(root, name)).st_mtime)
                except OSError:
                    pass
    return latest


def _staleness(path: Path, host: str, pid: int) -> tuple[str | None, bool]:
    """``(why path is provably stale or None, whether its writer provably runs)``."""
    if host != _host():
        return None, False
    if not _pid_runs(pid):
        return f'its writer, pid {pid}, no longer runs', False
    started = _process_start_s(pid)
    if started is None:
        return None, False
    if started > _last_write_s(path) + _CLOCK_SLACK_S:
        return f'pid {pid} now belongs to a process started after it was last written', False
    # Alive with this pid when the folder was last written, and alive now: the writer.
    return None, True


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink()


def sweep_partials(folder: str | os.PathLike, remove: bool = True,
                   name: str | None = None) -> list[Leftover]:
    """Find the hidden partial outputs in ``folder``; remove the provably stale ones.

    Args:
        folder: Where the outputs are written (the parent of ``--out``).
        remove: Remove the stale ones (False: only report).
        name: Only the partial outputs of the output with this file name (None: all).

    Returns:
        One :class:`Leftover` per partial output found, removed or kept (with the reason).
        A folder that cannot be listed gives an empty list (the write that follows
        reports the real problem).
    """
    folder = Path(folder)
    try:
        entries = sorted(p for p in folder.iterdir() if MARK in p.name)
    except OSError:
        return []
    found = []
    for path in entries:
        owned = _OWNED.match(path.name)
        if name is not None:
            named = owned or _LEGACY.match(path.name)
            if named is None or named['name'] != name:
                continue           # another output's
        if owned is None:
            if _LEGACY.match(path.name):
                found.append(Leftover(path, False, 'written before partial outputs named '
                                                   'their writer; its writer is unknown'))
            continue
        try:
            stale, in_use = _staleness(path, owned['host'], int(owned['pid']))
        except OSError:
            continue           # vanished meanwhile (its writer finished or removed it)
        if stale is None:
            if owned['host'] != _host():
                why = f'written on host {owned["host"]}'
            elif in_use:
                why = f'its writer, pid {owned["pid"]}, runs'
            else:
                why = f'pid {owned["pid"]} runs, whether as its writer is unknown'
            found.append(Leftover(path, False, why, in_use))
            continue
        if not remove:
            found.append(Leftover(path, False, stale))
            continue
        try:
            _remove(path)
        except FileNotFoundError:
            continue
        except OSError as err:
            found.append(Leftover(path, False, f'{stale}, but removing it failed: '
                                               f'{err.strerror or err}'))
            continue
        found.append(Leftover(path, True, stale))
    return found


def sweep_and_report(out: str | os.PathLike, prog: str | None, stream=None,
                     same_output: bool = False) -> list[Leftover]:
    """:func:`sweep_partials` in the folder of ``out``, one line per leftover on stderr.

    What the writers call before they write: a removed leftover is said, a kept one comes
    with the command that removes it.

    Args:
        out: The output about to be written.
        prog: Program name that starts each line (None: none).
        stream: Where the lines go (default: ``sys.stderr``).
        same_output: Only the leftovers of ``out`` itself (the file writers: their folder
            may be anyone's); False: every partial output in the folder (the bag writers).
    """
    stream = sys.stderr if stream is None else stream
    found = sweep_partials(Path(out).parent, name=Path(out).name if same_output else None)
    for leftover in found:
        if not leftover.in_use:        # another run writing beside us is no news
            print(f'{prog}: {leftover.message()}' if prog else leftover.message(),
                  file=stream)
    return found
