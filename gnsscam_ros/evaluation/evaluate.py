"""Evaluate the filter on one drive, next to the robust snapshot WLS baseline."""
from __future__ import annotations


from ..core.filter import FilterConfig
from ..core.frames import LocalFrame
from ..core.types import Drive
from .runner import RunRecord, accuracy, run_filter, run_snapshot_baseline, summarize, truth_at


def evaluate_drive(drive: Drive, config: FilterConfig, seed: int = 0,
                   progress: bool = False) -> dict:
    """Filter metrics and the baseline's, from one run on the same data.

    Returns:
        The evaluation JSON: ``rmse_2d_m``, ``rmse_3d_m``, ``epochs``, ``integrity`` keyed by
        alert limit, ``protection_level`` (:func:`.metrics.protection_level_metrics`),
        ``baseline_wls`` and the configuration used.

    Raises:
        ValueError: The drive has no ground truth.
    """
    return evaluate_drive_record(drive, config, seed, progress)[0]


def evaluate_drive_record(drive: Drive, config: FilterConfig, seed: int = 0,
                          progress: bool = False) -> tuple[dict, RunRecord]:
    """:func:`evaluate_drive` and the run record (its ``epochs`` table: one row per GNSS
    epoch)."""
    if drive.truth is None:
        raise ValueError(f'{drive.name}: no ground truth, nothing to evaluate against')
    record = run_filter(drive, config, seed=seed, progress=progress)
    out = summarize(record, config)
    frame = LocalFrame.at_origin_or(drive.origin_llh, drive.truth.ecef_m[0])
    stamps, fixes = run_snapshot_baseline(drive, frame, config.measurement_var_m2)
    baseline = accuracy(fixes, truth_at(drive, frame, stamps))
    out['baseline_wls'] = baseline
    out['rmse_2d_ratio_to_wls'] = (out['rmse_2d_m'] / baseline['rmse_2d_m']
                                   if baseline['rmse_2d_m'] else None)
    out['dataset'] = {'name': drive.name, 'gnss_epochs': len(drive.gnss),
                      **{k: v for k, v in drive.info.items()
                         if isinstance(v, (str, int, float, bool)) or v is None}}
    out['config'] = config.as_flat()
    out['seed'] = seed
    return out, record
