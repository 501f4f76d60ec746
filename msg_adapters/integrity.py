"""``integrity_risk`` and ``diagnostics`` (``diagnostic_msgs/DiagnosticArray``) <-> dataclasses.

``integrity_risk`` carries one status:

* level ``OK`` (0): integrity sufficient, the protection level is within the alert limit
  (so the risk bound at the alert limit is at most the target risk) and no input is missing;
  ``ERROR`` (2): insufficient (alarm); ``STALE`` (3): no valid solution (no GNSS for too
  long, an epoch without a GNSS update, or before the first fix). A consumer must treat
  anything but OK as "do not trust the position".
* values ``risk_bound``, ``empirical_risk``, ``divergence_risk``, ``alert_limit_m``,
  ``target_risk``, ``epoch_stamp`` (integer ns of the GNSS epoch), ``protection_level_m``
  (the smallest radius whose bound meets the target; ``inf`` when none does, ``nan`` when
  stale), ``status`` (the filter status of the epoch behind the verdict: ``updated``,
  ``propagated``, ``rejected``, ``waiting``; ``no_gnss`` when there is none),
  ``risk_bound_<L>m`` (the risk bound at a further alert limit of ``L`` m, ``L`` formatted
  with ``:g``), plus informational extras (``n_satellites``, ``motion_unknown_s``, ...).
  Floats are written with ``repr`` so they parse back exactly; unknown values are ``nan``.

The message is encoded from the core's verdict (``gnsscam_ros.core.verdict.
IntegrityVerdict``, the one the epoch engine decides) by :func:`integrity_risk_to_msg`, and
parsed back into :class:`IntegrityRisk` for consumers by :func:`parse_integrity_risk`.
``status`` and ``risk_bound_<L>m`` are typed fields of both (``epoch_status``,
``risk_bounds_by_limit``); this module alone knows their keys.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from gnsscam_ros.core import verdict as core_verdict

from .errors import MessageError
from .message_classes import RCLPY
from .stamps import ns_to_stamp, stamp_to_ns
from .wire import INTEGRITY

if TYPE_CHECKING:                  # ROS messages: looked up in RCLPY where built, so that
    # the bag tools and the evaluation import this package without ROS 2 installed.
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

OK, WARN, ERROR, STALE = 0, 1, 2, 3
LEVEL_NAMES = {OK: 'OK', WARN: 'WARN', ERROR: 'ERROR', STALE: 'STALE'}
#: The core verdict's levels -> DiagnosticStatus levels.
VERDICT_LEVELS = {core_verdict.OK: OK, core_verdict.ERROR: ERROR, core_verdict.STALE: STALE}
INTEGRITY_STATUS_NAME = 'gnsscam_ros: integrity risk'
_FLOAT_KEYS = ('risk_bound', 'empirical_risk', 'divergence_risk', 'alert_limit_m',
               'target_risk')
_STATUS_KEY = 'status'
_NO_GNSS = 'no_gnss'            # the wire's status of a verdict with no GNSS epoch behind it
_BOUND_KEY = re.compile(r'^risk_bound_(.+)m$')


def _bound_key(limit_m: float) -> str:
    return f'risk_bound_{float(limit_m):g}m'


def _typed_values(values: dict) -> tuple[str | None, dict[float, float], dict]:
    """``(epoch status, {alert limit: risk bound}, the other values)`` of wire values.

    Raises:
        ValueError: A ``risk_bound_<L>m`` whose limit or value is not a number.
    """
    status, bounds, rest = None, {}, {}
    for key, value in values.items():
        match = _BOUND_KEY.match(str(key))
        if key == _STATUS_KEY:
            status = None if value in (None, _NO_GNSS) else str(value)
        elif match:
            bounds[float(match.group(1))] = float(value)
        else:
            rest[key] = value
    return status, bounds, rest


def level_to_int(level) -> int:
    """A DiagnosticStatus level (``bytes`` of length 1 in rclpy, or int) -> int."""
    if isinstance(level, (bytes, bytearray)):
        if len(level) != 1:
            raise MessageError(f'diagnostic level {level!r} is not one byte', 'value')
        return level[0]
    return int(level)


def format_value(value) -> str:
    """A KeyValue value: floats with ``repr`` (exact round trip), others with ``str``."""
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, bool):
        return 'true' if value else 'false'
    return str(value)


def make_status(name: str, level: int, message: str, values: dict,
                hardware_id: str = '') -> DiagnosticStatus:
    """One DiagnosticStatus from a ``{key: value}`` dict (values formatted by
    :func:`format_value`)."""
    key_value = RCLPY['diagnostic_msgs/msg/KeyValue']
    return RCLPY['diagnostic_msgs/msg/DiagnosticStatus'](
        level=bytes([int(level)]), name=name, message=message, hardware_id=hardware_id,
        values=[key_value(key=str(k), value=format_value(v)) for k, v in values.items()])


def make_diagnostic_array(stamp_ns: int, statuses: list[DiagnosticStatus]) -> DiagnosticArray:
    """A DiagnosticArray of ``statuses`` stamped ``stamp_ns``."""
    return RCLPY['diagnostic_msgs/msg/DiagnosticArray'](
        header=RCLPY['std_msgs/msg/Header'](stamp=ns_to_stamp(stamp_ns)), status=statuses)


def status_values(status: DiagnosticStatus) -> dict[str, str]:
    """``{key: value}`` of a DiagnosticStatus."""
    return {kv.key: kv.value for kv in status.values}


@dataclass(frozen=True)
class IntegrityRisk:
    """The integrity verdict of one GNSS epoch (or a stale report), for consumers.

    Attributes:
        stamp_ns: Header stamp of the message [ns] (the epoch for an epoch result, the
            report time for a stale report).
        level: OK (0), ERROR (2) or STALE (3).
        message: Human-readable explanation.
        risk_bound: Upper bound on P(horizontal error > alert limit) (nan when stale).
        empirical_risk: R_M, mean mass of the M posteriors beyond the alert limit.
        divergence_risk: D_Ber^-1(R_M, eps), the PAC-Bayes slack.
        alert_limit_m: Alert limit [m].
        target_risk: Integrity is sufficient when ``risk_bound <= target_risk``.
        epoch_stamp_ns: Stamp of the GNSS epoch the values refer to [ns] (None before
            the first epoch).
        protection_level_m: Protection level [m], None when not computed.
        name: Status name.
        extra: Other values (strings when parsed), without the two below.
        epoch_status: Filter status of the GNSS epoch behind the verdict (``'updated'``,
            ``'propagated'``, ``'rejected'``, ``'waiting'``); None when there is none (a
            periodic report without GNSS; ``no_gnss`` on the wire, also when parsed from
            a message without a status).
        risk_bounds_by_limit: ``{alert limit [m]: risk bound}`` at further alert limits
            (the main limit is ``alert_limit_m``/``risk_bound``).

    A producer that still passes ``status`` or ``risk_bound_<L>m`` in ``extra`` gets them
    moved into the typed fields (which win when both are given).
    """

    stamp_ns: int
    level: int
    message: str
    risk_bound: float
    empirical_risk: float
    divergence_risk: float
    alert_limit_m: float
    target_risk: float
    epoch_stamp_ns: int | None = None
    protection_level_m: float | None = None
    name: str = INTEGRITY_STATUS_NAME
    extra: dict = field(default_factory=dict)
    epoch_status: str | None = None
    risk_bounds_by_limit: dict[float, float] = field(default_factory=dict)

    def __post_init__(self):
        if _STATUS_KEY not in self.extra and not any(
                _BOUND_KEY.match(str(k)) for k in self.extra):
            return
        status, bounds, rest = _typed_values(self.extra)
        # Frozen: the fields are set once, here, from what the producer gave.
        object.__setattr__(self, 'extra', rest)
        if self.epoch_status is None:
            object.__setattr__(self, 'epoch_status', status)
        object.__setattr__(self, 'risk_bounds_by_limit',
                           {**bounds, **self.risk_bounds_by_limit})

    @property
    def integrity_ok(self) -> bool:
        """True only for level OK: ERROR and STALE both mean "do not trust"."""
        return self.level == OK

    @property
    def stale(self) -> bool:
        return self.level == STALE

    @property
    def level_name(self) -> str:
        return LEVEL_NAMES.get(self.level, str(self.level))


def integrity_risk_to_msg(verdict: core_verdict.IntegrityVerdict) -> DiagnosticArray:
    """The core's integrity verdict -> the ``integrity_risk`` DiagnosticArray.

    Its details are written as further values after the typed ones.

    Raises:
        MessageError: A level other than OK, ERROR and STALE, or OK with a non-finite
            bound above the target or a protection level above the alert limit (an OK
            verdict must be backed by numbers).
    """
    level = VERDICT_LEVELS.get(verdict.level)
    if level is None:
        raise MessageError(f'integrity level {verdict.level!r} is not OK, ERROR or STALE',
                           'value')
    if level == OK and not (math.isfinite(verdict.risk_bound)
                            and verdict.risk_bound <= verdict.target_risk):
        raise MessageError(f'level OK needs a finite bound <= target, got '
                           f'{verdict.risk_bound}', 'value')
    if level == OK and not (math.isfinite(verdict.protection_level_m)
                            and verdict.protection_level_m <= verdict.alert_limit_m):
        raise MessageError(f'level OK needs a finite protection level <= the alert limit, '
                           f'got {verdict.protection_level_m}', 'value')
    values = {k: float(getattr(verdict, k)) for k in _FLOAT_KEYS}
    values['epoch_stamp'] = ('' if verdict.epoch_stamp_ns is None
                             else int(verdict.epoch_stamp_ns))
    values['protection_level_m'] = float(verdict.protection_level_m)
    values[_STATUS_KEY] = (_NO_GNSS if verdict.epoch_status is None
                           else str(verdict.epoch_status))
    for limit, bound in verdict.risk_bounds_by_limit.items():
        values[_bound_key(limit)] = float(bound)
    values.update(verdict.details)
    status = make_status(INTEGRITY_STATUS_NAME, level, verdict.message, values)
    return make_diagnostic_array(verdict.stamp_ns, [status])


def parse_integrity_risk(msg: DiagnosticArray, what: str = INTEGRITY
                         ) -> IntegrityRisk:
    """The ``integrity_risk`` DiagnosticArray -> :class:`IntegrityRisk`.

    The status is the first one carrying a ``risk_bound`` value.

    Raises:
        MessageError: No such status, a missing or unparsable value, or an unknown level.
    """
    for status in msg.status:
        values = status_values(status)
        if 'risk_bound' in values:
            break
    else:
        raise MessageError(f'{what}: no status with a risk_bound value', 'fields')
    level = level_to_int(status.level)
    if level not in (OK, ERROR, STALE):
        raise MessageError(f'{what}: level {level} is not OK, ERROR or STALE', 'value')
    try:
        floats = {k: float(values.pop(k)) for k in _FLOAT_KEYS}
        epoch = values.pop('epoch_stamp')
        epoch_ns = int(epoch) if epoch else None
        pl = values.pop('protection_level_m', None)
        pl = float(pl) if pl is not None else None
        epoch_status, bounds, values = _typed_values(values)
    except KeyError as err:
        raise MessageError(f'{what}: value {err.args[0]!r} missing', 'fields') from err
    except ValueError as err:
        raise MessageError(f'{what}: unparsable value ({err})', 'value') from err
    return IntegrityRisk(stamp_ns=stamp_to_ns(msg.header.stamp), level=level,
                         message=status.message, epoch_stamp_ns=epoch_ns,
                         protection_level_m=pl, name=status.name, extra=values,
                         epoch_status=epoch_status, risk_bounds_by_limit=bounds, **floats)
