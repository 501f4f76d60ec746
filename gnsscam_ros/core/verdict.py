"""The integrity verdict of an epoch: decided here, once, from the filter's findings.

The particle filter reports what it found (``filter.EpochResult``: whether the epoch was
an update, the part of the interval without dead reckoning, how long it has settled since
the heading was acquired, the consistency test of the cloud, the protection level and the
risk bounds); :func:`integrity_verdict` turns that into the one verdict every consumer
uses: fusion_node publishes it on ``integrity_risk`` (``msg_adapters.integrity_risk_to_msg``
encodes this type), and the evaluation scores it. Nothing else decides OK.

OK needs all of these, in this order of the reasons against it: a GNSS update
(else STALE), motion known over the whole interval, a cloud consistent with the
measurements, the settling time after the heading acquisition, the protection level
within the alert limit and the risk bound at the alert limit within the target.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from .types import INVALID, UPDATED

if TYPE_CHECKING:       # annotations only: msg_adapters (and with it every node) imports
    # this module, and the filter would bring numba into the light nodes.
    from .config import FilterConfig
    from .filter import EpochResult

#: Integrity levels of a verdict (``integrity_risk``: DiagnosticStatus OK / ERROR / STALE).
OK, ERROR, STALE = 'OK', 'ERROR', 'STALE'


@dataclass(frozen=True)
class IntegrityVerdict:
    """What ``integrity_risk`` publishes for one epoch (or for silence).

    Attributes:
        stamp_ns: Time of the verdict [ns] (the epoch's; a STALE report for silence
            carries the time it was made).
        level: ``OK`` (integrity sufficient), ``ERROR`` (alarm) or ``STALE`` (no valid
            solution behind it).
        message: Human-readable verdict: its level and the first of ``reasons``.
        alert_limit_m: Configured alert limit [m].
        target_risk: Configured target integrity risk.
        risk_bound: Risk bound at the configured alert limit (NaN when STALE).
        empirical_risk: Its empirical part (NaN when STALE).
        divergence_risk: Its divergence part (NaN when STALE).
        epoch_stamp_ns: Stamp of the GNSS epoch behind the verdict (None: none yet).
        protection_level_m: Protection level [m] (NaN when STALE, inf when none).
        epoch_status: Filter status of that epoch ('updated', 'propagated', 'rejected',
            'waiting', 'invalid'); None when no GNSS epoch is behind the verdict.
        risk_bounds_by_limit: ``{alert limit [m]: risk bound}`` of the further alert
            limits (``extra_alert_limits_m``).
        reasons: Why the level is not OK, most fundamental first (empty when OK).
        valid: The findings that do not depend on the alert limit allow OK (an
            update, motion known, settled, consistent with the measurements): the
            flag at a further alert limit L is ``valid and protection level <= L``.
        details: Further figures (satellites, KL, epsilon, motion, camera).
    """

    stamp_ns: int
    level: str
    message: str
    alert_limit_m: float
    target_risk: float
    risk_bound: float = math.nan
    empirical_risk: float = math.nan
    divergence_risk: float = math.nan
    epoch_stamp_ns: int | None = None
    protection_level_m: float = math.nan
    epoch_status: str | None = None
    risk_bounds_by_limit: dict = field(default_factory=dict)
    reasons: tuple[str, ...] = ()
    valid: bool = False
    details: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        """Integrity sufficient (level OK)."""
        return self.level == OK


def stale_verdict(stamp_ns: int, reasons: tuple[str, ...], config: FilterConfig,
                  epoch_stamp_ns: int | None = None,
                  epoch_status: str | None = None) -> IntegrityVerdict:
    """A STALE verdict: no valid solution behind it.

    Args:
        stamp_ns: Time of the verdict [ns].
        reasons: Why there is none (the message joins them).
        config: The filter parameters in force (alert limit, target).
        epoch_stamp_ns: The last GNSS epoch's stamp (None: none yet).
        epoch_status: Its filter status (None: no GNSS epoch behind the verdict).
    """
    return IntegrityVerdict(
        stamp_ns=int(stamp_ns), level=STALE, message='; '.join(reasons),
        alert_limit_m=float(config.alert_limit_m), target_risk=float(config.target_risk),
        epoch_stamp_ns=None if epoch_stamp_ns is None else int(epoch_stamp_ns),
        epoch_status=epoch_status, reasons=tuple(reasons))


def _reasons_against(result: EpochResult, config: FilterConfig) -> tuple[list[str], bool]:
    """``(reasons against OK, most fundamental first; whether the findings that do not
    depend on the alert limit allow OK)`` of an updated epoch."""
    risk = result.risk
    consistency = result.consistency
    level = float(result.protection_level_m)
    limit = float(risk.alert_limits_m[0])
    bound = float(risk.risk_bound[0])
    motion_known = result.motion_unknown_s == 0.0
    settled = result.settling_s >= config.integrity_settling_s
    reasons = []
    if not motion_known:
        reasons.append(f'dead reckoning missing for {result.motion_unknown_s:.2f} s of this '
                       f'interval: motion unknown')
    if consistency.inconsistent:
        reasons.append(f'the cloud is inconsistent with the measurements (test statistic '
                       f'{consistency.statistic_nats:.1f} nats, snapshot solution '
                       f'{consistency.separation_m:.0f} m away)')
    if not settled:
        reasons.append('settling after the first fix or a lost heading (heading '
                       f'acquisition, then {config.integrity_settling_s:g} s)')
    if not level <= limit:
        reasons.append(f'protection level {level:.1f} m above the alert limit {limit:g} m')
    if not bound <= config.target_risk:
        reasons.append(f'risk bound {bound:.3g} > target {config.target_risk:g}')
    return reasons, motion_known and settled and not consistency.inconsistent


def integrity_verdict(result: EpochResult, config: FilterConfig,
                      reinitialising: str | None = None,
                      dead_reckoning_resets: int = 0) -> IntegrityVerdict:
    """The integrity verdict of an epoch result: the only place OK is decided.

    Args:
        result: The filter's result of the epoch (its findings).
        config: The filter parameters in force (alert limit, target, settling time).
        reinitialising: Why the filter waits for a fix to start again (None: it does
            not); part of a STALE verdict's reasons.
        dead_reckoning_resets: Restarts of the dead reckoning so far (a detail).

    Returns:
        STALE without a GNSS update; else OK when no reason speaks against it (module
        docstring), ERROR with the reasons otherwise.
    """
    if result.status != UPDATED or result.risk is None:
        reasons = (f'no valid solution ({result.status}): {result.reason}',)
        if reinitialising and result.status != INVALID:
            reasons += (reinitialising,)
        return stale_verdict(result.stamp_ns, reasons, config, result.stamp_ns,
                             result.status)
    risk = result.risk
    reasons, valid = _reasons_against(result, config)
    bound = float(risk.risk_bound[0])
    level = float(result.protection_level_m)
    limit = float(risk.alert_limits_m[0])
    details = {'n_satellites': result.n_satellites, 'kl_nats': float(risk.kl_nats),
               'epsilon': float(risk.epsilon), 'inverse_bernoulli': config.inverse_bernoulli,
               'motion_unknown_s': float(result.motion_unknown_s),
               'integrity_valid': bool(valid),
               'dead_reckoning_resets': int(dead_reckoning_resets)}
    if result.camera_alpha is not None:
        details['camera_images'] = len(result.camera_frame_ids)
        details['camera_excluded'] = bool(result.camera_excluded)
    if reasons:
        message = f'integrity insufficient: {reasons[0]}'
    else:
        message = (f'integrity sufficient: protection level {level:.1f} m <= alert limit '
                   f'{limit:g} m (risk bound {bound:.3g} <= {config.target_risk:g})')
    return IntegrityVerdict(
        stamp_ns=int(result.stamp_ns), level=ERROR if reasons else OK, message=message,
        alert_limit_m=limit, target_risk=float(config.target_risk), risk_bound=bound,
        empirical_risk=float(risk.empirical_risk[0]),
        divergence_risk=float(risk.divergence_risk[0]),
        epoch_stamp_ns=int(result.stamp_ns), protection_level_m=level,
        epoch_status=result.status,
        risk_bounds_by_limit={float(risk.alert_limits_m[a]): float(risk.risk_bound[a])
                              for a in range(1, len(risk.alert_limits_m))},
        reasons=tuple(reasons), valid=valid, details=details)
