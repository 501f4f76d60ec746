"""The figures of ``docs/rinex.md`` in one result file, with its provenance.

Usage::

    python -m gnsscam_ros.evaluation.rinex_report --out docs/results/rinex.json \\
        --orbits slac:NAV:SP3:CLK --station slac_G=slac_G.json [--station NAME=JSON ...]

``--orbits`` runs :func:`.orbits.compare`; each ``--station`` takes the ``station`` and
``preprocessing`` sections of a ``gnsscam_eval rinex --json`` result (the command line that
wrote it is the caller's to record: ``--note``). The file holds the date, the host and
this command line; ``test/test_rinex_docs.py`` fails when ``docs/rinex.md`` and the file
disagree.
"""
from __future__ import annotations

import argparse
import datetime
import json
import platform
import sys
from pathlib import Path

from ..datasets.errors import DatasetError
from ..io.atomic import OutputExistsError, write_json_atomic
from .orbits import compare


def render_tables(result: dict) -> str:
    """The Markdown tables of ``docs/rinex.md`` from a result file (the test compares)."""
    lines = ['| orbits | samples | 3D RMS [m] (target <= 2) | max [m] | clock samples | '
             'clock RMS [m] (target <= 3) | clock RMS [ns] |', '|---|---|---|---|---|---|---|']
    for name, o in sorted(result['orbits'].items()):
        lines.append(f"| {name} | {o['orbit_samples']} | {o['orbit_3d_rms_m']:.2f} | "
                     f"{o['orbit_3d_max_m']:.2f} | {o['clock_samples']} | "
                     f"{o['clock_rms_m']:.2f} | {o['clock_rms_ns']:.2f} |")
    lines += ['', '| station run | epochs | WLS horizontal RMS [m] (<= 3) | WLS vertical RMS [m] '
              '(<= 6) | filter horizontal RMS [m] (<= WLS) | filter median horizontal error '
              '[m] | median PL [m] | PL / error (<= 3) | MI rate (<= 0.10) |',
              '|---|---|---|---|---|---|---|---|---|']
    for name, st in sorted(result['stations'].items()):
        f = st['station']
        lines.append(f"| {name} | {st['epochs']} | {f['wls_horizontal_rms_m']:.2f} | "
                     f"{f['wls_vertical_rms_m']:.2f} | {f['filter_horizontal_rms_m']:.2f} | "
                     f"{f['filter_median_horizontal_error_m']:.2f} | "
                     f"{f['median_protection_level_m']:.2f} | {f['pl_to_error_ratio']:.1f} | "
                     f"{f['mi_rate']:.3f} |")
    return '\n'.join(lines) + '\n'


def main(argv: list[str] | None = None) -> int:
    """Exit 0 written, 3 bad input, 4 output refused."""
    parser = argparse.ArgumentParser(prog='python -m gnsscam_ros.evaluation.rinex_report')
    parser.add_argument('--out', type=Path, help='result file to write')
    parser.add_argument('--orbits', metavar='NAME:NAV:SP3:CLK', action='append', default=[])
    parser.add_argument('--station', metavar='NAME=JSON', action='append', default=[])
    parser.add_argument('--note', action='append', default=[],
                        help='free text kept in the file (e.g. the eval command lines)')
    parser.add_argument('--force', action='store_true')
    parser.add_argument('--markdown', type=Path, metavar='JSON',
                        help='only print the tables of an existing result file')
    args = parser.parse_args(argv if argv is not None else sys.argv[1:])
    if args.markdown is not None:
        print(render_tables(json.loads(args.markdown.read_text())), end='')
        return 0
    if args.out is None:
        parser.error('--out is required (or --markdown)')
    result = {'date': datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds'),
              'host': platform.node(), 'machine': platform.machine(),
              'command': 'python -m gnsscam_ros.evaluation.rinex_report ' + ' '.join(
                  argv if argv is not None else sys.argv[1:]),
              'notes': args.note, 'orbits': {}, 'stations': {}}
    try:
        for spec in args.orbits:
            name, nav, sp3, clk = spec.split(':')
            result['orbits'][name] = compare([Path(nav)], Path(sp3), Path(clk))
        for spec in args.station:
            name, path = spec.split('=', 1)
            try:
                data = json.loads(Path(path).read_text())
            except (OSError, ValueError) as err:
                raise DatasetError(f'{path}: cannot read an evaluation result: {err}') from err
            result['stations'][name] = {'station': data['station'],
                                        'preprocessing': data['preprocessing'],
                                        'epochs': data['epochs']}
    except (DatasetError, ValueError, KeyError) as err:
        print(f'rinex_report: {err}', file=sys.stderr)
        return 3
    try:
        write_json_atomic(args.out, result, force=args.force)
    except (OSError, OutputExistsError, ValueError) as err:
        print(f'rinex_report: cannot write {args.out}: {err}', file=sys.stderr)
        return 4
    print(f'wrote {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
