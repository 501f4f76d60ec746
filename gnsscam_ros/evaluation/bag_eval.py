"""Metrics of a run recorded in a bag (``gnsscam_eval bag RESULT_BAG``).

The nodes publish ``integrity_risk`` (one verdict per GNSS epoch), ``pose`` (map frame),
``fix`` (WGS84) and ``particles``; record them together with the replayed
``ground_truth/pose`` and ``map/origin`` (or pass the dataset bag as ``truth_bag``), e.g.::

    ros2 bag record -o result /integrity_risk /pose /fix /particles \\
        /ground_truth/pose /map/origin

:func:`evaluate_result_bag` returns the dictionary of the offline evaluation
(:func:`.runner.summarize` and :func:`.evaluate.evaluate_drive`), computed by the same
functions (:func:`.runner.accuracy`, :func:`.metrics.integrity_metrics`,
:func:`..core.integrity.hazard_mass`, :func:`.runner.run_snapshot_baseline`).

How the bag maps onto the offline quantities:

* **Epochs**: the ``integrity_risk`` verdicts with level OK or ERROR (the node's UPDATED
  epochs; STALE = no valid solution is counted in ``statuses`` only), joined to the
  estimate with the same stamp as their ``epoch_stamp``.
* **Estimate**: ``fix`` when recorded: WGS84 does not depend on where the node anchored its
  ``map`` frame (by default at its first fix, not at ``map/origin``). Otherwise ``pose``,
  which then must be in the ENU frame at ``map/origin`` (or ``origin_llh``).
  Errors are measured in the ENU frame at ``map/origin`` (else at the first truth point).
* **Alert limits and bounds**: ``alert_limit_m`` / ``risk_bound`` of each verdict, plus the
  typed ``risk_bounds_by_limit`` for further limits; the target is ``target_risk``. Only the
  inverse-Bernoulli method the node ran (extra ``inverse_bernoulli``) is available.
* **Reference risk** (mass of the posterior beyond the alert limit from the true
  position): from the recorded ``particles`` of the epoch, taken as equally weighted
  (exact when the node publishes its weighted subsample, ``max_published_particles``),
  moved by ``fix - pose`` so that they sit around the estimate used; without particles,
  from the Gaussian of the ``pose`` (or ``fix``) covariance, with 4096 fixed draws. The
  offline runner averages the M posteriors instead, so failure ratio, failure error and
  bound gap are close to, not identical with, an offline run; RMSE, P_FA and P_MI only
  depend on estimate, bound and truth and are the same.
* **Protection level**: ``protection_level_m`` of each OK/ERROR verdict (a missing or NaN
  value counts as no PL, i.e. inf); ``protection_level`` holds
  :func:`.metrics.protection_level_metrics` at the verdicts' alert limit, with the flag's
  own OK (level OK) for ``flag_ok``.
* **Per-epoch rows** (:func:`evaluate_result_bag_epochs`, ``--epochs-csv``): one per GNSS
  epoch of the dataset bag when it has GNSS, else per epoch named by an
  ``integrity_risk`` message; an epoch without an OK/ERROR verdict is STALE.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pymap3d

from ..bags import schema
from ..bags.errors import BagContentError
from ..bags.read import ResultBag, read_drive, read_results
from ..core.filter import FilterConfig
from ..core.frames import LocalFrame
from ..core.integrity import hazard_mass
from ..core.types import Drive
from .metrics import integrity_metrics, protection_level_metrics
from .runner import EpochTable, accuracy, empty_epoch_table, run_snapshot_baseline, truth_at

_LEVELS = {0: 'OK', 1: 'WARN', 2: 'ERROR', 3: 'STALE'}
REFERENCE_SAMPLES = 4096


def _gaussian_samples(centre: np.ndarray, cov: np.ndarray, z: np.ndarray) -> np.ndarray:
    """(K, 3) draws of N(centre, cov) from fixed standard normal draws ``z``."""
    cov = 0.5 * (cov + cov.T)
    vals, vecs = np.linalg.eigh(cov)
    # Eigen-decomposition instead of Cholesky: tolerates the semi-definite covariance of a
    # collapsed particle set.
    return centre + (z * np.sqrt(np.clip(vals, 0.0, None))) @ vecs.T


def _estimates(res: ResultBag, frame: LocalFrame, origin_known: bool
               ) -> tuple[str, np.ndarray, np.ndarray]:
    """``(source, stamps (E,), ENU (E, 3))`` of the estimates in the evaluation frame."""
    if len(res.fix_stamp_ns):
        ecef = np.column_stack(pymap3d.geodetic2ecef(res.fix_llh[:, 0], res.fix_llh[:, 1],
                                                     res.fix_llh[:, 2]))
        return 'fix', res.fix_stamp_ns, frame.ecef_to_enu(ecef)
    if len(res.pose_stamp_ns):
        if not origin_known:
            raise BagContentError(
                f'{res.path}: only {schema.POSE} (map frame) and no {schema.FIX}, and the '
                f'map origin is unknown: record {schema.FIX} or {schema.ORIGIN}, or pass the '
                'origin', path=res.path, topic=schema.POSE)
        return 'pose', res.pose_stamp_ns, res.pose_enu_m
    raise BagContentError(f'{res.path}: no {schema.FIX} or {schema.POSE} messages',
                          path=res.path)


def _verdicts(res: ResultBag) -> dict[int, object]:
    """The last OK/ERROR verdict of each epoch, keyed by its epoch stamp [ns]."""
    out = {}
    for risk in res.integrity:
        if risk.level in (0, 2) and math.isfinite(risk.risk_bound):
            stamp = risk.epoch_stamp_ns if risk.epoch_stamp_ns is not None else risk.stamp_ns
            out[int(stamp)] = risk
    return out


def _bounds(risk) -> dict[float, float]:
    """``{alert limit [m]: risk bound}`` of one verdict (main limit and extras)."""
    return {float(risk.alert_limit_m): float(risk.risk_bound),
            **{float(k): float(v) for k, v in risk.risk_bounds_by_limit.items()}}


def _pl(risk) -> float:
    """The protection level of a verdict, NaN when it carries none."""
    value = getattr(risk, 'protection_level_m', None)
    return math.nan if value is None else float(value)


def _epoch_table(res: ResultBag, verdicts: dict, frame: LocalFrame, est_stamps: np.ndarray,
                 est_enu: np.ndarray, truth_drive: Drive, gnss_drive: Drive | None
                 ) -> EpochTable:
    """One row per GNSS epoch (see the module docstring)."""
    if gnss_drive is not None:
        stamps = sorted({int(e.stamp_ns) for e in gnss_drive.gnss})
    elif res.integrity:
        stamps = sorted({int(r.epoch_stamp_ns if r.epoch_stamp_ns is not None else r.stamp_ns)
                         for r in res.integrity})
    else:
        stamps = sorted(int(s) for s in est_stamps)
    if not stamps:
        return empty_epoch_table()
    stale = {}
    for r in res.integrity:
        key = int(r.epoch_stamp_ns if r.epoch_stamp_ns is not None else r.stamp_ns)
        if r.stamp_ns == key:          # the epoch's own report, not a periodic one
            stale[key] = r
    est_index = {int(s): i for i, s in enumerate(est_stamps)}
    n = len(stamps)
    enu = np.full((n, 3), np.nan)
    pl, bound = np.full(n, np.nan), np.full(n, np.nan)
    levels, status, reason = (np.empty(n, dtype=object) for _ in range(3))
    sats = np.zeros(n, dtype=int)
    for k, s in enumerate(stamps):
        if s in est_index:
            enu[k] = est_enu[est_index[s]]
        v = verdicts.get(s)
        if v is not None:
            pl[k], bound[k] = _pl(v), float(v.risk_bound)
            levels[k] = _LEVELS.get(v.level, str(v.level))
        else:
            levels[k] = 'STALE'
            v = stale.get(s)
        status[k] = '' if v is None else (v.epoch_status or 'no_gnss')
        reason[k] = '' if v is None else v.message
        try:
            sats[k] = int(float(v.extra.get('n_satellites', 0))) if v is not None else 0
        except ValueError:
            sats[k] = 0
    stamps_arr = np.array(stamps, dtype=np.int64)
    lat, lon, height = (np.full(n, np.nan) for _ in range(3))
    have = np.all(np.isfinite(enu), axis=1)
    if have.any():
        la, lo, h = frame.enu_to_geodetic(enu[have])
        lat[have], lon[have], height[have] = la, lo, h
    truth = truth_at(truth_drive, frame, stamps_arr)
    err = np.hypot(enu[:, 0] - truth[:, 0], enu[:, 1] - truth[:, 1])
    return EpochTable(stamp_ns=stamps_arr, status=status, reason=reason, estimate_enu_m=enu,
                      lat_deg=lat, lon_deg=lon, height_m=height, protection_level_m=pl,
                      risk_bound=bound, integrity=levels, horizontal_error_m=err,
                      satellites=sats)


def _reference_risks(res: ResultBag, stamps: list[int], est: np.ndarray,
                     true_enu: np.ndarray, limits: list[float], horizontal: bool,
                     source: str) -> tuple[np.ndarray, dict]:
    """Reference risk per epoch and alert limit from the recorded posterior (module doc):
    ``((T, A) risks, {posterior source: epochs})``."""
    pose_index = {int(s): i for i, s in enumerate(res.pose_stamp_ns)}
    z = np.random.default_rng(0).standard_normal((REFERENCE_SAMPLES, 3))
    limits_arr = np.array(limits, dtype=float)
    reference = np.full((len(stamps), len(limits)), np.nan)
    sources = {'particles': 0, 'pose_covariance': 0, 'fix_covariance': 0, 'none': 0}
    fix_cov = dict(zip((int(s) for s in res.fix_stamp_ns), res.fix_cov_enu_m2))
    for k, s in enumerate(stamps):
        if not len(limits):
            break
        p = pose_index.get(s)
        offset = est[k] - res.pose_enu_m[p] if p is not None else None
        cloud = res.particles.get(s)
        if cloud is not None and len(cloud) and (p is not None or source == 'pose'):
            samples = cloud[:, :3] + (offset if offset is not None else 0.0)
            sources['particles'] += 1
        elif p is not None and np.all(np.isfinite(res.pose_cov[p, :3, :3])):
            samples = _gaussian_samples(est[k], res.pose_cov[p, :3, :3], z)
            sources['pose_covariance'] += 1
        elif s in fix_cov and np.all(np.isfinite(fix_cov[s])):
            samples = _gaussian_samples(est[k], fix_cov[s], z)
            sources['fix_covariance'] += 1
        else:
            sources['none'] += 1
            continue
        n = samples.shape[0]
        reference[k] = hazard_mass(samples[None], np.full((1, n), -math.log(n)), true_enu[k],
                                   limits_arr, horizontal)

    return reference, sources


def _integrity_by_limit(verdicts: dict, stamps: list[int], err: np.ndarray,
                        reference: np.ndarray, limits: list[float], target: float
                        ) -> tuple[float, dict, str]:
    """``(the verdicts' own alert limit, {limit: integrity metrics}, inverse method)``."""
    defaults = FilterConfig()
    main_limits = {float(verdicts[s].alert_limit_m) for s in stamps if s in verdicts}
    main_limit = (main_limits.pop() if len(main_limits) == 1
                  else limits[0] if limits else defaults.alert_limit_m)
    # At the verdicts' own alert limit "declared sufficient" is the published level OK;
    # for further limits the flag would be: valid (settled, motion known; the
    # ``integrity_valid`` extra, taken as true when absent) and the bound within the target.
    flagged_ok = np.array([s in verdicts and verdicts[s].integrity_ok for s in stamps])
    valid = np.array([s in verdicts and verdicts[s].extra.get('integrity_valid', 'true')
                      == 'true' for s in stamps])
    by_limit = {}
    for a, limit in enumerate(limits):
        bound = np.array([_bounds(verdicts[s]).get(limit, np.nan) for s in stamps],
                         dtype=float)
        keep = np.isfinite(bound)
        declared = (flagged_ok[keep] if limit == main_limit
                    else valid[keep] & (bound[keep] <= target))
        by_limit[f'{limit:g}'] = integrity_metrics(err[keep], bound[keep],
                                                   reference[keep, a], limit, target,
                                                   declared_ok=declared)
    methods = {str(verdicts[s].extra.get('inverse_bernoulli', 'published'))
               for s in stamps if s in verdicts}
    method = methods.pop() if len(methods) == 1 else 'published'
    return main_limit, by_limit, method


def _baseline(gnss_drive: Drive | None, truth_drive: Drive, frame: LocalFrame,
              var_m2: float) -> dict:
    """Snapshot WLS accuracy on the dataset's GNSS (None values without GNSS)."""
    baseline = {'rmse_2d_m': None, 'rmse_3d_m': None, 'epochs': 0, 'p50_2d_m': None,
                'p95_2d_m': None, 'max_2d_m': None}
    if gnss_drive is not None:
        b_stamps, fixes = run_snapshot_baseline(gnss_drive, frame, var_m2)
        if len(b_stamps):
            baseline = accuracy(fixes, truth_at(truth_drive, frame, b_stamps))
    return baseline


def evaluate_result_bag(result_bag: str | Path, truth_bag: str | Path | None = None,
                        namespace: str = '/', origin_llh: tuple | None = None,
                        horizontal_risk: bool | None = None,
                        measurement_var_m2: float | None = None) -> dict:
    """Accuracy and integrity metrics of a recorded run (the offline evaluation's keys).

    See :func:`evaluate_result_bag_epochs` (this is its dictionary).
    """
    return evaluate_result_bag_epochs(result_bag, truth_bag, namespace, origin_llh,
                                      horizontal_risk, measurement_var_m2)[0]


def evaluate_result_bag_epochs(result_bag: str | Path, truth_bag: str | Path | None = None,
                               namespace: str = '/', origin_llh: tuple | None = None,
                               horizontal_risk: bool | None = None,
                               measurement_var_m2: float | None = None
                               ) -> tuple[dict, EpochTable]:
    """Accuracy and integrity metrics of a recorded run, and its per-epoch rows.

    Args:
        result_bag: Bag with ``integrity_risk`` and ``fix`` or ``pose`` (optionally
            ``particles``, ``ground_truth/pose``, ``map/origin``, ``gnss/pseudoranges``).
        truth_bag: The dataset bag (from ``gnsscam_convert``) when the result bag lacks
            ground truth; its GNSS also gives the snapshot WLS baseline.
        namespace: Namespace of the recorded topics.
        origin_llh: Origin of the nodes' ``map`` frame (lat_deg, lon_deg, alt_m), when
            neither bag has ``map/origin`` and only ``pose`` was recorded.
        horizontal_risk: Alert limits on horizontal (True) or 3D error (default: the
            filter's default, horizontal).
        measurement_var_m2: Pseudorange variance of the WLS baseline [m^2] (default: the
            filter's default).

    Returns:
        ``rmse_2d_m``, ``rmse_3d_m``, ``epochs``, ``p50_2d_m``, ``p95_2d_m``, ``max_2d_m``,
        ``integrity`` (by alert limit, :func:`.metrics.integrity_metrics`),
        ``integrity_by_inverse_bernoulli``, ``protection_level``
        (:func:`.metrics.protection_level_metrics`), ``statuses`` (integrity levels),
        ``filter_seconds`` (None), ``baseline_wls`` (None values without GNSS),
        ``rmse_2d_ratio_to_wls`` and ``bag`` (sources, counts, origin); and the
        :class:`.runner.EpochTable` of every GNSS epoch.

    Raises:
        BagReadError, BagTypeError: Unreadable bag or wrong topic type (file/topic named).
        BagContentError: No ground truth, no estimates, or an unknown map origin.
    """
    defaults = FilterConfig()
    horizontal = defaults.horizontal_risk if horizontal_risk is None else horizontal_risk
    var_m2 = defaults.measurement_var_m2 if measurement_var_m2 is None else measurement_var_m2
    res = read_results(result_bag, namespace)
    truth, origin, gnss_drive = res.truth, res.origin_llh, None
    if truth_bag is not None:
        dataset = read_drive(truth_bag, namespace, require_gnss=False)
        truth = truth if truth is not None else dataset.truth
        origin = origin if origin is not None else dataset.origin_llh
        gnss_drive = dataset if dataset.gnss else None
    if origin_llh is not None:
        origin = tuple(float(v) for v in origin_llh)
    if truth is None or not len(truth):
        raise BagContentError(f'{res.path}: no {schema.TRUTH} to evaluate against; record it '
                              'or pass the dataset bag', path=res.path, topic=schema.TRUTH)
    frame = LocalFrame.at_origin_or(origin, truth.ecef_m[0])
    source, est_stamps, est_enu = _estimates(res, frame, origin is not None)
    est_index = {int(s): i for i, s in enumerate(est_stamps)}

    verdicts = _verdicts(res)
    if res.integrity:
        stamps = [s for s in sorted(verdicts) if s in est_index]
    else:
        stamps = sorted(est_index)
    unmatched = sum(1 for s in verdicts if s not in est_index)
    stamps_arr = np.array(stamps, dtype=np.int64)
    idx = np.array([est_index[s] for s in stamps], dtype=int)
    est = est_enu[idx].reshape(-1, 3)
    truth_drive = Drive(name='truth', origin_llh=None, gnss=[], odometry=None, imu=None,
                        truth=truth)
    true_enu = (truth_at(truth_drive, frame, stamps_arr) if len(stamps)
                else np.zeros((0, 3)))
    out = accuracy(est, true_enu)

    # Alert limits in the order first seen; an epoch lacking a limit is left out of it.
    limits: list[float] = []
    for b in (_bounds(verdicts[s]) for s in stamps if s in verdicts):
        limits += [a for a in b if a not in limits]
    targets = {float(verdicts[s].target_risk) for s in stamps if s in verdicts}
    if len(targets) > 1:
        raise BagContentError(f'{res.path}: target_risk changes during the run '
                              f'({sorted(targets)}); evaluate the parts separately',
                              path=res.path, topic=schema.INTEGRITY)
    target = targets.pop() if targets else defaults.target_risk

    reference, sources = _reference_risks(res, stamps, est, true_enu, limits, horizontal,
                                          source)
    diff = est - true_enu
    err = np.hypot(diff[:, 0], diff[:, 1]) if horizontal else np.linalg.norm(diff, axis=1)
    main_limit, by_limit, method = _integrity_by_limit(verdicts, stamps, err, reference,
                                                       limits, target)
    out['integrity'] = by_limit
    out['integrity_by_inverse_bernoulli'] = {method: by_limit}
    pl = np.array([_pl(verdicts[s]) if s in verdicts else math.nan for s in stamps],
                  dtype=float)
    ok = np.array([s in verdicts and verdicts[s].level == 0 for s in stamps], dtype=bool)
    out['protection_level'] = protection_level_metrics(err, pl, main_limit, integrity_ok=ok)
    levels: dict[str, int] = {}
    for risk in res.integrity:
        name = _LEVELS.get(risk.level, str(risk.level))
        levels[name] = levels.get(name, 0) + 1
    out['statuses'] = levels
    out['filter_seconds'] = None

    baseline = _baseline(gnss_drive, truth_drive, frame, var_m2)
    out['baseline_wls'] = baseline
    out['rmse_2d_ratio_to_wls'] = (out['rmse_2d_m'] / baseline['rmse_2d_m']
                                   if baseline['rmse_2d_m'] and len(stamps) else None)
    out['target_risk'] = target
    out['bag'] = {'result': str(res.path), 'truth': None if truth_bag is None
                  else str(truth_bag), 'estimate_source': source,
                  'reference_risk_source': sources, 'unmatched_verdicts': unmatched,
                  'origin_llh': None if origin is None else list(origin),
                  'horizontal_risk': horizontal, 'topics': res.topics}
    table = _epoch_table(res, verdicts, frame, est_stamps, est_enu, truth_drive, gnss_drive)
    return out, table
