"""``python -m gnsscam_ros.evaluation.docs``: the figures of the documentation, rendered
from the result files the tools wrote, never typed.

Every file in ``docs/results/`` is the ``--json`` of one command (``gnsscam_eval smartloc``,
``emulated``, ``robustness``, ``campaign``, the demo's ``summary.json``, ``gnsscam_bench``,
``evaluation.rinex_report``) and holds its date, machine and command line
(:mod:`gnsscam_ros.io.provenance`). This command renders from them:

* ``docs/results.md`` whole: a table of the sources, then one section per result;
* the block of ``README.md`` between ``<!-- results:begin -->`` and
  ``<!-- results:end -->`` (the demo's headline figures).

Usage::

    python -m gnsscam_ros.evaluation.docs               # write both
    python -m gnsscam_ros.evaluation.docs --check       # exit 1 when either is stale
    python -m gnsscam_ros.evaluation.docs --import-demo out/demo-20261202T001500Z

``--import-demo DIR`` first copies a finished demo run's ``summary.json`` to
``docs/results/demo.json`` and its figures to ``docs/figures/demo_*.png`` (replacing the
previous ones). ``test/test_results_docs.py`` fails when a rendered page differs from what
its result files give. Exit codes: 0 done (or up to date), 1 ``--check`` found a stale page,
3 a result file that cannot be read or lacks its provenance, 4 a page that cannot be written.
"""
from __future__ import annotations

import argparse
import json
import math
import re
import shutil
import sys
from pathlib import Path

from ..io.atomic import atomic_output, write_json_atomic
from ..io.tables import format_table
from .campaign_summary import campaign_tables
from .plots import dataset_title
from .rinex_report import render_tables as rinex_tables

EXIT_OK, EXIT_STALE, EXIT_INPUT, EXIT_OUTPUT = 0, 1, 3, 4
ROOT = Path(__file__).resolve().parents[2]
#: The demo's figures kept in docs/figures: (dataset, file in its folder).
DEMO_FIGURES = (('emulated', 'trajectory.png'), ('emulated', 'error_pl_nodes.png'),
                ('smartloc', 'error_pl_nodes.png'))
#: ``gnsscam_eval smartloc`` variants of docs/results (file stem -> what differs).
VARIANTS = {
    'smartloc': 'the default (learned error model, learned bias hypotheses, M = 200)',
    'variant_paper': "the paper: motion samples only, M = 10, the paper's approximation",
    'variant_motion_only_exact': 'motion samples only, M = 10, exact inverse',
    'variant_cn0_bias': 'bias hypotheses sized by C/N0 constants calibrated on smartLoc',
    'variant_stated_errors': "the receiver's stated variances and the C/N0 bias constants",
    'variant_independent_epochs': 'every GNSS epoch independent (no correlation time)',
}
BEGIN, END = '<!-- {}:begin -->', '<!-- {}:end -->'


class ResultError(ValueError):
    """A result file that cannot be rendered (unreadable, or without its provenance)."""


# ============================================================================ reading
def load_results(folder: Path) -> dict[str, dict]:
    """Every ``*.json`` of ``folder`` by file stem.

    Raises:
        ResultError: A file is not JSON or says neither when nor how it was made.
    """
    results = {}
    for path in sorted(Path(folder).glob('*.json')):
        try:
            data = json.loads(path.read_text(encoding='utf-8'))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            raise ResultError(f'{path}: cannot be read as JSON: {err}') from None
        if not isinstance(data, dict) or not data.get('date') or not command_of(data):
            raise ResultError(f'{path}: no date or command line (write it with the tool\'s '
                              '--json, which records them)')
        results[path.stem] = data
    return results


def command_of(result: dict) -> str:
    """The command line that wrote a result (``command_line``; rinex_report: ``command``)."""
    line = result.get('command_line') or result.get('command')
    return line if isinstance(line, str) and ' ' in line else ''


def machine_of(result: dict) -> str:
    """Host, CPUs and the load average at the start, in a few words."""
    machine = result.get('machine')
    if isinstance(machine, dict):
        load = machine.get('load_average_at_start')
        text = f"{machine.get('hostname', '?')}, {machine.get('cpus', '?')} CPUs"
        return text + (f', load {load[0]:.1f} at the start' if load else '')
    return f"{result.get('host', '?')} ({machine or '?'})"


def under_load(result: dict) -> bool:
    """True when the machine was busy at the start (load average above half its CPUs):
    its timing figures are not speed figures."""
    machine = result.get('machine')
    if not isinstance(machine, dict) or not machine.get('load_average_at_start'):
        return True
    return machine['load_average_at_start'][0] > 0.5 * (machine.get('cpus') or 1)


# ========================================================================== rendering
def _num(value, digits: int = 2) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return '-'
    if isinstance(value, float):
        return f'{value:.{digits}f}'
    return str(value)


def _rate(value) -> str:
    """A rate or share with three decimals (two hide an MI rate of 0.004)."""
    return _num(value, 3)


def _code(text: str) -> list[str]:
    return ['```', text, '```']


def _pl_table(runs: list[tuple[str, dict]]) -> str:
    """Protection level of runs (label, ``protection_level`` block): MI rate, PL median and
    p95, availability at every alert limit, the flag's misses at its alert limit."""
    first = runs[0][1]
    limits = list(first['availability'])
    rows = []
    for label, pl in runs:
        flag = pl.get('flag_ok') or {}
        rows.append([label, pl['epochs'], _rate(pl['mi_rate']), pl['median_m'], pl['p95_m']]
                    + [_rate(pl['availability'].get(k)) for k in limits]
                    + [f"{flag.get('error_above_al_epochs')}/{flag.get('ok_epochs')}"])
    return format_table(['run', 'epochs', 'MI rate', 'PL p50 [m]', 'PL p95 [m]']
                        + [f'avail {k} m' for k in limits]
                        + [f"err>{first['alert_limit_m']:g}|OK"], rows)


def _evaluation_section(name: str, result: dict, figures: list[str]) -> list[str]:
    """One ``gnsscam_eval smartloc|emulated|rinex`` result: accuracy, integrity, PL."""
    base = result['baseline_wls']
    lines = [f"### {dataset_title(result['dataset']['name'])} (`docs/results/{name}.json`)", '',
             f"Seed {result['seed']}, N = {result['config']['n_particles']} x M = "
             f"{result['config']['n_posteriors']}.", '']
    lines += _code(format_table(
        ['epochs', 'RMSE 2D [m]', 'RMSE 3D [m]', 'p95 2D [m]', 'WLS 2D [m]', 'WLS 3D [m]',
         'ratio 2D'],
        [[result['epochs'], result['rmse_2d_m'], result['rmse_3d_m'], result['p95_2d_m'],
          base['rmse_2d_m'], base['rmse_3d_m'], result['rmse_2d_ratio_to_wls']]]))
    pl = result.get('protection_level')
    if pl:
        lines += [''] + _code(_pl_table([(name, pl)]))
    integ = result.get('integrity', {})
    if integ:
        rows = [[limit, _rate(m['p_fa']), _rate(m['p_mi']), _rate(m['failure_ratio']),
                 f"{m['faults']}/{m['epochs']}"] for limit, m in integ.items()]
        lines += [''] + _code(format_table(['AL [m]', 'P_FA', 'P_MI', 'failure ratio',
                                            'err>AL/epochs'], rows))
    lines += [''] + [f'![{Path(f).stem}]({f})' for f in figures]
    return lines


def _demo_section(demo: dict) -> list[str]:
    lines = ['## The demo (`docs/results/demo.json`)', '',
             'Each dataset converted to a bag, replayed through the four nodes (one process '
             'each) and recorded, next to the offline run of the same data, seed and '
             'configuration and the snapshot WLS:', '']
    rows = []
    for key, r in demo['results'].items():
        for label in ('nodes', 'offline'):
            m = r[label]
            pl = m['protection_level']
            rows.append([key, label, m['epochs'], m['rmse_2d_m'], m['rmse_3d_m'],
                         _rate(pl['mi_rate']), pl['median_m'], pl['p95_m']])
        w = r['wls']
        rows.append([key, 'snapshot WLS', w['epochs'], w['rmse_2d_m'], w['rmse_3d_m'],
                     None, None, None])
    lines += _code(format_table(['data', 'run', 'epochs', 'RMSE 2D [m]', 'RMSE 3D [m]',
                                 'MI rate', 'PL p50 [m]', 'PL p95 [m]'], rows))
    lines += ['', 'Availability (share of epochs with PL <= AL) at each alert limit:', '']
    lines += _code(_pl_table([(f'{key} {label}', r[label]['protection_level'])
                              for key, r in demo['results'].items()
                              for label in ('nodes', 'offline')]))
    timing = 'under load: not speed figures' if under_load(demo) else 'machine idle'
    lines += ['', f'Replay and stages ({timing}):', '']
    for key, r in demo['results'].items():
        rep = r['replay']
        lines.append(f"* {key}: {_num(rep['bag_span_s'], 0)} s of data in "
                     f"{_num(rep['wall_s'], 1)} s ({_num(rep['speed_x_real_time'], 1)}x real "
                     f"time); GNSS epochs {rep['gnss_epochs']} published, "
                     f"{rep['gnss_epochs_processed']} processed; nodes vs offline "
                     f"estimates differ by at most {r['max_estimate_difference_m']:.2g} m "
                     f"over {r['common_epochs']} epochs")
    lines.append(f"* total {_num(demo['total_s'], 0)} s")
    figures = [f'figures/demo_{key}_{name}' for key, name in DEMO_FIGURES
               if key in demo['results']]
    return lines + [''] + [f'![{Path(f).stem}]({f})' for f in figures]


def _variants_section(results: dict) -> list[str]:
    present = [k for k in VARIANTS if k in results]
    if len(present) < 2:
        return []
    rows = []
    for key in present:
        r = results[key]
        pl = r['protection_level']
        rows.append([key, r['rmse_2d_m'], r['rmse_2d_ratio_to_wls'], _rate(pl['mi_rate']),
                     pl['median_m'], pl['p95_m'], _rate(pl['availability'].get('25'))])
    lines = ['## What each variant measured (smartLoc Berlin, one filter seed)', '',
             'The same drive and seed; only what the row names differs (one run is one '
             'Monte Carlo draw: the robustness matrix has the default over ten seeds):', '']
    lines += [f'* `{k}`: {VARIANTS[k]}' for k in present] + ['']
    return lines + _code(format_table(['run', 'RMSE 2D [m]', 'ratio to WLS', 'MI rate',
                                       'PL p50 [m]', 'PL p95 [m]', 'avail 25 m'], rows))


def robustness_results(results: dict[str, dict]) -> list[str]:
    """The stems of the ``gnsscam_eval robustness`` result files: the default matrix
    (``robustness``) first, then runs of extra cells (``robustness_*``)."""
    return sorted((k for k, r in results.items() if r.get('command') == 'robustness'),
                  key=lambda k: (k != 'robustness', k))


def _robustness_section(name: str, result: dict) -> list[str]:
    rows = [[c['name'], _rate(c['mi_rate']['mean']), _rate(c['mi_rate']['upper']),
             c['rmse_ratio_to_wls'],
             c['pl_to_error_ratio'], c['cloud_calibration']['spread_to_error'],
             'yes' if c['pass'] else 'no: ' + ', '.join(
                 k for k, t in c['targets'].items() if not t['pass'])]
            for c in result['cells']]
    title = 'Robustness matrix' if name == 'robustness' else 'Robustness, extra cells'
    lines = [f'## {title} (`docs/results/{name}.json`)', '',
             f"{result['cells_passed']} of {len(result['cells'])} cells meet every target ("
             + '; '.join(f"`{k}`: {t['what']} <= {t['limit']:g}"
                         for k, t in result['targets'].items())
             + '); the full table and figure: [robustness.md](robustness.md).', '']
    return lines + _code(format_table(['cell', 'MI rate', 'MI upper', 'RMSE / WLS',
                                       'PL / error', 'spread / error', 'pass'], rows))


def render_results(results: dict[str, dict]) -> str:
    """``docs/results.md`` from the result files (by file stem)."""
    lines = ['# Results', '',
             '<!-- Generated by `python -m gnsscam_ros.evaluation.docs` from docs/results/*.json:'
             ' do not edit. test/test_results_docs.py checks it. -->', '',
             'Every figure on this page is rendered from a result file of `docs/results/`, '
             'written (`--json`) by the command this table gives, with its date and machine. '
             'To refresh one: run its command again, then '
             '`python -m gnsscam_ros.evaluation.docs` ([development.md](development.md)).', '',
             '| file | date (UTC) | machine | command |', '|---|---|---|---|']
    for name, r in results.items():
        lines.append(f"| `{name}.json` | {r['date']} | {machine_of(r)} | "
                     f"`{command_of(r)}` |")
    if 'demo' in results:
        lines += [''] + _demo_section(results['demo'])
    evaluations = [k for k in ('smartloc', 'emulated') if k in results]
    if evaluations:
        lines += ['', '## Offline evaluations (`gnsscam_eval`)', '']
        for key in evaluations:
            figures = sorted(f'figures/{Path(p).name}' for p in results[key].get('plots', []))
            lines += _evaluation_section(key, results[key], figures) + ['']
    lines += [''] + _variants_section(results)
    for name in robustness_results(results):
        lines += [''] + _robustness_section(name, results[name])
    if 'rinex' in results:
        lines += ['', '## Reference stations from RINEX (`docs/results/rinex.json`)', '',
                  'Targets and context: [rinex.md](rinex.md).', '',
                  rinex_tables(results['rinex'])]
    if 'campaign' in results:
        c = results['campaign']
        lines += ['', '## Emulated campaign (`docs/results/campaign.json`)', '']
        lines += _code(campaign_tables(c['cases'], c['intervals']))
    if 'bench' in results:
        lines += [''] + _bench_section(results['bench'])
    return '\n'.join(line.rstrip() for line in lines).strip() + '\n'


def _bench_section(bench: dict) -> list[str]:
    timing = ('under load: not speed figures' if under_load(bench)
              else 'machine idle at the start')
    rows = [[n, d['evaluations'], d['epoch_ms'], d['bare_likelihood_ms'], d['ratio'],
             d['camera_epoch_ms'], d['camera_ratio']] for n, d in bench['details'].items()]
    lines = [f'## Epoch time (`docs/results/bench.json`, {timing})', '']
    lines += _code(format_table(['N/posterior', 'M*N', 'epoch [ms]', 'bare lik [ms]', 'ratio',
                                 'camera epoch [ms]', 'camera ratio'], rows))
    default = bench.get('default_config')
    if default:
        lines += ['', f"Default configuration (N = {default['n_particles']}, M = "
                  f"{default['n_posteriors']}): {default['epoch_ms_median']:.2f} ms per epoch, "
                  f"{default['ratio_at_sn']:.2f}x the bare arithmetic of its likelihood."]
    return lines


def render_readme_block(results: dict[str, dict]) -> str:
    """The README's headline figures: the demo's nodes rows (or a pointer to make them)."""
    demo = results.get('demo')
    if demo is None:
        return ('No demo result in `docs/results/` yet: `./run demo`, then '
                '`./run python -m gnsscam_ros.evaluation.docs --import-demo out/demo-*`.')
    rows = []
    for key, r in demo['results'].items():
        m, pl = r['nodes'], r['nodes']['protection_level']
        rows.append(f"| {key} | {m['epochs']} | {_num(m['rmse_2d_m'])} m | "
                    f"{_num(r['wls']['rmse_2d_m'])} m | {_num(pl['median_m'])} m | "
                    f"{_rate(pl['mi_rate'])} |")
    first = next(iter(demo['results'].values()))
    return '\n'.join([f"The demo of {demo['date'][:10]} through the nodes (filter seed "
                      f"{first['seed']}, alert limit {first['config']['alert_limit_m']:g} m; "
                      '`docs/results/demo.json`, more in [docs/results.md](docs/results.md)):',
                      '',
                      '| data | epochs | 2D RMSE | snapshot WLS | median PL | MI rate |',
                      '|---|---|---|---|---|---|', *rows])


def replace_block(text: str, name: str, body: str) -> str:
    """``text`` with the block between the markers of ``name`` set to ``body``.

    Raises:
        ValueError: The markers are missing or out of order.
    """
    begin, end = BEGIN.format(name), END.format(name)
    pattern = re.compile(re.escape(begin) + r'.*?' + re.escape(end), re.S)
    if len(pattern.findall(text)) != 1:
        raise ValueError(f'expected one {begin} ... {end} block')
    return pattern.sub(lambda _: f'{begin}\n{body}\n{end}', text)


def rendered_pages(root: Path, results: dict[str, dict]) -> dict[Path, str]:
    """What each generated page must hold: ``docs/results.md`` and ``README.md``."""
    readme = root / 'README.md'
    return {root / 'docs' / 'results.md': render_results(results),
            readme: replace_block(readme.read_text(encoding='utf-8'), 'results',
                                  render_readme_block(results))}


def figure_sources(results: dict[str, dict]) -> dict[str, str]:
    """Each figure of ``docs/`` (path relative to it) -> the result file that names it: the
    ``--plots`` of an evaluation, the demo's imported figures, the robustness ``--figure``."""
    sources = {}
    for name, result in results.items():
        for plot in result.get('plots') or []:
            if name != 'demo':
                sources[f'figures/{Path(plot).name}'] = name
    if 'demo' in results:
        for key, figure in DEMO_FIGURES:
            if key in results['demo']['results']:
                sources[f'figures/demo_{key}_{figure}'] = 'demo'
    for name in robustness_results(results):
        if results[name].get('figure'):
            sources[Path(results[name]['figure']).name] = name
    return sources


# ============================================================================== main
def import_demo(run_dir: Path, root: Path) -> None:
    """Copy a finished demo run's summary and figures into ``docs/``.

    Raises:
        ResultError: ``run_dir`` holds no finished run (no ``summary.json``).
    """
    summary = Path(run_dir) / 'summary.json'
    if not summary.is_file():
        raise ResultError(f'{summary}: not found (a demo run that finished writes it)')
    data = json.loads(summary.read_text(encoding='utf-8'))
    write_json_atomic(root / 'docs' / 'results' / 'demo.json', data, force=True)
    for key, name in DEMO_FIGURES:
        source = Path(run_dir) / key / name
        if key in data['results'] and source.is_file():
            with atomic_output(root / 'docs' / 'figures' / f'demo_{key}_{name}', force=True,
                               mode='wb') as handle, source.open('rb') as src:
                shutil.copyfileobj(src, handle)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m gnsscam_ros.evaluation.docs',
                                     description=__doc__.split('\n')[0])
    parser.add_argument('--root', type=Path, default=ROOT, help='repository root')
    parser.add_argument('--check', action='store_true',
                        help='write nothing; exit 1 when a page differs from its results')
    parser.add_argument('--import-demo', type=Path, metavar='DIR',
                        help="copy a demo run's summary.json and figures into docs/ first")
    args = parser.parse_args(argv)
    try:
        if args.import_demo is not None and not args.check:
            import_demo(args.import_demo, args.root)
        pages = rendered_pages(args.root, load_results(args.root / 'docs' / 'results'))
    except (ResultError, ValueError, OSError, KeyError) as err:
        print(f'docs: {err}', file=sys.stderr)
        return EXIT_INPUT
    stale = [p for p, text in pages.items()
             if not p.is_file() or p.read_text(encoding='utf-8') != text]
    if args.check:
        for path in stale:
            print(f'docs: {path} differs from its result files (render it)', file=sys.stderr)
        return EXIT_STALE if stale else EXIT_OK
    for path in stale:
        try:
            with atomic_output(path, force=True, encoding='utf-8') as handle:
                handle.write(pages[path])
        except OSError as err:
            print(f'docs: cannot write {path}: {err}', file=sys.stderr)
            return EXIT_OUTPUT
        print(f'wrote {path}')
    return EXIT_OK


if __name__ == '__main__':
    sys.exit(main())
