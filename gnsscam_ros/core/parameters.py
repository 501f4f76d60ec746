"""Parameter metadata: each parameter's default, meaning, unit, range and provenance,
declared once as field metadata of a frozen dataclass (:func:`parameter`).

From it come the validation of the dataclass (``core.config``'s parts, ``core.engine.
InputTiming``), the ROS parameters of the nodes (descriptor, range, read-only), the
options of the command lines (``evaluation.cli``), the comments of ``config/*.yaml`` and
the markdown parameter reference (:func:`render_parameter_table`, between the markers
``<!-- parameters:begin -->`` and ``<!-- parameters:end -->`` of a document).
"""
from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field

#: Key of the field metadata that holds a parameter's description.
_META = 'gnsscam_parameter'
#: Name of the document section that holds the rendered parameter table.
PARAMETER_SECTION = 'parameters'


@dataclass(frozen=True)
class Range:
    """Admissible values of a numeric parameter; a bound of None is no bound.

    ROS parameter ranges are closed, so an open bound (``low_open``) is enforced by the
    configuration's own validation only.
    """

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False

    def contains(self, value) -> bool:
        """Whether ``value`` lies in the range (NaN never does)."""
        if self.low is not None and not (value > self.low if self.low_open
                                         else value >= self.low):
            return False
        return self.high is None or bool(value < self.high if self.high_open
                                         else value <= self.high)

    def closed(self, unbounded: float) -> tuple[float, float]:
        """``(low, high)`` with a missing bound replaced by ``-unbounded`` / ``unbounded``
        (the form of a ROS parameter range)."""
        return (-unbounded if self.low is None else self.low,
                unbounded if self.high is None else self.high)

    def __str__(self) -> str:
        low, high = _number(self.low), _number(self.high)
        if self.low is not None and self.high is not None:
            return (f'in {"(" if self.low_open else "["}{low}, {high}'
                    f'{")" if self.high_open else "]"}')
        if self.low is not None:
            return f'{">" if self.low_open else ">="} {low}'
        if self.high is not None:
            return f'{"<" if self.high_open else "<="} {high}'
        return 'any value'


def _number(value) -> str:
    return f'{value:g}' if isinstance(value, float) else str(value)


@dataclass(frozen=True)
class ParameterSpec:
    """One parameter as the node, the command line, the YAML file and the validation see it.

    Attributes:
        name: Flat parameter name (unique across the parts).
        default: Default value.
        doc: Meaning, without the unit.
        unit: Unit ('' for none), e.g. 'm^2/s'.
        range: Admissible numeric values (None: not numeric or unchecked).
        choices: Admissible string values (empty: any).
        part: Where it is declared: the attribute of ``FilterConfig`` holding its part, or
            the dataclass (``InputTiming``).
        node_parameter: Declared as a node parameter (False: evaluation only).
        read_only: A node refuses changes after start-up.
        provenance: Where the default comes from, when measured or chosen on data ('' when
            it is a design value).
    """

    name: str
    default: object
    doc: str
    unit: str = ''
    range: Range | None = None
    choices: tuple = ()
    part: str = ''
    node_parameter: bool = True
    read_only: bool = False
    provenance: str = ''

    @property
    def description(self) -> str:
        """Meaning, provenance and unit, one paragraph."""
        text = f'{self.doc} {self.provenance}' if self.provenance else self.doc
        return f'{text} Unit: {self.unit}.' if self.unit else text

    @property
    def constraint(self) -> str:
        """The admissible values in words ('' when any value of the type is)."""
        if self.choices:
            return 'one of ' + ', '.join(self.choices)
        return '' if self.range is None else str(self.range)

    def problem(self, value) -> str | None:
        """Why ``value`` is refused (None when it is admissible)."""
        if self.choices and value not in self.choices:
            return f'{self.name} must be one of {self.choices}'
        if self.range is not None and not self.range.contains(value):
            return f'{self.name} must be {self.range}'
        return None


def parameter(default, doc: str, unit: str = '', *, low=None, high=None,
              low_open: bool = False, high_open: bool = False, choices: tuple = (),
              node: bool = True, read_only: bool = False, provenance: str = ''):
    """A dataclass field with its parameter metadata.

    Args:
        default: Default value (immutable).
        doc: Meaning, without the unit; sentences ending with a full stop.
        unit: Unit ('' for none).
        low, high: Bounds of the admissible values (None: unbounded).
        low_open, high_open: The bound itself is excluded.
        choices: Admissible string values.
        node: Declared as a node parameter.
        read_only: A node refuses changes after start-up.
        provenance: Where the default comes from (data it was measured or chosen on).
    """
    value_range = (None if low is None and high is None
                   else Range(low, high, low_open, high_open))
    spec = ParameterSpec(name='', default=default, doc=doc, unit=unit, range=value_range,
                         choices=tuple(choices), node_parameter=node, read_only=read_only,
                         provenance=provenance)
    return field(default=default, metadata={_META: spec})


@functools.lru_cache(maxsize=None)
def field_specs(cls, part: str = '') -> tuple[ParameterSpec, ...]:
    """The :class:`ParameterSpec` of every field of the dataclass ``cls`` (named, with
    ``part``), in field order."""
    return tuple(dataclasses.replace(f.metadata[_META], name=f.name, part=part)
                 for f in dataclasses.fields(cls))


def problems(specs, values: dict) -> list[str]:
    """Why each value of ``{name: value}`` is refused by its spec (empty: all admissible)."""
    return [p for p in (s.problem(values[s.name]) for s in specs) if p]


def invalid(reasons: list[str], what: str = 'filter configuration') -> ValueError:
    """The error that refuses a configuration for ``reasons``."""
    return ValueError(f'invalid {what}: ' + '; '.join(reasons))


# -------------------------------------------------------------- the parameter reference
def _cell(text: str) -> str:
    return str(text).replace('|', '\\|').replace('\n', ' ')


def _default_text(value) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, str):
        return f"'{value}'"
    if isinstance(value, float):
        return repr(value)              # 10.0, not 10: the type shows
    if isinstance(value, tuple):
        return '[' + ', '.join(_default_text(v) for v in value) + ']'
    return str(value)


def render_parameter_table(groups) -> str:
    """The markdown parameter reference of ``groups`` (``(title, specs)`` pairs): per
    parameter its name, default, unit, admissible values, meaning and provenance, wrapped
    in the markers of :data:`PARAMETER_SECTION` so that a document can embed it
    (``io.marked``).

    Args:
        groups: ``(title, iterable of ParameterSpec)``; the title names where the
            parameters are declared, e.g. ``'fusion_node: FilterConfig.gnss'``.

    Returns:
        The table with its begin and end marker lines.
    """
    rows = [f'<!-- {PARAMETER_SECTION}:begin -->',
            '| parameter | default | unit | admissible | meaning | provenance | declared in |',
            '|---|---|---|---|---|---|---|']
    for title, specs in groups:
        for spec in specs:
            flags = ' (read-only)' if spec.read_only else ''
            rows.append(f'| `{spec.name}` | `{_cell(_default_text(spec.default))}` | '
                        f'{_cell(spec.unit)} | {_cell(spec.constraint)} | '
                        f'{_cell(spec.doc)}{flags} | {_cell(spec.provenance)} | '
                        f'{_cell(title)} |')
    rows.append(f'<!-- {PARAMETER_SECTION}:end -->')
    return '\n'.join(rows) + '\n'
