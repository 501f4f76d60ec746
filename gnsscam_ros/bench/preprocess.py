"""``python -m gnsscam_ros.bench.preprocess [--obs FILE --nav FILE ...]``: cost of the GNSS
preprocessing layer per epoch.

Times :meth:`~gnsscam_ros.core.preprocess.Preprocessor.process` (ephemeris selection,
satellite positions and clocks at transmission time, atmosphere, variances) over the
epochs of an observation file, after a warm-up pass, and prints the median wall time per
epoch [ms] with the satellites observed and corrected. Default input: the NYA1 fixture of
``test/data/rinex`` (GPS, GLONASS, Galileo, BeiDou observed; ~36 satellites per epoch).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from ..core.preprocess import Preprocessor
from ..datasets.rinex import read_navigation, read_observations

_FIXTURES = Path(__file__).resolve().parents[2] / 'test' / 'data' / 'rinex'


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m gnsscam_ros.bench.preprocess')
    parser.add_argument('--obs', type=Path,
                        default=_FIXTURES / 'NYA100NOR_S_20241240000_01D_30S_MO.crx.gz')
    parser.add_argument('--nav', type=Path, action='append')
    parser.add_argument('--repeats', type=int, default=200)
    args = parser.parse_args(argv)
    navs = args.nav or [_FIXTURES / f'NYA100NOR_S_20241240000_01D_{s}.rnx.gz'
                        for s in ('GN', 'EN', 'CN')]
    obs = read_observations(args.obs)
    pre = Preprocessor(read_navigation(navs))
    for epoch in obs.epochs:            # warm-up, and the rough position of the receiver
        pre.process(epoch)
    times, kept = [], []
    for i in range(args.repeats):
        epoch = obs.epochs[i % len(obs.epochs)]
        start = time.perf_counter()
        result = pre.process(epoch)
        times.append(time.perf_counter() - start)
        kept.append(result.epoch.n_sv)
    observed = np.mean([e.pr_m.size for e in obs.epochs])
    print(f'preprocessing: {np.median(times) * 1e3:.2f} ms per epoch (median of '
          f'{args.repeats}), {observed:.0f} satellites observed, {np.mean(kept):.0f} corrected')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
