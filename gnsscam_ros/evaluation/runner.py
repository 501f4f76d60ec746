"""Run the filter and the snapshot baseline over a drive and score them against truth."""
from __future__ import annotations

import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from ..core import integrity
from ..core.filter import UPDATED, FilterConfig
from ..core.frames import LocalFrame
from ..core.engine import EpochEngine, EpochReport, InputTiming, best_match
from ..core.fusion import CameraMeasurement
from ..core.gnss import check_epoch
from ..core.motion import DeadReckoningConfig, DeadReckoningState, dead_reckon
from ..core.snapshot import solve_snapshot
from ..core.types import Drive, GnssEpoch
from .metrics import (cloud_calibration, integrity_metrics, level_sizing, nees,
                      protection_level_metrics, rmse)


@dataclass
class EpochTable:
    """One row per GNSS epoch of a run, updated or not (the ``--epochs-csv`` content).

    Attributes:
        stamp_ns: (E,) epoch stamps (the input's time) [ns].
        status: (E,) filter status ('updated', 'propagated', 'rejected', 'waiting').
        reason: (E,) why the epoch was not an update, or why integrity is not OK.
        estimate_enu_m: (E, 3) estimate in the map frame [m]; NaN while there is none.
        lat_deg, lon_deg, height_m: (E,) the estimate in WGS84; NaN while there is none.
        protection_level_m: (E,) PL [m] (inf: none within reach); NaN when not updated.
        risk_bound: (E,) risk bound at the configured alert limit; NaN when not updated.
        integrity: (E,) the verdict's level (``core.verdict``): 'OK', 'ERROR' (updated,
            not OK) or 'STALE' (not updated).
        horizontal_error_m: (E,) horizontal error against the truth; NaN without truth or
            estimate.
        satellites: (E,) satellites used in the update.
    """

    stamp_ns: np.ndarray
    status: np.ndarray
    reason: np.ndarray
    estimate_enu_m: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    height_m: np.ndarray
    protection_level_m: np.ndarray
    risk_bound: np.ndarray
    integrity: np.ndarray
    horizontal_error_m: np.ndarray
    satellites: np.ndarray

    CSV_COLUMNS = ('stamp_ns', 'lat_deg', 'lon_deg', 'height_m', 'protection_level_m',
                   'risk_bound', 'integrity', 'horizontal_error_m', 'status', 'reason',
                   'east_m', 'north_m', 'up_m', 'satellites')

    def __len__(self) -> int:
        return int(self.stamp_ns.size)

    def csv_rows(self):
        """Rows under ``CSV_COLUMNS`` (NaN cells are written empty)."""
        for k in range(len(self)):
            e, n, u = (float(v) for v in self.estimate_enu_m[k])
            yield [int(self.stamp_ns[k]), float(self.lat_deg[k]), float(self.lon_deg[k]),
                   float(self.height_m[k]), float(self.protection_level_m[k]),
                   float(self.risk_bound[k]), str(self.integrity[k]),
                   float(self.horizontal_error_m[k]), str(self.status[k]),
                   str(self.reason[k]), e, n, u, int(self.satellites[k])]


def empty_epoch_table() -> EpochTable:
    z = np.zeros(0)
    return EpochTable(np.zeros(0, np.int64), np.zeros(0, str), np.zeros(0, str),
                      np.zeros((0, 3)), z, z, z, z, z, np.zeros(0, str), z,
                      np.zeros(0, int))


@dataclass
class RunRecord:
    """Per-epoch arrays of one filter run (only epochs with a GNSS update and truth);
    ``epochs`` holds one row for every GNSS epoch."""

    stamp_ns: np.ndarray
    estimate_enu_m: np.ndarray
    truth_enu_m: np.ndarray
    risk_bound: dict            # method -> (T, A)
    reference_risk: np.ndarray  # (T, A)
    alert_limits_m: np.ndarray
    protection_level_m: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (T,)
    # (T, 3, 3) the covariance reported with each estimate (``EpochResult.covariance_m2``).
    covariance_m2: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    # (T,) the verdict is OK (``IntegrityVerdict.ok``).
    integrity_ok: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    # (T,) ``IntegrityVerdict.valid``: the flag at a further alert limit L is
    # valid & (PL <= L).
    integrity_valid: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    statuses: dict = field(default_factory=dict)
    seconds: float = 0.0
    camera_alpha: dict = field(default_factory=dict)   # frame_id -> mixture weight alpha*
    camera_excluded_epochs: int = 0
    camera_epochs: int = 0
    epochs: EpochTable = field(default_factory=empty_epoch_table)
    #: Epochs at which the filter recovered (``EpochResult.recovered``: part of the cloud
    #: moved onto the snapshot solution), counted over every GNSS epoch of the run.
    recoveries: int = 0


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


def offline_camera_matches(camera, database, top_k: int = 5) -> list[CameraMeasurement]:
    """Best database match of every frame of a camera stream, as camera_node produces them
    (top-``top_k`` query, best first; ``frame_id`` counts every frame) and the engine
    keeps them (:func:`~gnsscam_ros.core.engine.best_match`).

    Args:
        camera: Frames (``bags.read.BagCamera`` or ``datasets.emulated.camera.CameraStream``).
        database: The map database (positions in the map frame).
        top_k: camera_node's ``top_k``.
    """
    out = []
    positions = database.positions.enu_m
    for i, stamp, image in camera.frames():
        found = database.query(image, top_k=top_k)
        match = best_match(stamp, positions[[f.index for f in found]],
                           np.array([f.score for f in found]), i)
        if match is not None:
            out.append(match)
    return out


def run_filter(drive: Drive, config: FilterConfig, seed: int = 0, progress: bool = False,
               camera_matches: list[CameraMeasurement] | None = None,
               states: list[DeadReckoningState] | None = None,
               dr_config: DeadReckoningConfig | None = None) -> RunRecord:
    """Run the particle filter over a drive; truth is used only for scoring.

    The inputs go through the nodes' path (:func:`engine_reports`): imu_node's dead
    reckoning over the drive's odometry and IMU, and the camera matches, into an
    :class:`~gnsscam_ros.core.engine.EpochEngine`.

    Args:
        drive: The data.
        config: Filter parameters.
        seed: Seed of the filter's random generator.
        progress: Show progress on stderr.
        camera_matches: Best database match of every camera image (position at the image
            time, map frame); None runs GNSS only.
        states: Dead-reckoning states to use instead of dead-reckoning the drive (tests
            that lose or restart the dead reckoning).
        dr_config: imu_node's dead-reckoning parameters (default: its defaults).

    Returns:
        Per-epoch estimates, truth, risk bounds (configured and other inverse method) and
        reference risks for every alert limit of the configuration.
    """
    return run_epochs(drive, config, seed, camera_matches, states, dr_config, progress)[0]


def engine_reports(engine: EpochEngine, epochs: list[GnssEpoch],
                   states: list[DeadReckoningState] | None,
                   camera_matches: list[CameraMeasurement] | None) -> Iterator[EpochReport]:
    """Feed a drive's inputs to an engine in stamp order, as the replayed nodes get them,
    and yield the report of each GNSS epoch (the engine's state is that epoch's when it
    is yielded).

    At equal stamps dead reckoning comes before camera images and those before GNSS
    (the replay's tie order). Every epoch is run once its inputs have reached it, and the
    rest when the inputs end.
    """
    states = list(states or [])
    matches = list(camera_matches or [])
    events = ([(s.stamp_ns, 0, k) for k, s in enumerate(states)]
              + [(m.stamp_ns, 1, k) for k, m in enumerate(matches)]
              + [(e.stamp_ns, 2, k) for k, e in enumerate(epochs)])
    events.sort()
    for _, kind, k in events:
        if kind == 0:
            engine.add_dead_reckoning(states[k])
        elif kind == 1:
            engine.add_camera(matches[k].stamp_ns, matches[k])
        else:
            engine.add_gnss(epochs[k])
        if engine.queue:
            yield from engine.ready_reports()
    yield from engine.ready_reports(flush=True)


def run_epochs(drive: Drive, config: FilterConfig, seed: int,
               camera_matches: list[CameraMeasurement] | None = None,
               states: list[DeadReckoningState] | None = None,
               dr_config: DeadReckoningConfig | None = None,
               progress: bool = False) -> tuple[RunRecord, EpochEngine]:
    """The filter over every GNSS epoch of a drive, scored against its truth.

    Arguments as :func:`run_filter`.

    Returns:
        The run record and the engine after the run (its filter's map frame, its motion
        accumulator's counts).
    """
    frame = LocalFrame(*drive.origin_llh) if drive.origin_llh is not None else None
    if states is None:
        states = dead_reckon(drive.imu, drive.odometry, dr_config)
    engine = EpochEngine(config, frame=frame, rng=np.random.default_rng(seed),
                         timing=InputTiming(gnss_queue_size=None))
    limits = config.alert_limits_m
    other = integrity.APPROX if config.inverse_bernoulli == integrity.EXACT else integrity.EXACT
    stamps, estimates, bounds, bounds_other, references = [], [], [], [], []
    levels, oks, valids, covariances = [], [], [], []
    statuses: dict[str, int] = {}
    bar = Progress(f'filter {drive.name}', len(drive.gnss), progress)
    start = time.monotonic()
    truth_enu = None
    camera_alpha: dict[int, float] = {}
    camera_epochs = camera_excluded = recoveries = 0
    rows = []       # every epoch: (stamp, status, reason, enu, PL, bound, level, sats)
    for i, report in enumerate(engine_reports(engine, drive.gnss, states, camera_matches)):
        epoch, result = report.epoch, report.result
        if result.camera_alpha is not None:
            camera_epochs += 1
            camera_excluded += int(result.camera_excluded)
            camera_alpha.update(zip(result.camera_frame_ids, result.camera_alpha.tolist()))
        statuses[result.status] = statuses.get(result.status, 0) + 1
        recoveries += int(result.recovered)
        bar.update(i + 1)
        rows.append(_epoch_row(report))
        if result.status != UPDATED or drive.truth is None:
            continue
        if truth_enu is None:
            truth_enu = engine.frame.ecef_to_enu(drive.truth.ecef_m)
        truth = np.array([np.interp(epoch.stamp_ns, drive.truth.stamp_ns, truth_enu[:, j])
                          for j in range(3)])
        stamps.append(epoch.stamp_ns)
        estimates.append(result.position_enu_m)
        bounds.append(result.risk.risk_bound)
        bounds_other.append(integrity.risk_bound(
            result.risk.empirical_risk, result.risk.kl_nats, config.n_posteriors,
            config.risk_delta, other).risk_bound)
        references.append(report.posterior_set.hazard_mass(truth, limits))
        levels.append(result.protection_level_m)
        covariances.append(result.covariance_m2)
        oks.append(report.verdict.ok)
        valids.append(report.verdict.valid)
    seconds = time.monotonic() - start
    stamps_arr = np.array(stamps, dtype=np.int64)
    record = RunRecord(
        stamp_ns=stamps_arr, estimate_enu_m=np.array(estimates).reshape(-1, 3),
        truth_enu_m=(truth_at(drive, engine.frame, stamps_arr) if stamps
                     else np.zeros((0, 3))),
        risk_bound={config.inverse_bernoulli: np.array(bounds).reshape(-1, len(limits)),
                    other: np.array(bounds_other).reshape(-1, len(limits))},
        reference_risk=np.array(references).reshape(-1, len(limits)), alert_limits_m=limits,
        protection_level_m=np.array(levels, dtype=float),
        covariance_m2=np.array(covariances, dtype=float).reshape(-1, 3, 3),
        integrity_ok=np.array(oks, dtype=bool),
        integrity_valid=np.array(valids, dtype=bool),
        statuses=statuses, seconds=seconds, camera_alpha=camera_alpha,
        camera_excluded_epochs=camera_excluded, camera_epochs=camera_epochs,
        epochs=_epoch_table(rows, engine.frame, drive), recoveries=recoveries)
    return record, engine


def _epoch_row(report: EpochReport) -> tuple:
    result, verdict = report.result, report.verdict
    updated = result.status == UPDATED
    enu = (np.full(3, np.nan) if result.position_enu_m is None
           else np.asarray(result.position_enu_m, dtype=float))
    pl = (float(result.protection_level_m) if updated and result.protection_level_m
          is not None else np.nan)
    bound = (float(result.risk.risk_bound[0]) if updated and result.risk is not None
             else np.nan)
    # Not updated: the filter's reason (the verdict adds its STALE prefix); updated: the
    # verdict's first reason against OK ('' when OK).
    reason = result.reason if not updated else (verdict.reasons or ('',))[0]
    return (int(result.stamp_ns), result.status, reason or '', enu, pl, bound,
            verdict.level, int(result.n_satellites))


def _epoch_table(rows: list[tuple], frame: LocalFrame | None, drive: Drive) -> EpochTable:
    """The per-epoch table of a run: WGS84 estimates and the horizontal error."""
    if not rows:
        return empty_epoch_table()
    stamps = np.array([r[0] for r in rows], dtype=np.int64)
    enu = np.array([r[3] for r in rows], dtype=float).reshape(-1, 3)
    lat = lon = height = np.full(len(rows), np.nan)
    if frame is not None:
        have = np.all(np.isfinite(enu), axis=1)
        lat, lon, height = (np.full(len(rows), np.nan) for _ in range(3))
        if have.any():
            la, lo, h = frame.enu_to_geodetic(enu[have])
            lat[have], lon[have], height[have] = la, lo, h
    err = np.full(len(rows), np.nan)
    if drive.truth is not None and frame is not None and len(drive.truth):
        truth = truth_at(drive, frame, stamps)
        err = np.hypot(enu[:, 0] - truth[:, 0], enu[:, 1] - truth[:, 1])
    return EpochTable(
        stamp_ns=stamps, status=np.array([r[1] for r in rows], dtype=object),
        reason=np.array([r[2] for r in rows], dtype=object), estimate_enu_m=enu,
        lat_deg=lat, lon_deg=lon, height_m=height,
        protection_level_m=np.array([r[4] for r in rows], dtype=float),
        risk_bound=np.array([r[5] for r in rows], dtype=float),
        integrity=np.array([r[6] for r in rows], dtype=object), horizontal_error_m=err,
        satellites=np.array([r[7] for r in rows], dtype=int))


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


def run_nees(record: RunRecord, config: FilterConfig) -> np.ndarray:
    """(T,) NEES of a run's errors against its reported covariances, measured like the
    PL (east-north by default; ``metrics.nees``)."""
    d = 2 if config.horizontal_risk else 3
    return nees((record.estimate_enu_m - record.truth_enu_m)[:, :d],
                record.covariance_m2[:, :d, :d])


def bound_miss_share(config: FilterConfig) -> float:
    """The share of the pooled posterior mass the risk bound lets lie beyond its level
    when the posteriors agree with their priors (``q_max`` at a KL divergence of 0): what
    a level exactly as wide as the bound says may miss (``metrics.level_sizing``)."""
    return integrity.max_empirical_risk(
        config.target_risk,
        integrity.divergence_budget(0.0, config.n_posteriors, config.risk_delta),
        config.inverse_bernoulli)


def summarize(record: RunRecord, config: FilterConfig) -> dict:
    """Accuracy and integrity metrics of a run, keyed like the evaluation JSON."""
    out = accuracy(record.estimate_enu_m, record.truth_enu_m)
    diff = record.estimate_enu_m - record.truth_enu_m
    err = np.hypot(diff[:, 0], diff[:, 1]) if config.horizontal_risk else np.linalg.norm(
        diff, axis=1)
    # Declared sufficient = the flag a user sees at that alert limit: at the configured
    # one the verdict itself (as the evaluation of a result bag takes it); at a further
    # limit, the verdict's valid (settled, motion known) and PL <= AL (configured
    # method); for the other inverse, valid and its bound within the target.
    valid = (record.integrity_valid if record.integrity_valid.size == err.size
             else np.ones(err.size, dtype=bool))
    by_method = {}
    for method, bounds in record.risk_bound.items():
        by_method[method] = {}
        for a, limit in enumerate(record.alert_limits_m):
            if (method == config.inverse_bernoulli and a == 0
                    and record.integrity_ok.size == err.size):
                declared = record.integrity_ok
            elif (method == config.inverse_bernoulli
                  and record.protection_level_m.size == err.size):
                declared = valid & (record.protection_level_m <= limit)
            else:
                declared = valid & (bounds[:, a] <= config.target_risk)
            by_method[method][f'{limit:g}'] = integrity_metrics(
                err, bounds[:, a], record.reference_risk[:, a], limit, config.target_risk,
                declared_ok=declared)
    out['integrity'] = by_method[config.inverse_bernoulli]
    out['integrity_by_inverse_bernoulli'] = by_method
    out['protection_level'] = protection_level_metrics(
        err, record.protection_level_m, config.alert_limit_m,
        integrity_ok=record.integrity_ok if record.integrity_ok.size == err.size else None)
    if record.protection_level_m.size == err.size:
        out['level_sizing'] = level_sizing(err, record.protection_level_m,
                                           bound_miss_share(config))
    if record.covariance_m2.shape[0] == err.size:
        out['cloud_calibration'] = cloud_calibration(run_nees(record, config),
                                                     2 if config.horizontal_risk else 3)
    out['statuses'] = record.statuses
    out['recoveries'] = record.recoveries
    out['filter_seconds'] = record.seconds
    return out
