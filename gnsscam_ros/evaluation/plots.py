"""Figures of the paper's kind (matplotlib, headless): trajectories and risk over time."""
from __future__ import annotations

import re
from pathlib import Path

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402  (backend must be chosen first)
import numpy as np  # noqa: E402
from matplotlib.colors import LogNorm  # noqa: E402

from .report import stanford_counts  # noqa: E402  pure counting, importable without plots

LOG_FLOOR_M = 0.1          # log axes cannot show 0; errors/PLs below this sit on the edge


def _save(fig, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f'.{path.name}.tmp.png')
    fig.savefig(tmp, dpi=110, bbox_inches='tight')
    plt.close(fig)
    tmp.replace(path)                 # never a half-written figure under the final name
    return path


def dataset_title(name: str) -> str:
    """A readable title for a dataset name: ``emulated-urban-s3-f6`` -> ``Emulated urban
    drive (seed 3, 6 faulty satellites)``, ``Berlin_Potsdamer_Platz`` -> ``smartLoc Berlin
    Potsdamer Platz``; other names unchanged."""
    match = re.fullmatch(r'emulated-urban-s(\d+)-f(\d+)(-nonlos)?', name)
    if match:
        seed, faults, nonlos = match.groups()
        faulty = 'no faulty satellite' if faults == '0' else (
            f'{faults} faulty satellite' + ('s' if faults != '1' else ''))
        return (f'Emulated urban drive (seed {seed}, {faulty}'
                + (', no NLOS)' if nonlos else ')'))
    if name.startswith('Berlin_'):
        return 'smartLoc ' + name.replace('_', ' ')
    return name


def _panel_layout(truth_enu: np.ndarray, panels: int) -> tuple[int, int, tuple]:
    """``(rows, columns, figure size)`` so that equal-aspect panels fill the figure: a
    trajectory wider than tall stacks its panels, a tall one puts them side by side
    (side by side, a wide smartLoc track left most of each panel blank)."""
    span = np.ptp(truth_enu[:, :2], axis=0) if len(truth_enu) else np.ones(2)
    ratio = float(np.clip((span[1] + 1.0) / (span[0] + 1.0), 0.3, 3.0))   # height/width
    legend_in = 1.0                      # below each panel
    if ratio < 1.0:
        width = 7.0
        return panels, 1, (width, (width * ratio + legend_in) * panels + 0.6)
    height = 7.0
    # Not narrower than the legend and title need (the x limits widen to fill it).
    width = max(height / ratio, 3.5)
    return 1, panels, (width * panels, height + legend_in + 0.6)


def trajectory_plot(path: Path, title: str, truth_enu: np.ndarray,
                    estimates: dict[str, np.ndarray], alert_limit_m: float) -> Path:
    """Estimated trajectories over ground truth, errors above the alert limit marked
    (Figs 4-5).

    Args:
        path: Output PNG.
        title: Figure title.
        truth_enu: (T, 3) ground truth [m].
        estimates: Method name -> (T, 3) estimates aligned with ``truth_enu`` [m].
        alert_limit_m: Horizontal alert limit [m]: epochs whose error exceeds it are
            marked.
    """
    rows, cols, size = _panel_layout(truth_enu, len(estimates))
    fig, axes = plt.subplots(rows, cols, figsize=size, squeeze=False, layout='constrained')
    for ax, (name, est) in zip(axes.ravel(), estimates.items()):
        err = np.hypot(*(est[:, :2] - truth_enu[:, :2]).T)
        ax.plot(truth_enu[:, 0], truth_enu[:, 1], color='0.6', lw=3, label='ground truth')
        ax.plot(est[:, 0], est[:, 1], color='tab:blue', lw=1, label=name)
        bad = err > alert_limit_m
        ax.scatter(est[bad, 0], est[bad, 1], s=8, color='tab:red',
                   label=f'error > alert limit {alert_limit_m:g} m ({bad.mean():.0%})')
        ax.set_aspect('equal', adjustable='datalim')
        ax.set_xlabel('east [m]')
        ax.set_ylabel('north [m]')
        ax.set_title(f'{name}\n2D RMSE {np.sqrt(np.mean(err ** 2)):.1f} m', fontsize=10)
        # Below the panel: inside, it covered part of the track.
        ax.legend(loc='upper center', bbox_to_anchor=(0.5, -0.1), fontsize=8)
    fig.suptitle(title)
    return _save(fig, path)


def risk_plot(path: Path, title: str, time_s: np.ndarray, bound: np.ndarray,
              reference: np.ndarray, alert_limit_m: float, target_risk: float,
              reference_label: str = 'reference risk (truth)') -> Path:
    """Integrity risk bound against the reference risk over time (Figs 8-11).

    The share of epochs whose bound is below the reference is the failure ratio *against
    this reference*: ``reference_label`` says which one it is (the offline run's M
    posteriors, or a recorded particle cloud, give different references for the same
    estimates).
    """
    fig, ax = plt.subplots(figsize=(11, 3.5))
    ax.plot(time_s, reference, color='tab:orange', lw=1, label=reference_label)
    ax.plot(time_s, bound, color='tab:blue', lw=1, label='risk bound')
    fail = bound < reference
    ax.scatter(time_s[fail], bound[fail], s=6, color='tab:red',
               label=f'bound < reference: failure ratio {fail.mean():.0%}')
    ax.axhline(target_risk, color='0.3', ls='--', lw=0.8, label=f'target {target_risk:g}')
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel('time [s]')
    ax.set_ylabel(f'risk, alert limit {alert_limit_m:g} m')
    ax.set_title(title)
    # Outside the axes: inside, it covered the curves.
    ax.legend(loc='upper left', bbox_to_anchor=(1.01, 1.0), fontsize=8)
    return _save(fig, path)


def _decade_above(value: float) -> float:
    return 10.0 ** np.ceil(np.log10(value))


def stanford_diagram(path: Path, title: str, error_m: np.ndarray,
                     protection_level_m: np.ndarray, alert_limit_m: float,
                     valid: np.ndarray | None = None) -> dict[str, int]:
    """Stanford diagram of the integrity output: error against protection level, log-log.

    Epochs are binned in a 2D histogram with logarithmic cells (colour = epochs per cell),
    which stays readable with 10^5 epochs where a scatter turns into a blot. Values below
    ``LOG_FLOOR_M`` are drawn at the floor. Epochs without a finite PL are drawn in a
    separate top row labelled "no PL" and counted as unavailable. The diagonal PL = error
    and the alert limit lines split the plane into the regions of
    :func:`~gnsscam_ros.evaluation.report.stanford_counts`, each labelled with its count.

    Args:
        path: Output PNG.
        title: Figure title.
        error_m: (T,) horizontal position error [m].
        protection_level_m: (T,) horizontal protection level [m]; inf/NaN = none.
        alert_limit_m: Horizontal alert limit [m].
        valid: Optional (T,) bool mask of epochs to use (e.g. those with ground truth);
            by default every epoch, and then every error must be finite.

    Returns:
        The region counts of the drawn epochs (keys of ``report.STANFORD_KEYS``).
    """
    err = np.asarray(error_m, dtype=float).ravel()
    pl = np.asarray(protection_level_m, dtype=float).ravel()
    if valid is not None:
        keep = np.asarray(valid, dtype=bool).ravel()
        if not (keep.size == err.size == pl.size):
            raise ValueError(f'valid ({keep.size}), error ({err.size}) and protection '
                             f'level ({pl.size}) differ in length')
        err, pl = err[keep], pl[keep]
    counts = stanford_counts(err, pl, alert_limit_m)   # also validates the inputs

    no_pl = ~np.isfinite(pl)
    # Axis range: whole decades, at least one decade either side of the alert limit so
    # every region has room for its label.
    lo = min(LOG_FLOOR_M, alert_limit_m / 10.0)
    finite = np.concatenate([err, pl[~no_pl], [alert_limit_m * 10.0]])
    hi = _decade_above(max(finite.max(), lo * 10.0))
    per_decade = 10
    decades = int(round(np.log10(hi / lo)))
    edges = np.logspace(np.log10(lo), np.log10(hi), decades * per_decade + 1)
    # One extra row above the top edge holds the epochs without a PL.
    top = edges[-1] * (edges[1] / edges[0]) ** 4
    y_edges = np.append(edges, top)
    x = np.clip(err, lo, hi)
    y = np.where(no_pl, np.sqrt(hi * top), np.clip(pl, lo, hi))
    hist, _, _ = np.histogram2d(x, y, bins=[edges, y_edges])

    fig, ax = plt.subplots(figsize=(7, 6))
    ax.set_xscale('log')
    ax.set_yscale('log')
    if hist.any():
        mesh = ax.pcolormesh(edges, y_edges, np.ma.masked_equal(hist.T, 0), cmap='viridis',
                             norm=LogNorm(vmin=1, vmax=max(hist.max(), 2)))
        fig.colorbar(mesh, ax=ax, label='epochs per cell')
    al = alert_limit_m
    ax.plot([lo, hi], [lo, hi], color='k', lw=1)
    ax.axvline(al, color='k', lw=1, ls='--')
    ax.axhline(al, color='k', lw=1, ls='--')
    ax.axhline(hi, color='0.4', lw=0.8)
    ax.text(hi / 1.1, np.sqrt(hi * top), 'no PL', ha='right', va='center', fontsize=7,
            color='0.3', bbox=dict(facecolor='white', alpha=0.85, lw=0))

    def share(key):
        n = counts[key]
        return f'{n} ({n / counts["epochs"]:.1%})' if counts['epochs'] else '0'

    # Labels in the region corners farthest from the diagonal, where few epochs fall.
    pad = 10 ** (0.05 * np.log10(hi / lo))     # a small margin, as a factor on log axes
    labels = [
        (lo * pad, al / pad, 'left', 'top', f'nominal\n{share("nominal")}', 'tab:green'),
        (al / pad, lo * pad, 'right', 'bottom', f'MI\n{share("mi")}', 'tab:orange'),
        (hi / pad, lo * pad, 'right', 'bottom', f'HMI\n{share("hmi")}', 'tab:red'),
        (lo * pad, hi / pad, 'left', 'top',
         f'unavailable\n{share("unavailable")}\nof which no PL: {counts["no_pl"]}', '0.3'),
        (hi / pad, al * pad, 'right', 'bottom',
         f'unavailable & MI\n{share("unavailable_mi")}', 'tab:purple'),
    ]
    for tx, ty, ha, va, text, colour in labels:
        ax.text(tx, ty, text, ha=ha, va=va, fontsize=8, color=colour,
                bbox=dict(facecolor='white', alpha=0.85, edgecolor=colour, lw=0.6))
    ax.set_xlim(lo, hi)
    ax.set_ylim(lo, top)
    ax.set_xlabel('horizontal position error [m]')
    ax.set_ylabel('horizontal protection level [m]')
    ax.set_title(f'{title}\nAL {al:g} m, {counts["epochs"]} epochs', fontsize=10)
    _save(fig, Path(path))
    return counts


def error_pl_timeline(path: Path, title: str, time_s: np.ndarray, error_m: np.ndarray,
                      protection_level_m: np.ndarray, alert_limit_m: float,
                      integrity_levels: np.ndarray | None = None) -> Path:
    """Horizontal error and protection level over time, log y.

    A log axis keeps 1 m errors and 1000 m PLs readable on one plot; values below
    ``LOG_FLOOR_M`` sit on the floor. Epochs without a finite PL are shaded grey. With
    ``integrity_levels``, epochs the flag called 'OK' while the error exceeded the alert
    limit (the failures integrity is about) are marked red.

    Args:
        path: Output PNG.
        title: Figure title.
        time_s: (T,) epoch times [s].
        error_m: (T,) horizontal position error [m]; NaN = no ground truth (a gap).
        protection_level_m: (T,) horizontal protection level [m]; inf/NaN = none.
        alert_limit_m: Horizontal alert limit [m].
        integrity_levels: Optional (T,) strings 'OK' / 'ERROR' / 'STALE'.
    """
    t = np.asarray(time_s, dtype=float).ravel()
    err = np.asarray(error_m, dtype=float).ravel()
    pl = np.asarray(protection_level_m, dtype=float).ravel()
    if not (t.size == err.size == pl.size):
        raise ValueError(f'time ({t.size}), error ({err.size}) and protection level '
                         f'({pl.size}) differ in length')
    no_pl = ~np.isfinite(pl)
    fig, ax = plt.subplots(figsize=(10, 3.5))
    ax.set_yscale('log')
    # One artist for all the no-PL spans (thousands of axvspans would be slow).
    ax.fill_between(t, 0, 1, where=no_pl, step='mid', color='0.85', lw=0,
                    transform=ax.get_xaxis_transform(),
                    label=f'no PL ({no_pl.mean() if t.size else 0:.0%})')
    ax.plot(t, np.where(no_pl, np.nan, np.clip(pl, LOG_FLOOR_M, None)),
            color='tab:orange', lw=1, label='protection level')
    ax.plot(t, np.clip(err, LOG_FLOOR_M, None), color='tab:blue', lw=1,
            label='horizontal error')       # drawn last: the error is what is judged
    ax.axhline(alert_limit_m, color='0.3', ls='--', lw=0.8,
               label=f'alert limit {alert_limit_m:g} m')
    if integrity_levels is not None:
        levels = np.asarray(integrity_levels).ravel()
        if levels.size != t.size:
            raise ValueError(f'integrity_levels ({levels.size}) and time ({t.size}) '
                             'differ in length')
        with np.errstate(invalid='ignore'):
            missed = (levels == 'OK') & (err > alert_limit_m)   # NaN error: not a miss
        ax.scatter(t[missed], np.clip(err[missed], LOG_FLOOR_M, None), s=10,
                   color='tab:red', zorder=3,
                   label=f'flag OK, error > AL ({int(missed.sum())})')
    # Bottom at the decade below the smallest value: no empty decades down to the floor.
    shown = np.concatenate([err, pl, [alert_limit_m]])
    shown = shown[np.isfinite(shown) & (shown > 0)]
    ax.set_ylim(bottom=max(LOG_FLOOR_M, 10.0 ** np.floor(np.log10(shown.min()))))
    ax.set_xlabel('time [s]')
    ax.set_ylabel('horizontal [m]')
    ax.set_title(title)
    # Outside the axes: inside, it hides the epochs it describes.
    ax.legend(loc='upper left', bbox_to_anchor=(1.01, 1.0), fontsize=8)
    return _save(fig, Path(path))


def integrity_plots(folder: Path, name: str, title: str, stamp_ns: np.ndarray,
                    error_m: np.ndarray, protection_level_m: np.ndarray,
                    integrity_levels: np.ndarray, alert_limit_m: float) -> list[Path]:
    """The Stanford diagram and the error/PL timeline of one run, from its epoch rows.

    Writes ``<folder>/stanford_<name>.png`` (the updated epochs, i.e. level OK or ERROR,
    with a finite error) and ``<folder>/error_pl_<name>.png`` (every epoch; STALE ones
    have no PL).

    Args:
        folder: Output folder (created).
        name: File name part.
        title: Figure title.
        stamp_ns: (E,) epoch stamps [ns].
        error_m: (E,) horizontal error [m], NaN without truth/estimate.
        protection_level_m: (E,) PL [m], NaN/inf = none.
        integrity_levels: (E,) 'OK' / 'ERROR' / 'STALE'.
        alert_limit_m: Alert limit [m].

    Returns:
        The PNG paths (the Stanford diagram only when some epoch qualifies).
    """
    folder = Path(folder)
    stamps = np.asarray(stamp_ns, dtype=np.int64).ravel()
    err = np.asarray(error_m, dtype=float).ravel()
    pl = np.asarray(protection_level_m, dtype=float).ravel()
    levels = np.asarray(integrity_levels).astype(str).ravel()
    paths = []
    updated = (levels != 'STALE') & np.isfinite(err)
    if updated.any():
        stanford_diagram(folder / f'stanford_{name}.png', title, err, pl, alert_limit_m,
                         valid=updated)
        paths.append(folder / f'stanford_{name}.png')
    if stamps.size:
        t_s = (stamps - stamps[0]) * 1e-9
        paths.append(error_pl_timeline(folder / f'error_pl_{name}.png', title, t_s, err, pl,
                                       alert_limit_m, levels))
    return paths


#: Rates of :func:`interval_plot`: ``(key, with an alert limit, label)``.
INTERVAL_PANELS = (('mi_rate', False, 'MI rate (error > PL)'),
                   ('availability', True, 'availability (PL <= AL)'),
                   ('p_fa', True, 'P_FA'), ('p_mi', True, 'P_MI'),
                   ('failure_ratio', True, 'failure ratio'))


def interval_plot(path: Path, title: str, groups: list[dict], pooled: dict,
                  alert_limit: str) -> Path:
    """The integrity rates of a method per GNSS case, with their 95 % intervals.

    One panel per rate (:data:`INTERVAL_PANELS`, at ``alert_limit``); per case the pooled
    rate with its Clopper-Pearson interval (thick, epochs taken as independent), the
    between-seed interval (thin, offset; each seed one cluster) and the per-seed rates
    (grey dots); the last column pools every case.

    Args:
        path: Output PNG.
        title: Figure title.
        groups: ``intervals['by_case']`` entries of one method.
        pooled: ``intervals['by_method'][method]``.
        alert_limit: Alert limit key ("8").
    """
    columns = [(f"{g['bias_m']:g} m\n{g['faults']} f" if g['faults'] else 'NLOS', g)
               for g in groups] + [('all', pooled)]
    fig, axes = plt.subplots(len(INTERVAL_PANELS), 1, sharex=True,
                             figsize=(max(6.0, 0.9 * len(columns) + 2), 11))
    x = np.arange(len(columns))
    for ax, (key, limited, label) in zip(axes, INTERVAL_PANELS):
        for i, (_, g) in enumerate(columns):
            entry = g['rates'].get(key)
            if limited and entry is not None:
                entry = entry.get(alert_limit)
            if entry is None or entry['rate'] is None:
                continue
            seeds = [k / n for _, k, n in entry['per_seed'] if n]
            ax.scatter(np.full(len(seeds), i - 0.18), seeds, s=6, color='0.6', zorder=1)
            lo, hi = entry['ci95']
            ax.errorbar(i, entry['rate'], yerr=[[entry['rate'] - lo], [hi - entry['rate']]],
                        fmt='o', color='tab:blue', lw=2.5, capsize=3, zorder=3)
            between = entry.get('between_seeds')
            if between is not None:
                b_lo, b_hi = between['ci95']
                ax.errorbar(i + 0.18, entry['rate'], fmt='none', color='tab:orange', lw=1,
                            capsize=3, yerr=[[max(entry['rate'] - b_lo, 0)],
                                             [max(b_hi - entry['rate'], 0)]], zorder=2)
        ax.set_ylabel(label + (f'\nAL {alert_limit} m' if limited else ''), fontsize=8)
        ax.grid(axis='y', lw=0.3)
    axes[-1].set_xticks(x, [c[0] for c in columns], fontsize=7)
    axes[0].legend(handles=[
        plt.Line2D([], [], color='tab:blue', marker='o', lw=2.5,
                   label='pooled rate, 95 % Clopper-Pearson'),
        plt.Line2D([], [], color='tab:orange', lw=1, label='95 % between seeds'),
        plt.Line2D([], [], color='0.6', marker='o', ls='', ms=3, label='per seed')],
        loc='upper left', bbox_to_anchor=(1.01, 1.0), fontsize=7)
    fig.suptitle(title, y=0.93)
    return _save(fig, Path(path))
