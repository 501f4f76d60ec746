"""Readable tables and safe JSON output for the evaluation commands."""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path


class OutputExistsError(FileExistsError):
    """An output file exists and overwriting was not asked for."""


def write_json_atomic(path: Path, data, force: bool = False) -> Path:
    """Write JSON to ``path`` via a temporary file and an atomic rename.

    A crash or Ctrl-C never leaves a half-written file, and an existing file is replaced
    only with ``force``.

    Raises:
        OutputExistsError: ``path`` exists and ``force`` is False.
    """
    path = Path(path)
    if path.exists() and not force:
        raise OutputExistsError(f'{path} exists; pass --force to replace it')
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f'.{path.name}.', dir=path.parent)
    try:
        with os.fdopen(fd, 'w', encoding='utf-8') as handle:
            json.dump(data, handle, indent=2, allow_nan=False, default=_jsonable)
            handle.write('\n')
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_npz_atomic(path: Path, **arrays) -> Path:
    """Write a compressed-free .npz via a temporary file and an atomic rename (cache use)."""
    import numpy as np
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f'.{path.name}.', suffix='.npz', dir=path.parent)
    try:
        with os.fdopen(fd, 'wb') as handle:
            np.savez(handle, **arrays)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def _jsonable(value):
    """numpy scalars and arrays to plain JSON values."""
    if hasattr(value, 'tolist'):
        return value.tolist()
    raise TypeError(f'{type(value).__name__} is not JSON serialisable')


def _fmt(value, digits: int = 2) -> str:
    if value is None:
        return '-'
    if isinstance(value, float):
        return f'{value:.{digits}f}'
    return str(value)


def format_table(headers: list[str], rows: list[list]) -> str:
    """A plain-text table with right-aligned columns."""
    cells = [[_fmt(c) for c in row] for row in rows]
    widths = [max(len(h), *(len(r[i]) for r in cells)) if cells else len(h)
              for i, h in enumerate(headers)]
    line = '  '.join(h.rjust(w) for h, w in zip(headers, widths))
    out = [line, '-' * len(line)]
    out += ['  '.join(c.rjust(w) for c, w in zip(r, widths)) for r in cells]
    return '\n'.join(out)


def integrity_rows(label: str, integrity: dict) -> list[list]:
    """Rows of the integrity table (one per alert limit) of one run."""
    return [[label, limit, m['p_fa'], m['p_mi'], m['failure_ratio'], m['failure_error_m'],
             m['bound_gap'], f"{m['faults']}/{m['epochs']}"]
            for limit, m in integrity.items()]


INTEGRITY_HEADERS = ['run', 'AL [m]', 'P_FA', 'P_MI', 'fail ratio', 'fail err [m]',
                     'bound gap', 'err>AL/epochs']
