"""Figures of the paper's kind (matplotlib, headless): trajectories and risk over time."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402  (backend must be chosen first)
import numpy as np  # noqa: E402

ERROR_HIGHLIGHT_M = 10.0


def _save(fig, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f'.{path.name}.tmp.png')
    fig.savefig(tmp, dpi=110, bbox_inches='tight')
    plt.close(fig)
    tmp.replace(path)                 # never a half-written figure under the final name
    return path


def trajectory_plot(path: Path, title: str, truth_enu: np.ndarray,
                    estimates: dict[str, np.ndarray]) -> Path:
    """Estimated trajectories over ground truth, errors above 10 m highlighted (Figs 4-5).

    Args:
        path: Output PNG.
        title: Figure title.
        truth_enu: (T, 3) ground truth [m].
        estimates: Method name -> (T, 3) estimates aligned with ``truth_enu`` [m].
    """
    fig, axes = plt.subplots(1, len(estimates), figsize=(6 * len(estimates), 6),
                             squeeze=False)
    for ax, (name, est) in zip(axes[0], estimates.items()):
        err = np.hypot(*(est[:, :2] - truth_enu[:, :2]).T)
        ax.plot(truth_enu[:, 0], truth_enu[:, 1], color='0.6', lw=3, label='ground truth')
        ax.plot(est[:, 0], est[:, 1], color='tab:blue', lw=1, label=name)
        bad = err > ERROR_HIGHLIGHT_M
        ax.scatter(est[bad, 0], est[bad, 1], s=8, color='tab:red',
                   label=f'error > {ERROR_HIGHLIGHT_M:g} m ({bad.mean():.0%})')
        ax.set_aspect('equal')
        ax.set_xlabel('east [m]')
        ax.set_ylabel('north [m]')
        ax.set_title(f'{name}: 2D RMSE {np.sqrt(np.mean(err ** 2)):.1f} m')
        ax.legend(loc='best', fontsize=8)
    fig.suptitle(title)
    return _save(fig, path)


def risk_plot(path: Path, title: str, time_s: np.ndarray, bound: np.ndarray,
              reference: np.ndarray, alert_limit_m: float, target_risk: float) -> Path:
    """Integrity risk bound against the reference risk over time (Figs 8-11)."""
    fig, ax = plt.subplots(figsize=(10, 3.5))
    ax.plot(time_s, reference, color='tab:orange', lw=1, label='reference risk (truth)')
    ax.plot(time_s, bound, color='tab:blue', lw=1, label='risk bound')
    fail = bound < reference
    ax.scatter(time_s[fail], bound[fail], s=6, color='tab:red',
               label=f'bound < reference ({fail.mean():.0%})')
    ax.axhline(target_risk, color='0.3', ls='--', lw=0.8, label=f'target {target_risk:g}')
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel('time [s]')
    ax.set_ylabel(f'risk, alert limit {alert_limit_m:g} m')
    ax.set_title(title)
    ax.legend(loc='upper right', fontsize=8)
    return _save(fig, path)
