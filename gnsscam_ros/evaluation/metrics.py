"""Accuracy and integrity metrics (design.md §4, paper §7.3).

Definitions, per epoch with a GNSS update, for one alert limit AL:

* position error: distance between estimate and ground truth (2D: east-north; 3D);
  RMSE is the root of the mean squared error over epochs.
* fault (hazardous event): the position error (horizontal, like the risk) exceeds AL.
* declared insufficient: the risk bound exceeds the target risk.
* P_FA = (#insufficient and no fault) / (#no fault): false alarms among fault-free epochs.
* P_MI = (#sufficient and fault) / (#fault): missed identifications among faulty epochs.
* failure: the risk bound is below the reference risk (computed with ground truth);
  failure ratio = #failures / #epochs; failure error = mean position error over the
  failures (None when there are none); bound gap = mean of (bound - reference risk).
"""
from __future__ import annotations

import numpy as np


def rmse(errors_m: np.ndarray) -> float:
    """Root mean square of errors [m]; NaN for no epochs."""
    errors_m = np.asarray(errors_m, dtype=float)
    return float(np.sqrt(np.mean(errors_m ** 2))) if errors_m.size else float('nan')


def _rate(numerator: int, denominator: int) -> float | None:
    return numerator / denominator if denominator else None


def integrity_metrics(error_m: np.ndarray, risk_bound: np.ndarray, reference_risk: np.ndarray,
                      alert_limit_m: float, target_risk: float) -> dict:
    """Integrity metrics of one alert limit over a run (see the module docstring).

    Args:
        error_m: (T,) position errors measured the way the alert limit is [m].
        risk_bound: (T,) risk bounds.
        reference_risk: (T,) reference risks from ground truth.
        alert_limit_m: Alert limit [m].
        target_risk: Integrity target (insufficient when the bound exceeds it).

    Returns:
        ``p_fa``, ``p_mi``, ``failure_ratio``, ``failure_error_m``, ``bound_gap`` and the
        counts behind them (rates are None when their denominator is zero).
    """
    error_m = np.asarray(error_m, dtype=float)
    risk_bound = np.asarray(risk_bound, dtype=float)
    reference_risk = np.asarray(reference_risk, dtype=float)
    fault = error_m > alert_limit_m
    insufficient = risk_bound > target_risk
    failure = risk_bound < reference_risk
    n = int(error_m.size)
    false_alarms = int(np.sum(insufficient & ~fault))
    missed = int(np.sum(~insufficient & fault))
    return {
        'p_fa': _rate(false_alarms, int(np.sum(~fault))),
        'p_mi': _rate(missed, int(np.sum(fault))),
        'failure_ratio': _rate(int(failure.sum()), n),
        'failure_error_m': float(error_m[failure].mean()) if failure.any() else None,
        'bound_gap': float(np.mean(risk_bound - reference_risk)) if n else None,
        'epochs': n,
        'faults': int(fault.sum()),
        'false_alarms': false_alarms,
        'missed_identifications': missed,
        'failures': int(failure.sum()),
        'mean_risk_bound': float(risk_bound.mean()) if n else None,
        'mean_reference_risk': float(reference_risk.mean()) if n else None,
    }
