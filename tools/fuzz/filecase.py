"""One corrupt input for one tool, and what a correct tool does with it."""
from __future__ import annotations

import os
import shutil
import subprocess
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from gnsscam_ros.io.partials import partial_prefix

from .corrupt_inputs import dead_pid


@dataclass
class FileCase:
    """A tool run on a corrupt input.

    Attributes:
        tool: Key of :data:`.tools.TOOLS`.
        name: What was corrupted and how (``bag_truncated``).
        argv: The tool's arguments.
        expect: Exit codes the tool documents for this input.
        names: Strings of which the error output must hold one (the file's path or name)
            when the tool refuses the input; empty: not checked.
        line: Line number the error must give (``FILE:LINE`` or ``line N``), or None.
        protect: Files that must be the same afterwards (inputs, existing outputs).
        watch: Folders in which nothing new may be left behind, apart from ``allowed``.
        allowed: Paths that may appear (the outputs of a successful run).
        stale: Leftovers of an earlier killed run that must be gone afterwards or named in
            the output (with the command to remove them).
        read_only: Folders made read-only for the run (for root too: :func:`read_only`).
        isolate: Run as a subprocess even when others run in this process (memory bombs).
        check: ``check(outcome) -> str | None``: a further check of a successful run.
    """

    tool: str
    name: str
    argv: list[str]
    expect: tuple[int, ...]
    names: list[str] = field(default_factory=list)
    line: int | None = None
    protect: list[Path] = field(default_factory=list)
    watch: list[Path] = field(default_factory=list)
    allowed: list[Path] = field(default_factory=list)
    stale: list[Path] = field(default_factory=list)
    read_only: list[Path] = field(default_factory=list)
    isolate: bool = False
    check: Callable | None = None


def named(*paths) -> list[str]:
    """Acceptable ways for an error to name ``paths``: full path, file name, or the full
    path of the folder it would be in (``cannot create /sys/x``)."""
    out = []
    for p in paths:
        out += [str(p), Path(p).name]
        if len(Path(p).parts) > 2:
            out.append(str(Path(p).parent))
    return [s for s in out if s]


def copy_tree(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


@contextmanager
def read_only(folders: list[Path]):
    """The folders read-only while the block runs: mode 0555, and for root (whom modes do
    not stop) the immutable attribute (``chattr +i``). Yields False when a folder could not
    be made read-only (the case is then not run)."""
    done, ok = [], True
    try:
        for folder in folders:
            folder.chmod(0o555)
            if os.geteuid() == 0:
                res = subprocess.run(['chattr', '+i', str(folder)], capture_output=True)
                ok = ok and res.returncode == 0
            done.append(folder)
        yield ok
    finally:
        for folder in done:
            if os.geteuid() == 0:
                subprocess.run(['chattr', '-i', str(folder)], capture_output=True)
            folder.chmod(0o755)


def killed_writer_leftovers(rng, out: Path) -> list[Path]:
    """1-3 hidden partial files of ``out`` as a writer SIGKILLed on this host leaves them
    (``.NAME.partial-HOST-PID-*`` with the pid of a process that has ended): the next
    write of ``out`` must remove them."""
    ended = dead_pid()
    made = []
    for _ in range(int(rng.integers(1, 4))):
        path = out.parent / f'{partial_prefix(out, ended)}{rng.integers(1 << 30):x}'
        path.write_bytes(rng.bytes(int(rng.integers(1, 4096))))
        made.append(path)
    return made


def all_removed(paths: list[Path], then: Callable | None = None) -> Callable:
    """``check(outcome)``: every path in ``paths`` is gone, then ``then(outcome)``."""
    def check(outcome) -> str | None:
        kept = [p.name for p in paths if os.path.lexists(p)]
        if kept:
            return f'dead writers\' leftovers kept: {kept}'
        return then(outcome) if then is not None else None
    return check
