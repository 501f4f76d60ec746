"""Files written whole or not at all: atomic JSON, CSV and npz writers.

Every writer goes through :func:`atomic_output`: a temporary file beside the target that
replaces it by rename, so a crash or Ctrl-C never leaves a half-written file, and an
existing file is replaced only when asked (``force``). The temporary file is named as
:mod:`.partials` names partial outputs, ``.NAME.partial-HOST-PID-XXXXXXXX``: one that a
SIGKILL leaves behind is removed by the next write of the same output once its writer
provably no longer runs (and reported with the command that removes it when that cannot
be proved).
"""
from __future__ import annotations

import csv
import json
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from .partials import make_partial_file, sweep_and_report


class OutputExistsError(FileExistsError):
    """An output file exists and overwriting was not asked for."""


@contextmanager
def atomic_output(path: Path, force: bool = False, mode: str = 'w', **open_kwargs):
    """An open temporary file beside ``path`` that replaces it atomically on success.

    A crash, an exception or Ctrl-C inside the block leaves no half-written file (the
    temporary one is removed), and an existing ``path`` is replaced only with ``force``.
    Leftovers of killed writes of ``path`` are swept first (:mod:`.partials`; one line on
    stderr for each).

    Raises:
        OutputExistsError: ``path`` exists and ``force`` is False.
    """
    path = Path(path)
    if path.exists() and not force:
        raise OutputExistsError(f'{path} exists; pass --force to replace it')
    path.parent.mkdir(parents=True, exist_ok=True)
    sweep_and_report(path, None, same_output=True)
    fd, tmp = make_partial_file(path)
    try:
        with os.fdopen(fd, mode, **open_kwargs) as handle:
            yield handle
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def check_writable(path: Path) -> None:
    """Raise the OSError that writing ``path`` would meet, before any work is done.

    Probes the folder (or its nearest existing ancestor, which the writers create the rest
    of) with an anonymous temporary file, so a read-only or special folder is found at
    once, not after an hour of computing; nothing is left behind. Permission bits do not
    stop root, so this asks the file system itself.

    Raises:
        OSError: naming ``path``: the folder is not a folder or refuses new files.
    """
    path = Path(path)
    folder = path.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise NotADirectoryError(20, f'{folder} is not a folder', str(path))
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as err:
        raise type(err)(err.errno, err.strerror, str(path)) from err


def write_json_atomic(path: Path, data, force: bool = False) -> Path:
    """Write JSON to ``path`` via a temporary file and an atomic rename.

    A crash or Ctrl-C never leaves a half-written file, and an existing file is replaced
    only with ``force``. Infinite floats (e.g. a protection level that does not exist) are
    written as the strings ``"inf"``/``"-inf"`` (strict JSON has no infinity; ``float()``
    reads them back); NaN is refused.

    Raises:
        OutputExistsError: ``path`` exists and ``force`` is False.
    """
    with atomic_output(path, force, encoding='utf-8') as handle:
        json.dump(_finite_json(data), handle, indent=2, allow_nan=False, default=_jsonable)
        handle.write('\n')
    return Path(path)


def write_npz_atomic(path: Path, **arrays) -> Path:
    """Write a compressed-free .npz via a temporary file and an atomic rename (cache use)."""
    with atomic_output(path, force=True, mode='wb') as handle:   # no '.npz' appended
        np.savez(handle, **arrays)
    return Path(path)


def _finite_json(value):
    """``value`` with every infinite float (also in numpy arrays) as "inf"/"-inf"."""
    if isinstance(value, dict):
        return {k: _finite_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_json(v) for v in value]
    if hasattr(value, 'tolist') and not isinstance(value, (str, bytes)):
        return _finite_json(value.tolist())
    if isinstance(value, float) and value in (float('inf'), float('-inf')):
        return 'inf' if value > 0 else '-inf'
    return value


def _jsonable(value):
    """numpy scalars and arrays to plain JSON values."""
    if hasattr(value, 'tolist'):
        return value.tolist()
    raise TypeError(f'{type(value).__name__} is not JSON serialisable')


def write_csv_atomic(path: Path, header: list[str], rows, force: bool = False) -> Path:
    """Write a CSV table via a temporary file and an atomic rename.

    Same policy as :func:`write_json_atomic`. Floats are written with ``repr`` so that
    reading them back gives the identical value; None and NaN become an empty field, which
    spreadsheet and pandas readers take as missing. Infinities stay ``inf``/``-inf``
    (``float()`` reads them back).

    Args:
        path: Output CSV.
        header: Column names.
        rows: Iterable of sequences, each as long as ``header`` (may be a generator; it is
            consumed while writing).
        force: Replace an existing ``path``.

    Raises:
        OutputExistsError: ``path`` exists and ``force`` is False.
        ValueError: A row's length differs from the header's (nothing is written).
    """
    # newline='': the csv module writes its own line endings.
    with atomic_output(path, force, encoding='utf-8', newline='') as handle:
        writer = csv.writer(handle)
        writer.writerow(header)
        for number, row in enumerate(rows, start=1):
            cells = [_csv_cell(value) for value in row]
            if len(cells) != len(header):
                raise ValueError(f'{path}: row {number} has {len(cells)} fields, '
                                 f'the header {len(header)}')
            writer.writerow(cells)
    return Path(path)


def _csv_cell(value) -> str:
    """One CSV field: None/NaN empty, floats exact (repr), numpy scalars as plain values."""
    if value is None:
        return ''
    if hasattr(value, 'item') and not hasattr(value, '__len__'):
        value = value.item()          # numpy scalar: repr would read 'np.float64(...)'
    if isinstance(value, float):
        return '' if value != value else repr(value)   # NaN is the only x != x
    return str(value)
