"""Targets, verdicts and tables shared by the campaigns."""
from __future__ import annotations

import math
from dataclasses import dataclass

from gnsscam_ros.io.tables import format_table


@dataclass(frozen=True)
class Target:
    """One target of the issue and what the run measured for it.

    Attributes:
        name: Short name (``crashes == 0``).
        passed: Whether the measured value meets it.
        measured: The figure, as printed.
    """

    name: str
    passed: bool
    measured: str

    def as_dict(self) -> dict:
        return {'name': self.name, 'passed': self.passed, 'measured': self.measured}


def at_most(name: str, value, limit) -> Target:
    ok = value is not None and not (isinstance(value, float) and math.isnan(value)) \
        and value <= limit
    return Target(name, bool(ok), fmt(value))


def at_least(name: str, value, limit) -> Target:
    ok = value is not None and not (isinstance(value, float) and math.isnan(value)) \
        and value >= limit
    return Target(name, bool(ok), fmt(value))


def fmt(value) -> str:
    if value is None:
        return '-'
    if isinstance(value, float):
        if math.isnan(value):
            return 'nan'
        if math.isinf(value):
            return 'inf' if value > 0 else '-inf'
        return f'{value:.3g}' if abs(value) < 1e4 else f'{value:.0f}'
    return str(value)


def verdict_line(campaign: str, targets: list[Target]) -> str:
    """One line: PASS only when every target passes; each target with its figure."""
    failed = [t for t in targets if not t.passed]
    parts = '; '.join(f"{t.name}: {'PASS' if t.passed else 'FAIL'} ({t.measured})"
                      for t in targets)
    head = 'PASS' if not failed else f'FAIL ({len(failed)} of {len(targets)} targets)'
    return f'verdict {campaign}: {head} -- {parts}'


def table(headers: list[str], rows: list[list]) -> str:
    """A plain-text table; floats with three significant digits."""
    return format_table(headers, [[fmt(c) if isinstance(c, float) else c for c in row]
                                  for row in rows])


def targets_table(targets: list[Target]) -> str:
    return table(['target', 'measured', 'result'],
                 [[t.name, t.measured, 'PASS' if t.passed else 'FAIL'] for t in targets])
