"""A campaign's integrity rates with confidence intervals, its tables and its CSV rows.

Every rate is a count over epochs, pooled over the seeds of a group (one GNSS case and
method, or every case of a method): ``rate = sum k / sum n`` with its exact
Clopper-Pearson 95 % interval (epochs taken as independent), the between-seed interval
(each seed one independent cluster, :func:`.intervals.between_seed_interval`), and the
per-seed counts. The rates (definitions in :mod:`.metrics`), per alert limit where
they have one:

* ``p_fa``: false alarms / fault-free epochs; ``p_mi``: missed identifications / faulty
  epochs; ``failure_ratio``: bound below the reference risk / epochs;
* ``mi_rate``: error > PL / epochs; ``availability``: PL <= AL / epochs.
"""
from __future__ import annotations

from .campaign import GNSS_CASES, METHODS
from .intervals import CONFIDENCE, between_seed_interval, rate_entry
from ..io.tables import format_table

#: Rates with an alert limit, from each case's ``integrity`` block.
INTEGRITY_RATES = ('p_fa', 'p_mi', 'failure_ratio')


def case_counts(metrics: dict) -> dict[tuple[str, str | None], tuple[int, int]]:
    """``{(rate, alert limit or None): (count, epochs)}`` of one case's metrics."""
    out = {}
    for limit, m in metrics['integrity'].items():
        out[('p_fa', limit)] = (m['false_alarms'], m['epochs'] - m['faults'])
        out[('p_mi', limit)] = (m['missed_identifications'], m['faults'])
        out[('failure_ratio', limit)] = (m['failures'], m['epochs'])
    pl = metrics['protection_level']
    out[('mi_rate', None)] = (pl['mi_epochs'], pl['epochs'])
    for limit, n_ok in pl['available_epochs'].items():
        out[('availability', limit)] = (n_ok, pl['epochs'])
    return out


def pooled_rates(cases: list[dict], confidence: float = CONFIDENCE) -> dict:
    """The rates of a group of cases, each seed's cases pooled into one cluster.

    Returns:
        ``{rate: entry}`` for ``mi_rate`` and ``{rate: {limit: entry}}`` for the others;
        an entry is :func:`.intervals.rate_entry` plus ``between_seeds`` (None with fewer
        than two seeds) and ``per_seed`` (``[[seed, count, n], ...]``).
    """
    by_seed: dict[tuple, dict[int, list[int]]] = {}
    for case in cases:
        for name, (k, n) in case_counts(case).items():
            acc = by_seed.setdefault(name, {}).setdefault(int(case['seed']), [0, 0])
            acc[0] += int(k)
            acc[1] += int(n)
    out: dict = {}
    for (rate, limit), seeds in by_seed.items():
        order = sorted(seeds)
        ks = [seeds[s][0] for s in order]
        ns = [seeds[s][1] for s in order]
        entry = rate_entry(sum(ks), sum(ns), confidence)
        entry['between_seeds'] = between_seed_interval(ks, ns, confidence)
        entry['per_seed'] = [[s, seeds[s][0], seeds[s][1]] for s in order]
        if limit is None:
            out[rate] = entry
        else:
            out.setdefault(rate, {})[limit] = entry
    return out


def _select(cases, **kw):
    return [c for c in cases if all(c[k] == v for k, v in kw.items())]


def gnss_cases_of(cases: list[dict]) -> list[tuple[int, float]]:
    """The GNSS cases present, in the paper's order first."""
    present = {(c['faults'], float(c['bias_m'])) for c in cases}
    return ([c for c in GNSS_CASES if c in present]
            + sorted(present - set(GNSS_CASES)))


def methods_of(cases: list[dict]) -> list[str]:
    present = {c['method'] for c in cases}
    return [m for m in METHODS if m in present] + sorted(present - set(METHODS))


def campaign_intervals(cases: list[dict], confidence: float = CONFIDENCE) -> dict:
    """Intervals of every rate per (method, GNSS case) and per method (all cases)."""
    by_case, by_method = [], {}
    for method in methods_of(cases):
        mine = _select(cases, method=method)
        by_method[method] = {'seeds': len({c['seed'] for c in mine}), 'runs': len(mine),
                             'rates': pooled_rates(mine, confidence)}
        for faults, bias in gnss_cases_of(mine):
            runs = _select(mine, faults=faults, bias_m=bias)
            by_case.append({'method': method, 'faults': faults, 'bias_m': bias,
                            'seeds': len(runs), 'rates': pooled_rates(runs, confidence)})
    return {'confidence': confidence, 'by_case': by_case, 'by_method': by_method,
            'note': 'ci95: Clopper-Pearson over epochs (independent epochs); '
                    'between_seeds: each seed one cluster (correlated epochs, '
                    'Korn-Graubard on the effective sample size)'}


def fmt_rate(entry: dict | None, counts: bool = True) -> str:
    """``0.0123 [0.0098, 0.0151] 45/3655`` (``-`` without epochs)."""
    if entry is None:
        return '-'
    if entry['rate'] is None:
        return '- 0/0' if counts else '-'
    lo, hi = entry['ci95']
    text = f"{entry['rate']:.4f} [{lo:.4f}, {hi:.4f}]"
    return f"{text} {entry['count']}/{entry['n']}" if counts else text


def fmt_between(entry: dict | None) -> str:
    """The between-seed interval and design effect of an entry."""
    between = None if entry is None else entry.get('between_seeds')
    if between is None:
        return '- (< 2 seeds)'
    lo, hi = between['ci95']
    deff = between['design_effect']
    return f"[{lo:.4f}, {hi:.4f}] deff {deff:.1f}" if deff else f'[{lo:.4f}, {hi:.4f}]'


def _case_label(faults: int, bias: float) -> list:
    return [f'{bias:g}' if faults else 'NLOS only', faults]


def _mean(values):
    values = [v for v in values if v is not None]
    return sum(values) / len(values) if values else None


def rmse_table(cases: list[dict]) -> str:
    """Table 2: RMSE of every method (mean over seeds)."""
    methods = methods_of(cases)
    rows = []
    for faults, bias in gnss_cases_of(cases):
        row = _case_label(faults, bias)
        rmse = {}
        for m in methods:
            runs = _select(cases, faults=faults, bias_m=bias, method=m)
            rmse[m] = (_mean([c['rmse_3d_m'] for c in runs]),
                       _mean([c['rmse_2d_m'] for c in runs]))
            row += list(rmse[m])
        fused, praim = rmse.get('fused', (None,))[0], rmse.get('particle_raim', (None,))[0]
        row.append(fused / praim if fused is not None and praim else None)
        rows.append(row)
    headers = ['bias [m]', 'faults']
    for m in methods:
        headers += [f'{m} 3D', f'{m} 2D']
    return ('Table 2: RMSE [m] (mean over seeds)\n'
            + format_table(headers + ['fused/PRAIM 3D'], rows))


def campaign_tables(cases: list[dict], intervals: dict | None = None) -> str:
    """Table 2 (RMSE), the integrity tables (per alert limit) and the protection-level
    table of every method with 95 % intervals and counts, and the pooled rates per method
    with their between-seed intervals."""
    intervals = intervals or campaign_intervals(cases)
    text = [rmse_table(cases)]
    by_case = intervals['by_case']
    limits = sorted({lim for g in by_case for lim in g['rates'].get('p_fa', {})}, key=float)
    for method in methods_of(cases):
        groups = [g for g in by_case if g['method'] == method]
        for limit in limits:
            rows = []
            for g in groups:
                runs = _select(cases, method=method, faults=g['faults'], bias_m=g['bias_m'])
                ints = [c['integrity'][limit] for c in runs]
                rows.append(_case_label(g['faults'], g['bias_m'])
                            + [fmt_rate(g['rates'][r][limit]) for r in INTEGRITY_RATES]
                            + [_mean([m['failure_error_m'] for m in ints]),
                               _mean([m['bound_gap'] for m in ints])])
            text += ['', f'Integrity of {method}, alert limit {limit} m: rate [95 % '
                         'Clopper-Pearson] count/epochs, pooled over seeds',
                     format_table(['bias [m]', 'faults', 'P_FA', 'P_MI', 'fail ratio',
                                   'fail err [m]', 'bound gap'], rows)]
        rows = [_case_label(g['faults'], g['bias_m'])
                + [g['seeds'], fmt_rate(g['rates']['mi_rate']),
                   fmt_between(g['rates']['mi_rate']),
                   fmt_rate(g['rates']['availability'].get(limits[0] if limits else '8'))]
                for g in groups]
        text += ['', f'Protection level of {method}: MI rate (error > PL) and availability '
                     f'at {limits[0] if limits else 8} m (PL <= AL), 95 % intervals',
                 format_table(['bias [m]', 'faults', 'seeds', 'MI rate', 'MI between seeds',
                               'availability'], rows)]
    text += ['', 'All cases pooled, per method: rate [95 % Clopper-Pearson] count/epochs; '
                 'between seeds: each seed one cluster (correlated epochs), deff = epochs '
                 'per independent epoch', pooled_table(intervals)]
    return '\n'.join(text)


def pooled_rows(intervals: dict) -> list[tuple[str, str, str | None, dict]]:
    """``(method, rate, alert limit, entry)`` of every pooled rate of every method."""
    rows = []
    for method, group in intervals['by_method'].items():
        for rate, value in group['rates'].items():
            if 'rate' in value:
                rows.append((method, rate, None, value))
            else:
                rows += [(method, rate, lim, e)
                         for lim, e in sorted(value.items(), key=lambda kv: float(kv[0]))]
    return rows


def pooled_table(intervals: dict) -> str:
    rows = [[method, rate + (f' {lim} m' if lim else ''), fmt_rate(e), fmt_between(e)]
            for method, rate, lim, e in pooled_rows(intervals)]
    return format_table(['method', 'rate', 'pooled', 'between seeds'], rows)


INTERVAL_CSV_COLUMNS = ['method', 'faults', 'bias_m', 'rate', 'alert_limit_m', 'count', 'n',
                        'value', 'ci95_low', 'ci95_high', 'seeds', 'between_low',
                        'between_high', 'design_effect']


def interval_csv_rows(intervals: dict):
    """Rows of ``intervals.csv`` (:data:`INTERVAL_CSV_COLUMNS`); the pooled rows of a
    method have empty ``faults`` and ``bias_m``."""
    groups = [(g['method'], g['faults'], g['bias_m'], g['rates'])
              for g in intervals['by_case']]
    groups += [(m, None, None, g['rates']) for m, g in intervals['by_method'].items()]
    for method, faults, bias, rates in groups:
        for rate, value in rates.items():
            items = [(None, value)] if 'rate' in value else sorted(
                value.items(), key=lambda kv: float(kv[0]))
            for limit, e in items:
                ci = e['ci95'] or [None, None]
                between = e['between_seeds'] or {}
                b_ci = between.get('ci95') or [None, None]
                yield [method, faults, bias, rate, limit, e['count'], e['n'], e['rate'],
                       ci[0], ci[1], len(e['per_seed']), b_ci[0], b_ci[1],
                       between.get('design_effect')]


RUN_CSV_COLUMNS = ['seed', 'faults', 'bias_m', 'method', 'epochs', 'gnss_epochs',
                   'rmse_2d_m', 'rmse_3d_m', 'mi_epochs', 'filter_seconds']


def run_csv(cases: list[dict]) -> tuple[list[str], list[list]]:
    """``(header, rows)`` of ``runs.csv``: one row per case with the counts of every
    rate (``<rate>_<limit>_count`` and ``_n``) next to the RMSE."""
    names = sorted({name for c in cases for name in case_counts(c)},
                   key=lambda nl: (nl[0], float(nl[1]) if nl[1] else 0.0))
    header = list(RUN_CSV_COLUMNS)
    for rate, limit in names:
        stem = rate if limit is None else f'{rate}_{limit}'
        header += [f'{stem}_count', f'{stem}_n']
    rows = []
    for c in cases:
        counts = case_counts(c)
        row = [c['seed'], c['faults'], c['bias_m'], c['method'], c['epochs'],
               c['gnss_epochs'], c['rmse_2d_m'], c['rmse_3d_m'],
               c['protection_level']['mi_epochs'], c['filter_seconds']]
        for name in names:
            row += list(counts.get(name, (None, None)))
        rows.append(row)
    return header, rows
