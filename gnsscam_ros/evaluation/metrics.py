"""Accuracy and integrity metrics (paper §7.3).

Definitions, per epoch with a GNSS update, for one alert limit AL:

* position error: distance between estimate and ground truth (2D: east-north; 3D);
  RMSE is the root of the mean squared error over epochs.
* fault (hazardous event): the position error (horizontal, like the risk) exceeds AL.
* declared sufficient: the integrity flag a user sees says OK at AL (the filter has
  settled, the motion is known and the protection level is within AL); without a flag
  (``declared_ok`` not given), the risk bound is within the target risk.
* P_FA = (#insufficient and no fault) / (#no fault): false alarms among fault-free epochs.
* P_MI = (#sufficient and fault) / (#fault): missed identifications among faulty epochs.
* failure: the risk bound is below the reference risk (computed with ground truth);
  failure ratio = #failures / #epochs; failure error = mean position error over the
  failures (None when there are none); bound gap = mean of (bound - reference risk).

Protection level (PL: the smallest radius around the estimate whose risk bound is within
the target risk; inf when there is none), per epoch with a GNSS update, error measured like
the PL (horizontal by default):

* misleading information (MI): error > PL; MI rate = #MI / #epochs (an inf PL is never MI).
* availability at AL: share of epochs with PL <= AL (what the flag needs to say OK).
* HMI given available at AL (``hmi_given_available``): among the epochs with PL <= AL,
  the share whose error exceeds AL, i.e. how often "OK by the PL" was hazardously wrong.
* flag OK with error > AL (``flag_ok``, at the configured alert limit, from the filter's
  own verdict, which also needs known motion): among the epochs the flag said OK, the
  share whose error exceeds the alert limit.
* PL median and 95th percentile: order statistics with inf (and a missing PL, NaN) counted
  as inf, so they are inf when that many epochs have no finite PL.
* Stanford counts at the configured alert limit: ``report.stanford_counts``.

Cloud calibration (``cloud_calibration``), per epoch with a GNSS update: the normalised
estimation error squared ``NEES = e' P^-1 e`` of the error ``e`` against the covariance
``P`` the filter reports with its estimate (the chosen set's), both measured like the PL
(east-north, or 3D). For a cloud whose spread matches its errors NEES follows a chi-square
law of 2 (3) degrees of freedom, median 1.386 (2.366). ``spread_to_error`` =
``sqrt(calibrated median / median NEES)``: 1 for a calibrated cloud, 2 for one twice as
wide as its errors (a PL that large for that reason, not for the bound's margin),
below 1 for an overconfident one. Epochs whose covariance is not finite or not positive
definite are left out (``epochs`` counts those used).

Level sizing (``level_sizing``): what the protection level's *shape* is worth apart from
its size. The scale ``k`` that leaves exactly a share ``miss_share`` of the epochs with an
error beyond ``k * PL`` (the ``1 - miss_share`` quantile of error / PL), and the median
level over the median error after that scaling. With ``miss_share`` the share the risk
bound itself allows to lie beyond its level (``q_max`` at a KL divergence of 0: 0.0288 at
the defaults), ``pl_to_error_sized`` is the smallest median PL / error a level of this
shape could have while missing no more often than the bound says it may; ``scale`` below 1
says by how much the level is wider than that, above 1 that it misses more often. Epochs
without a finite level are left out.
"""
from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from .report import stanford_counts

#: Alert limits whose availability every evaluation reports [m].
AVAILABILITY_LIMITS_M = (8.0, 16.0, 25.0, 50.0)


def rmse(errors_m: np.ndarray) -> float:
    """Root mean square of errors [m]; NaN for no epochs."""
    errors_m = np.asarray(errors_m, dtype=float)
    return float(np.sqrt(np.mean(errors_m ** 2))) if errors_m.size else float('nan')


def nees(error_m: np.ndarray, covariance_m2: np.ndarray) -> np.ndarray:
    """(T,) normalised estimation errors squared of (T, d) errors against (T, d, d)
    covariances; NaN where a covariance is not finite or not positive definite."""
    error_m = np.asarray(error_m, dtype=float)
    cov = np.asarray(covariance_m2, dtype=float)
    out = np.full(error_m.shape[0], np.nan)
    usable = np.isfinite(cov).all(axis=(1, 2)) & np.isfinite(error_m).all(axis=1)
    if usable.any():
        # Positive definite: the Cholesky factor exists (eigenvalues > 0).
        usable[usable] = np.linalg.eigvalsh(cov[usable]).min(axis=1) > 0.0
    if usable.any():
        e = error_m[usable]
        out[usable] = np.einsum('ti,ti->t', e, np.linalg.solve(cov[usable], e[..., None])[..., 0])
    return out


def cloud_calibration(nees_values: np.ndarray, dims: int) -> dict:
    """Calibration of the filter's reported spread against its errors from per-epoch
    NEES values of ``dims`` dimensions (see the module docstring): ``epochs``,
    ``median_nees``, ``calibrated_median_nees`` and ``spread_to_error`` (None without
    epochs or with a median of 0)."""
    values = np.asarray(nees_values, dtype=float)
    values = values[np.isfinite(values)]
    calibrated = float(chi2.median(dims))
    median = float(np.median(values)) if values.size else None
    return {'epochs': int(values.size), 'dims': int(dims), 'median_nees': median,
            'calibrated_median_nees': calibrated,
            'spread_to_error': (float(np.sqrt(calibrated / median)) if median else None)}


def level_sizing(error_m: np.ndarray, protection_level_m: np.ndarray,
                 miss_share: float) -> dict:
    """The level's size against its shape (see the module docstring): ``epochs``,
    ``miss_share``, ``pl_to_error`` (median PL over median error, as is), ``scale`` and
    ``pl_to_error_sized`` (None without epochs with a finite level and a median error
    above 0)."""
    err = np.asarray(error_m, dtype=float).ravel()
    pl = np.asarray(protection_level_m, dtype=float).ravel()
    if err.shape != pl.shape:
        raise ValueError(f'error ({err.size}) and protection level ({pl.size}) differ in '
                         'length')
    keep = np.isfinite(pl) & (pl > 0.0) & np.isfinite(err)
    err, pl = err[keep], pl[keep]
    out = {'epochs': int(err.size), 'miss_share': float(miss_share), 'pl_to_error': None,
           'scale': None, 'pl_to_error_sized': None}
    median_error = float(np.median(err)) if err.size else 0.0
    if not median_error > 0.0:
        return out
    # The order statistic with at most ``miss_share`` of the epochs strictly beyond it.
    ratio = np.sort(err / pl)
    scale = float(ratio[min(int(np.ceil((1.0 - miss_share) * err.size)) - 1, err.size - 1)])
    median_level = float(np.median(pl))
    out.update(pl_to_error=median_level / median_error, scale=scale,
               pl_to_error_sized=scale * median_level / median_error)
    return out


def _rate(numerator: int, denominator: int) -> float | None:
    return numerator / denominator if denominator else None


def integrity_metrics(error_m: np.ndarray, risk_bound: np.ndarray, reference_risk: np.ndarray,
                      alert_limit_m: float, target_risk: float,
                      declared_ok: np.ndarray | None = None) -> dict:
    """Integrity metrics of one alert limit over a run (see the module docstring).

    Args:
        error_m: (T,) position errors measured the way the alert limit is [m].
        risk_bound: (T,) risk bounds.
        reference_risk: (T,) reference risks from ground truth.
        alert_limit_m: Alert limit [m].
        target_risk: Integrity target (insufficient when the bound exceeds it).
        declared_ok: (T,) the flag's verdict at this alert limit (True = OK); None: the
            bound within the target counts as declared sufficient.

    Returns:
        ``p_fa``, ``p_mi``, ``failure_ratio``, ``failure_error_m``, ``bound_gap`` and the
        counts behind them (rates are None when their denominator is zero).
    """
    error_m = np.asarray(error_m, dtype=float)
    risk_bound = np.asarray(risk_bound, dtype=float)
    reference_risk = np.asarray(reference_risk, dtype=float)
    fault = error_m > alert_limit_m
    insufficient = (risk_bound > target_risk if declared_ok is None
                    else ~np.asarray(declared_ok, dtype=bool))
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


def percentile_with_inf(values: np.ndarray, q: float) -> float | None:
    """Linear-interpolation percentile where inf (and NaN, taken as inf) count as inf.

    ``np.percentile`` gives NaN when it interpolates towards inf; here the result is inf as
    soon as an inf value takes part. None for no values.
    """
    v = np.asarray(values, dtype=float).ravel()
    if not v.size:
        return None
    v = np.sort(np.where(np.isnan(v), np.inf, v))
    pos = q / 100.0 * (v.size - 1)
    lo, hi = int(np.floor(pos)), int(np.ceil(pos))
    if not np.isfinite(v[hi]):
        return float('inf')
    return float(v[lo] + (v[hi] - v[lo]) * (pos - lo))


def protection_level_metrics(error_m: np.ndarray, protection_level_m: np.ndarray,
                             alert_limit_m: float,
                             availability_limits_m=AVAILABILITY_LIMITS_M,
                             integrity_ok: np.ndarray | None = None) -> dict:
    """Protection-level metrics of a run (see the module docstring).

    Args:
        error_m: (T,) finite position errors measured like the PL [m].
        protection_level_m: (T,) protection levels [m]; inf or NaN = none.
        alert_limit_m: The configured alert limit (Stanford counts, ``flag_ok``) [m].
        availability_limits_m: Alert limits of ``availability`` and
            ``hmi_given_available`` (the configured one is always added) [m].
        integrity_ok: Optional (T,) verdicts of the filter (``EpochResult.integrity_ok``).

    Returns:
        ``epochs``, ``mi_epochs``, ``mi_rate``, ``no_pl_epochs``, ``median_m``, ``p95_m``,
        ``availability`` and ``available_epochs`` keyed by alert limit as a string ("8"),
        ``hmi_given_available`` keyed the same way (``rate``, ``hmi_epochs``,
        ``available_epochs``), ``alert_limit_m``, ``stanford`` (counts at it) and, with
        ``integrity_ok``, ``flag_ok`` (``ok_epochs``, ``error_above_al_epochs``,
        ``error_above_al_rate``). Rates are None without epochs.
    """
    err = np.asarray(error_m, dtype=float).ravel()
    pl = np.asarray(protection_level_m, dtype=float).ravel()
    if err.shape != pl.shape:
        raise ValueError(f'error ({err.size}) and protection level ({pl.size}) differ in '
                         'length')
    pl = np.where(np.isnan(pl), np.inf, pl)
    n = int(err.size)
    mi = int(np.sum(err > pl))
    limits = sorted({float(a) for a in availability_limits_m} | {float(alert_limit_m)})
    availability, available, hmi = {}, {}, {}
    for limit in limits:
        key = f'{limit:g}'
        ok = pl <= limit
        n_ok = int(ok.sum())
        n_hmi = int(np.sum(ok & (err > limit)))
        availability[key] = _rate(n_ok, n)
        available[key] = n_ok
        hmi[key] = {'rate': _rate(n_hmi, n_ok), 'hmi_epochs': n_hmi, 'available_epochs': n_ok}
    out = {
        'epochs': n, 'mi_epochs': mi, 'mi_rate': _rate(mi, n),
        'no_pl_epochs': int(np.sum(~np.isfinite(pl))),
        'median_m': percentile_with_inf(pl, 50), 'p95_m': percentile_with_inf(pl, 95),
        'availability': availability, 'available_epochs': available,
        'hmi_given_available': hmi, 'alert_limit_m': float(alert_limit_m),
        'stanford': stanford_counts(err, pl, alert_limit_m),
    }
    if integrity_ok is not None:
        flag = np.asarray(integrity_ok, dtype=bool).ravel()
        if flag.shape != err.shape:
            raise ValueError(f'integrity_ok ({flag.size}) and error ({err.size}) differ in '
                             'length')
        n_ok = int(flag.sum())
        bad = int(np.sum(flag & (err > alert_limit_m)))
        out['flag_ok'] = {'ok_epochs': n_ok, 'error_above_al_epochs': bad,
                          'error_above_al_rate': _rate(bad, n_ok)}
    return out
