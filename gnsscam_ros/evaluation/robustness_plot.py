"""The figure of ``gnsscam_eval robustness`` (matplotlib, headless)."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402  (backend must be chosen first)
import numpy as np  # noqa: E402
from matplotlib.ticker import NullFormatter, ScalarFormatter  # noqa: E402

from ..io.atomic import atomic_output  # noqa: E402

PASS_COLOR, FAIL_COLOR, SEED_COLOR = 'tab:green', 'tab:red', '0.6'
#: Ticks of the PL / error axis (log scale).
LOG_TICKS = (0.1, 0.2, 0.5, 1.0, 2.0, 3.0, 5.0, 10.0, 20.0, 50.0, 100.0)


def _marker(ax, x, value, target: dict, **kwargs) -> None:
    ax.scatter([x], [value], color=PASS_COLOR if target['pass'] else FAIL_COLOR, zorder=3,
               s=30, **kwargs)


def robustness_figure(path: Path, result: dict) -> Path:
    """Per cell: the MI rate with its between-seed 95 % interval, the 2D RMSE over the
    robust WLS's, and the median PL over the median error; the per-seed values as grey
    dots, the targets as dashed lines, each marker (and the MI interval, for the
    upper-bound target) green where it meets its target and red where not. Written
    atomically (replaces ``path``).

    Args:
        path: Output PNG.
        result: What :func:`.robustness.run_robustness` returned (with ``dataset``).
    """
    cells = [c for c in result['cells'] if 'mi_rate' in c]
    targets = {k: v['limit'] for k, v in result['targets'].items()}
    fig, axes = plt.subplots(3, 1, sharex=True, figsize=(max(7.0, 0.6 * len(cells) + 3), 9))
    x = np.arange(len(cells))
    mi_ax, rmse_ax, pl_ax = axes
    for i, c in enumerate(cells):
        mi = c['mi_rate']
        seeds = [r['mi_epochs'] / r['epochs'] for r in c['runs'] if r['epochs']]
        mi_ax.scatter(np.full(len(seeds), i - 0.2), seeds, s=6, color=SEED_COLOR, zorder=1)
        if mi['ci95'] is not None:
            lo, hi = mi['ci95']
            color = PASS_COLOR if c['targets']['mi_upper']['pass'] else FAIL_COLOR
            mi_ax.errorbar(i, mi['mean'], yerr=[[mi['mean'] - lo], [hi - mi['mean']]],
                           fmt='none', color=color, lw=1.5, capsize=4, zorder=2, alpha=0.7)
        if mi['mean'] is not None:
            _marker(mi_ax, i, mi['mean'], c['targets']['mi_mean'])
        wls = c['wls_rmse_2d_m']
        if wls:
            per_seed = [r['rmse_2d_m'] / wls for r in c['runs'] if r['epochs']]
            rmse_ax.scatter(np.full(len(per_seed), i - 0.2), per_seed, s=6,
                            color=SEED_COLOR, zorder=1)
        if c['rmse_ratio_to_wls'] is not None:
            _marker(rmse_ax, i, c['rmse_ratio_to_wls'], c['targets']['rmse_ratio_to_wls'])
        ratio = c['pl_to_error_ratio']
        if ratio is not None and np.isfinite(ratio):
            _marker(pl_ax, i, ratio, c['targets']['pl_to_error_ratio'])
        elif ratio is not None:
            pl_ax.annotate('inf', (i, 1.0), xycoords=('data', 'axes fraction'),
                           ha='center', va='top', color=FAIL_COLOR, fontsize=8)
    mi_ax.axhline(targets['mi_mean'], color='k', ls='--', lw=0.8,
                  label=f"mean target {targets['mi_mean']:g}")
    mi_ax.axhline(targets['mi_upper'], color='k', ls=':', lw=0.8,
                  label=f"upper-bound target {targets['mi_upper']:g}")
    mi_ax.set_ylabel('MI rate (error > PL): mean,\n95 % interval between seeds')
    mi_ax.set_ylim(bottom=0)
    mi_ax.legend(loc='upper left', bbox_to_anchor=(1.01, 1.0), fontsize=7)
    rmse_ax.axhline(targets['rmse_ratio_to_wls'], color='k', ls='--', lw=0.8,
                    label=f"target {targets['rmse_ratio_to_wls']:g}")
    rmse_ax.axhline(1.0, color='0.4', ls='-', lw=0.5, label='as good as the WLS')
    rmse_ax.set_ylabel('2D RMSE / robust WLS\n(mean over seeds)')
    rmse_ax.set_ylim(bottom=0)
    rmse_ax.legend(loc='upper left', bbox_to_anchor=(1.01, 1.0), fontsize=7)
    pl_ax.axhline(targets['pl_to_error_ratio'], color='k', ls='--', lw=0.8,
                  label=f"target {targets['pl_to_error_ratio']:g}")
    pl_ax.axhline(1.0, color='0.4', ls='-', lw=0.5, label='PL = error')
    pl_ax.set_ylabel('median PL /\nmedian error')
    pl_ax.set_yscale('log')
    pl_ax.set_yticks(LOG_TICKS)
    pl_ax.yaxis.set_major_formatter(ScalarFormatter())
    pl_ax.yaxis.set_minor_formatter(NullFormatter())
    finite = [c['pl_to_error_ratio'] for c in cells
              if c['pl_to_error_ratio'] is not None and np.isfinite(c['pl_to_error_ratio'])]
    pl_ax.set_ylim(min([0.8, *finite]) / 1.3, max([targets['pl_to_error_ratio'], *finite]) * 1.3)
    pl_ax.legend(loc='upper left', bbox_to_anchor=(1.01, 1.0), fontsize=7)
    for ax in axes:
        ax.grid(axis='y', lw=0.3)
    pl_ax.set_xticks(x, [c['name'] for c in cells], rotation=45, ha='right', fontsize=8)
    seeds = result['seeds']
    fig.suptitle(f"{result['dataset']['name']}: {len(seeds)} filter seeds per cell, one "
                 f"configuration\n{result['cells_passed']}/{len(result['cells'])} cells "
                 'meet every target (green: target met, red: not; grey: per seed)',
                 fontsize=10)
    fig.tight_layout()
    try:
        with atomic_output(Path(path), force=True, mode='wb') as handle:
            fig.savefig(handle, format='png', dpi=110, bbox_inches='tight')
    finally:
        plt.close(fig)
    return Path(path)
