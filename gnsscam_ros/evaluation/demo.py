"""The main job (``./run demo``): evaluate the filter on the real and the emulated data.

Runs the filter with its defaults on the smartLoc Berlin run (when the data folder is
there) and on the emulated urban drive with 6 faulty satellites of 100 m bias, each next
to the robust snapshot WLS baseline of the same run, prints one results table and writes
the JSON of each run into a new time-stamped folder (nothing is overwritten).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from ..core.filter import FilterConfig
from ..datasets.emulated import make_emulated_drive
from ..datasets.errors import DatasetError
from ..datasets.smartloc import discover_files, load_smartloc
from .cli import DEFAULT_ALERT_LIMITS_M, print_result
from .evaluate import evaluate_drive
from .report import format_table, write_json_atomic


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='gnsscam demo', description=__doc__.split('\n')[0])
    parser.add_argument('--shared', type=Path, default=Path('../shared'),
                        help='folder holding data/smartloc (default %(default)s)')
    parser.add_argument('--out', type=Path, default=Path('out'),
                        help='results root; each run writes a new sub-folder')
    parser.add_argument('--seed', type=int, default=1)
    args = parser.parse_args(argv)
    config = FilterConfig(alert_limit_m=DEFAULT_ALERT_LIMITS_M[0],
                          extra_alert_limits_m=DEFAULT_ALERT_LIMITS_M[1:])
    out_dir = args.out / time.strftime('demo-%Y%m%d-%H%M%S', time.gmtime())
    runs = []
    smartloc_dir = args.shared / 'data' / 'smartloc'
    if smartloc_dir.is_dir():
        try:
            runs.append(('smartloc', load_smartloc(*discover_files(smartloc_dir))))
        except DatasetError as err:
            print(f'demo: skipping smartLoc: {err}', file=sys.stderr)
    else:
        print(f'demo: {smartloc_dir} not found, running the emulated drive only',
              file=sys.stderr)
    runs.append(('emulated', make_emulated_drive(3, faults=6, bias_m=100.0)))
    summary = []
    for key, drive in runs:
        result = evaluate_drive(drive, config, seed=args.seed, progress=True)
        print_result(drive.name, result)
        print()
        path = write_json_atomic(out_dir / f'{key}.json', result)
        summary.append([drive.name, result['epochs'], result['rmse_2d_m'],
                        result['baseline_wls']['rmse_2d_m'], result['rmse_2d_ratio_to_wls'],
                        result['rmse_3d_m'], result['integrity']['8']['failure_ratio'],
                        result['integrity']['16']['failure_ratio'], str(path)])
    print(format_table(['drive', 'epochs', 'RMSE 2D [m]', 'WLS 2D [m]', 'ratio',
                        'RMSE 3D [m]', 'fail 8 m', 'fail 16 m', 'json'], summary))
    return 0


if __name__ == '__main__':
    sys.exit(main())
