"""Command-line options of the filter parameters, derived from their metadata.

Every ``FilterConfig`` parameter is an option named after it (``n_particles`` is
``--n-particles``), with its default, meaning, unit and admissible values from
``core.parameters``: the node parameters, the YAML files and the command lines use one
name each. The alert limits are one option, ``--alert-limits M [M ...]``: the first is
``alert_limit_m`` (the OK/ERROR flag), the others ``extra_alert_limits_m``. Old spellings
that documented commands use (``--particles``, ``--posteriors``,
``--correlation-time-s``) are still accepted, hidden from ``--help``.
"""
from __future__ import annotations

import argparse

from ..core.config import FilterConfig
from ..core.parameters import ParameterSpec

#: Alert limits the evaluation reports by default [m]: the flag's and a wider one.
DEFAULT_ALERT_LIMITS_M = (8.0, 16.0)
#: Parameters set through ``--alert-limits`` (not an option each).
ALERT_LIMIT_PARAMETERS = ('alert_limit_m', 'extra_alert_limits_m')
#: Earlier spellings of the options, accepted and hidden (README commands use them).
HIDDEN_ALIASES = {'n_particles': ('--particles',), 'n_posteriors': ('--posteriors',),
                  'error_correlation_time_s': ('--correlation-time-s',)}


def option_name(name: str) -> str:
    """The command-line option of the parameter ``name``: ``--n-particles``."""
    return '--' + name.replace('_', '-')


def filter_option_specs() -> tuple[ParameterSpec, ...]:
    """The parameters that are an option each (all but the alert limits)."""
    return tuple(s for s in FilterConfig.parameter_specs()
                 if s.name not in ALERT_LIMIT_PARAMETERS)


def _kind(spec: ParameterSpec) -> dict:
    """argparse keywords of the parameter's type."""
    if isinstance(spec.default, bool):
        return {'action': argparse.BooleanOptionalAction}
    if spec.choices:
        return {'choices': spec.choices}
    return {'type': type(spec.default), 'metavar': 'N' if isinstance(spec.default, int)
            else 'X'}


def _help(spec: ParameterSpec) -> str:
    unit = f' [{spec.unit}]' if spec.unit else ''
    admissible = f'{spec.constraint}; ' if spec.constraint and not spec.choices else ''
    # argparse formats help with %: the metadata's own text is escaped.
    return f'{spec.doc}{unit} ({admissible}'.replace('%', '%%') + 'default %(default)s)'


def add_filter_arguments(parser: argparse.ArgumentParser, seed_default: int) -> None:
    """The filter parameters as options, one group per ``FilterConfig`` part, plus
    ``--alert-limits`` and ``--seed`` (the filter's random seed)."""
    groups: dict[str, argparse._ArgumentGroup] = {}
    for spec in filter_option_specs():
        group = groups.get(spec.part)
        if group is None:
            group = groups[spec.part] = parser.add_argument_group(
                f'filter: FilterConfig.{spec.part}')
        kind = _kind(spec)
        group.add_argument(option_name(spec.name), dest=spec.name, default=spec.default,
                           help=_help(spec), **kind)
        for alias in HIDDEN_ALIASES.get(spec.name, ()):
            group.add_argument(alias, dest=spec.name, default=argparse.SUPPRESS,
                               help=argparse.SUPPRESS, **kind)
    integrity = groups['integrity']
    integrity.add_argument('--alert-limits', type=float, nargs='+', metavar='M',
                           default=list(DEFAULT_ALERT_LIMITS_M),
                           help='alert limits evaluated [m]: the first is alert_limit_m, '
                                'which sets the OK/ERROR flag and the figures, the others '
                                'extra_alert_limits_m (default: %(default)s)')
    integrity.add_argument('--seed', type=int, default=seed_default,
                           help='random seed of the filter (default %(default)s, as the '
                                'demo)')


def add_n_particles(group, default: int | None, what: str) -> None:
    """``--n-particles`` alone (commands that set no other filter parameter), with its
    hidden earlier spelling; ``what`` ends the help (the default's meaning)."""
    group.add_argument(option_name('n_particles'), dest='n_particles', type=int,
                       default=default, metavar='N',
                       help=f'particles per posterior N (FilterConfig.n_particles; {what})')
    for alias in HIDDEN_ALIASES['n_particles']:
        group.add_argument(alias, dest='n_particles', type=int, default=argparse.SUPPRESS,
                           help=argparse.SUPPRESS)


def config_from_args(args: argparse.Namespace) -> FilterConfig:
    """FilterConfig of the options (``--alert-limits``: the first is the filter's alert
    limit, the others are evaluated beside it).

    Raises:
        ValueError: An alert limit that is not a positive number of metres, or a value
            FilterConfig refuses (the message names it).
    """
    bad = [a for a in args.alert_limits if not 0.0 < a < float('inf')]
    if bad:
        raise ValueError(f'--alert-limits: {bad[0]:g} is not a positive number of metres')
    return FilterConfig(**{s.name: getattr(args, s.name) for s in filter_option_specs()},
                        alert_limit_m=args.alert_limits[0],
                        extra_alert_limits_m=tuple(args.alert_limits[1:]))
