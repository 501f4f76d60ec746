"""Run the filter and the snapshot baseline over a drive and score them against truth."""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field

import numpy as np

from ..core import integrity
from ..core.filter import UPDATED, FilterConfig, ParticleFilter
from ..core.frames import LocalFrame
from ..core.fusion import CameraMeasurement, measurements_at_epoch
from ..core.gnss import check_epoch
from ..core.motion import integrate_odometry
from ..core.snapshot import solve_snapshot
from ..core.types import Drive
from .metrics import integrity_metrics, rmse


@dataclass
class RunRecord:
    """Per-epoch arrays of one filter run (only epochs with a GNSS update)."""

    stamp_ns: np.ndarray
    estimate_enu_m: np.ndarray
    truth_enu_m: np.ndarray
    risk_bound: dict            # method -> (T, A)
    reference_risk: np.ndarray  # (T, A)
    alert_limits_m: np.ndarray
    protection_level_m: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (T,)
    integrity_ok: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    statuses: dict = field(default_factory=dict)
    seconds: float = 0.0
    camera_alpha: dict = field(default_factory=dict)   # frame_id -> mixture weight alpha*
    camera_excluded_epochs: int = 0
    camera_epochs: int = 0


def truth_at(drive: Drive, frame: LocalFrame, stamps_ns: np.ndarray) -> np.ndarray:
    """Ground truth interpolated at ``stamps_ns``, in the map frame [m]."""
    truth_enu = frame.ecef_to_enu(drive.truth.ecef_m)
    t = drive.truth.stamp_ns.astype(float)
    return np.stack([np.interp(stamps_ns.astype(float), t, truth_enu[:, i])
                     for i in range(3)], axis=1)


class Progress:
    """A one-line progress indicator on stderr for long runs (silent when disabled)."""

    def __init__(self, label: str, total: int, enabled: bool):
        self.label, self.total, self.enabled = label, total, enabled
        self.start = time.monotonic()
        self.last = -1.0

    def update(self, done: int) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if now - self.last < 0.5 and done < self.total:
            return
        self.last = now
        sys.stderr.write(f'\r{self.label}: {done}/{self.total} epochs '
                         f'({now - self.start:.1f} s)')
        if done >= self.total:
            sys.stderr.write('\n')
        sys.stderr.flush()


def run_filter(drive: Drive, config: FilterConfig, seed: int = 0, progress: bool = False,
               camera_matches: list[CameraMeasurement] | None = None) -> RunRecord:
    """Run the particle filter over a drive; truth is used only for scoring.

    The motion of each interval integrates the odometry (``integrate_odometry``); the
    camera matches are moved to the epoch with it.

    Args:
        drive: The data.
        config: Filter parameters.
        seed: Seed of the filter's random generator.
        progress: Show progress on stderr.
        camera_matches: Best database match of every camera image (position at the image
            time, map frame); None runs GNSS only.

    Returns:
        Per-epoch estimates, truth, risk bounds (configured and other inverse method) and
        reference risks for every alert limit of the configuration.
    """
    def inputs(filt: ParticleFilter, epoch) -> tuple:
        motion, camera = None, None
        if filt.last_stamp_ns is not None and epoch.stamp_ns > filt.last_stamp_ns:
            if drive.odometry is not None:
                motion = integrate_odometry(drive.odometry, filt.last_stamp_ns,
                                            epoch.stamp_ns)
            if camera_matches and filt.last_result is not None:
                camera = measurements_at_epoch(camera_matches, drive.odometry,
                                               filt.last_stamp_ns, epoch.stamp_ns,
                                               filt.last_result.yaw_rad)
        return motion, camera

    return run_epochs(drive, config, seed, inputs, progress)[0]


def run_epochs(drive: Drive, config: FilterConfig, seed: int, inputs,
               progress: bool = False) -> tuple[RunRecord, LocalFrame]:
    """The filter over every GNSS epoch of a drive, scored against its truth.

    Args:
        drive: The data.
        config: Filter parameters.
        seed: Seed of the filter's random generator.
        inputs: ``inputs(filter, epoch) -> (motion, camera)``, the other arguments of
            ``ParticleFilter.step`` for the epoch (called once per epoch, in order).
        progress: Show progress on stderr.

    Returns:
        The run record and the filter's map frame.
    """
    frame = LocalFrame(*drive.origin_llh) if drive.origin_llh is not None else None
    filt = ParticleFilter(config, frame=frame, rng=np.random.default_rng(seed))
    limits = config.alert_limits_m
    other = integrity.APPROX if config.inverse_bernoulli == integrity.EXACT else integrity.EXACT
    stamps, estimates, bounds, bounds_other, references = [], [], [], [], []
    levels, oks = [], []
    statuses: dict[str, int] = {}
    bar = Progress(f'filter {drive.name}', len(drive.gnss), progress)
    start = time.monotonic()
    truth_enu = None
    camera_alpha: dict[int, float] = {}
    camera_epochs = camera_excluded = 0
    for i, epoch in enumerate(drive.gnss):
        motion, camera = inputs(filt, epoch)
        result = filt.step(epoch, motion, camera)
        if result.camera_alpha is not None:
            camera_epochs += 1
            camera_excluded += int(result.camera_excluded)
            camera_alpha.update(zip(result.camera_frame_ids, result.camera_alpha.tolist()))
        statuses[result.status] = statuses.get(result.status, 0) + 1
        bar.update(i + 1)
        if result.status != UPDATED or drive.truth is None:
            continue
        if truth_enu is None:
            truth_enu = filt.frame.ecef_to_enu(drive.truth.ecef_m)
        truth = np.array([np.interp(epoch.stamp_ns, drive.truth.stamp_ns, truth_enu[:, j])
                          for j in range(3)])
        stamps.append(epoch.stamp_ns)
        estimates.append(result.position_enu_m)
        bounds.append(result.risk.risk_bound)
        bounds_other.append(integrity.risk_bound(
            result.risk.empirical_risk, result.risk.kl_nats, config.n_posteriors,
            config.risk_delta, other).risk_bound)
        references.append(filt.posterior_set.hazard_mass(truth, limits))
        levels.append(result.protection_level_m)
        oks.append(result.integrity_ok)
    seconds = time.monotonic() - start
    stamps_arr = np.array(stamps, dtype=np.int64)
    record = RunRecord(
        stamp_ns=stamps_arr, estimate_enu_m=np.array(estimates).reshape(-1, 3),
        truth_enu_m=(truth_at(drive, filt.frame, stamps_arr) if stamps else np.zeros((0, 3))),
        risk_bound={config.inverse_bernoulli: np.array(bounds).reshape(-1, len(limits)),
                    other: np.array(bounds_other).reshape(-1, len(limits))},
        reference_risk=np.array(references).reshape(-1, len(limits)), alert_limits_m=limits,
        protection_level_m=np.array(levels, dtype=float),
        integrity_ok=np.array(oks, dtype=bool),
        statuses=statuses, seconds=seconds, camera_alpha=camera_alpha,
        camera_excluded_epochs=camera_excluded, camera_epochs=camera_epochs)
    return record, filt.frame


def run_snapshot_baseline(drive: Drive, frame: LocalFrame,
                          measurement_var_m2: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """Robust snapshot WLS on every usable epoch: ``(stamp_ns (T,), enu_m (T, 3))``."""
    stamps, fixes = [], []
    previous = None
    for epoch in drive.gnss:
        check = check_epoch(epoch)
        if not check.usable:
            continue
        try:
            fix = solve_snapshot(epoch.subset(check.keep), previous,
                                 measurement_var_m2=measurement_var_m2)
        except ValueError:
            continue
        if not fix.converged:
            continue
        previous = fix.ecef_m
        stamps.append(epoch.stamp_ns)
        fixes.append(frame.ecef_to_enu(fix.ecef_m))
    return np.array(stamps, dtype=np.int64), np.array(fixes).reshape(-1, 3)


def accuracy(estimate_enu_m: np.ndarray, truth_enu_m: np.ndarray) -> dict:
    """RMSE 2D and 3D and the error percentiles of a run [m]."""
    diff = estimate_enu_m - truth_enu_m
    err2 = np.hypot(diff[:, 0], diff[:, 1])
    err3 = np.linalg.norm(diff, axis=1)
    return {'rmse_2d_m': rmse(err2), 'rmse_3d_m': rmse(err3), 'epochs': int(diff.shape[0]),
            'p50_2d_m': float(np.percentile(err2, 50)) if err2.size else None,
            'p95_2d_m': float(np.percentile(err2, 95)) if err2.size else None,
            'max_2d_m': float(err2.max()) if err2.size else None}


def summarize(record: RunRecord, config: FilterConfig) -> dict:
    """Accuracy and integrity metrics of a run, keyed like the evaluation JSON."""
    out = accuracy(record.estimate_enu_m, record.truth_enu_m)
    diff = record.estimate_enu_m - record.truth_enu_m
    err = np.hypot(diff[:, 0], diff[:, 1]) if config.horizontal_risk else np.linalg.norm(
        diff, axis=1)
    by_method = {}
    for method, bounds in record.risk_bound.items():
        by_method[method] = {
            f'{limit:g}': integrity_metrics(err, bounds[:, a], record.reference_risk[:, a],
                                            limit, config.target_risk)
            for a, limit in enumerate(record.alert_limits_m)}
    out['integrity'] = by_method[config.inverse_bernoulli]
    out['integrity_by_inverse_bernoulli'] = by_method
    out['statuses'] = record.statuses
    out['filter_seconds'] = record.seconds
    return out
