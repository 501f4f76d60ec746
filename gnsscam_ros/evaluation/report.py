"""Readable tables and safe JSON output for the evaluation commands."""
from __future__ import annotations

import csv
import json
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path


class OutputExistsError(FileExistsError):
    """An output file exists and overwriting was not asked for."""


@contextmanager
def atomic_output(path: Path, force: bool = False, mode: str = 'w', suffix: str = '',
                  **open_kwargs):
    """An open temporary file beside ``path`` that replaces it atomically on success.

    A crash, an exception or Ctrl-C inside the block leaves no half-written file (the
    temporary one is removed), and an existing ``path`` is replaced only with ``force``.

    Raises:
        OutputExistsError: ``path`` exists and ``force`` is False.
    """
    path = Path(path)
    if path.exists() and not force:
        raise OutputExistsError(f'{path} exists; pass --force to replace it')
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f'.{path.name}.', suffix=suffix, dir=path.parent)
    try:
        with os.fdopen(fd, mode, **open_kwargs) as handle:
            yield handle
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


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
    import numpy as np
    with atomic_output(path, force=True, mode='wb', suffix='.npz') as handle:
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


def protection_level_rows(label: str, pl: dict) -> list[list]:
    """One row of the protection-level table (:func:`protection_level_headers`)."""
    key = f"{pl['alert_limit_m']:g}"
    hmi = pl['hmi_given_available'][key]
    flag = pl.get('flag_ok')
    return [[label, pl['epochs'], pl['mi_rate'], pl['median_m'], pl['p95_m']]
            + [pl['availability'][k] for k in pl['availability']]
            + [f"{hmi['hmi_epochs']}/{hmi['available_epochs']}",
               f"{flag['error_above_al_epochs']}/{flag['ok_epochs']}" if flag else None]]


def protection_level_headers(pl: dict) -> list[str]:
    """Headers of the protection-level table of a ``protection_level`` block."""
    key = f"{pl['alert_limit_m']:g}"
    return (['run', 'epochs', 'MI rate', 'PL p50 [m]', 'PL p95 [m]']
            + [f'avail {k} m' for k in pl['availability']]
            + [f'err>{key}|PL<={key}', f'err>{key}|OK'])


def stanford_line(pl: dict) -> str:
    """The Stanford counts of a ``protection_level`` block, on one line."""
    st = pl['stanford']
    return (f"Stanford at AL {pl['alert_limit_m']:g} m: " + ', '.join(
        f'{k} {st[k]}' for k in STANFORD_KEYS))


INTEGRITY_HEADERS = ['run', 'AL [m]', 'P_FA', 'P_MI', 'fail ratio', 'fail err [m]',
                     'bound gap', 'err>AL/epochs']


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


STANFORD_KEYS = ('epochs', 'nominal', 'mi', 'hmi', 'unavailable', 'unavailable_mi',
                 'no_pl')


def stanford_counts(error_m, protection_level_m, alert_limit_m: float) -> dict[str, int]:
    """Epoch counts per region of the Stanford (integrity) diagram.

    Standard definitions (as in the WAAS/EGNOS Stanford-ESA plots), with PE the horizontal
    position error and PL the horizontal protection level, both [m], AL the alert limit:

    - ``nominal``: PE <= PL <= AL (normal operation).
    - ``mi``: PL < PE <= AL (misleading information, still within the alert limit).
    - ``hmi``: PL <= AL < PE (hazardously misleading information).
    - ``unavailable``: PL > AL and PE <= PL (system unavailable, bound holds).
    - ``unavailable_mi``: PL > AL and PE > PL (unavailable and misleading).

    The five regions partition the epochs: they sum to ``epochs``. An epoch with a
    non-finite PL (inf or NaN: no PL was available) counts as PL = inf, i.e. as
    ``unavailable``; ``no_pl`` counts those epochs again (a subset of ``unavailable``).

    Args:
        error_m: (T,) horizontal position error [m]; must be finite (select the epochs
            with ground truth before calling).
        protection_level_m: (T,) horizontal protection level [m]; inf/NaN = none.
        alert_limit_m: Horizontal alert limit [m], finite and > 0.

    Returns:
        Plain ints (JSON-ready) under the keys of ``STANFORD_KEYS``.

    Raises:
        ValueError: Shapes differ, an error is not finite, or the alert limit is invalid.
    """
    import numpy as np
    err = np.asarray(error_m, dtype=float).ravel()
    pl = np.asarray(protection_level_m, dtype=float).ravel()
    if err.shape != pl.shape:
        raise ValueError(f'error ({err.size}) and protection level ({pl.size}) differ in '
                         'length')
    if not np.all(np.isfinite(err)):
        # Dropping them silently would make every ratio built on these counts lie.
        raise ValueError('non-finite position error; select epochs with ground truth')
    if not (np.isfinite(alert_limit_m) and alert_limit_m > 0):
        raise ValueError(f'alert limit must be finite and > 0, got {alert_limit_m!r}')
    no_pl = ~np.isfinite(pl)
    pl = np.where(no_pl, np.inf, pl)       # NaN compares False everywhere: make it inf
    bounded = err <= pl
    available = pl <= alert_limit_m
    within = err <= alert_limit_m
    return {
        'epochs': int(err.size),
        'nominal': int(np.sum(available & bounded)),
        'mi': int(np.sum(available & ~bounded & within)),
        'hmi': int(np.sum(available & ~within)),   # PE > AL >= PL implies PE > PL
        'unavailable': int(np.sum(~available & bounded)),
        'unavailable_mi': int(np.sum(~available & ~bounded)),
        'no_pl': int(np.sum(no_pl)),
    }
