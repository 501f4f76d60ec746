"""Evaluation report rows: integrity and protection-level table rows, Stanford counts."""
from __future__ import annotations


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
