"""The parameter reference of every node, generated from the parameter metadata
(``core.parameters``): the markdown table, the ``config/<node>.yaml`` files, and
fusion_node's parameter groups.

:func:`render_parameter_reference` renders the table with its markers
``<!-- parameters:begin -->`` and ``<!-- parameters:end -->``, so that a document embeds
it; :func:`render_node_yaml` renders a node's ``config/<node>.yaml`` below its hand-written
header (each key with a comment: meaning, unit, default, admissible values).
``python -m gnsscam_ros.nodes.parameter_reference FILE ...`` rewrites the table of each
markdown file and the parameters of each ``config/<node>.yaml`` (atomically). Exit codes:
0 written or current, 2 no file given, the markers missing or a YAML file of no node, 4 a
file that cannot be read or written.
"""
from __future__ import annotations

import sys
from pathlib import Path

from gnsscam_ros.core.config import (YAML_END, FilterConfig, comment_lines,
                                     render_yaml_block, yaml_value)
from gnsscam_ros.core.engine import InputTiming
from gnsscam_ros.core.parameters import (PARAMETER_SECTION, ParameterSpec,
                                         render_parameter_table)
from gnsscam_ros.io.marked import rewrite_marked, rewrite_text

from .parameters import (CAMERA_NODE, EVERY_NODE, GNSS_NODE, IMU_NODE, FusionNodeSettings,
                         Groups, own)


def _filter_groups() -> Groups:
    parts: dict[str, list] = {}
    for spec in FilterConfig.parameter_specs():
        if spec.node_parameter:
            parts.setdefault(spec.part, []).append(spec)
    return [(f'FilterConfig.{part}', tuple(specs)) for part, specs in parts.items()]


#: fusion_node's parameters: the filter's (``FilterConfig``, all but the evaluation-only
#: ones), its own, the engine's waits and buffers (``InputTiming``), every node's.
FUSION_NODE: Groups = [*_filter_groups(), own(FusionNodeSettings),
                       ('InputTiming', InputTiming.parameter_specs()),
                       ('every node', EVERY_NODE)]
#: Every node's parameter groups.
NODE_PARAMETERS: dict[str, Groups] = {'gnss_node': GNSS_NODE, 'camera_node': CAMERA_NODE,
                                      'imu_node': IMU_NODE, 'fusion_node': FUSION_NODE}


def render_parameter_reference() -> str:
    """The markdown table of every node parameter (name, default, unit, admissible values,
    meaning, provenance, where declared), with its ``parameters`` markers."""
    return render_parameter_table(
        (f'{node}: {where}', specs) for node, groups in NODE_PARAMETERS.items()
        for where, specs in groups)


#: Where each group's metadata is declared (default: nodes/parameters.py).
_SOURCES = {'InputTiming': 'gnsscam_ros/core/engine.py',
            'DeadReckoningConfig': 'gnsscam_ros/core/motion.py',
            'every node': 'gnsscam_ros/nodes/parameters.py, EveryNode'}
#: The line of a node's YAML file after which its parameters are generated.
YAML_PARAMETERS = '  ros__parameters:\n'


def _yaml_entry(spec: ParameterSpec) -> list[str]:
    text = f'{spec.description} Default: {yaml_value(spec.default)}'
    extra = [spec.constraint] if spec.constraint else []
    extra += ['read-only at run time'] if spec.read_only else []
    text += ('; ' + ', '.join(extra) + '.') if extra else '.'
    return comment_lines(text, spec.constraint) + [f'    {spec.name}: '
                                                   f'{yaml_value(spec.default)}']


def render_node_yaml(node: str) -> str:
    """The parameters of ``config/<node>.yaml`` (everything after its
    ``ros__parameters:`` line): fusion_node's filter block (``core.config``) first, then
    per group a heading and per parameter its comment and default."""
    lines = []
    groups = NODE_PARAMETERS[node]
    if node == 'fusion_node':
        lines += render_yaml_block().rstrip('\n').split('\n') + ['', YAML_END]
        groups = [g for g in groups if not g[0].startswith('FilterConfig.')]
    command = f'python -m gnsscam_ros.nodes.parameter_reference config/{node}.yaml'
    lines += comment_lines('Generated from the parameter metadata: edit it where each group '
                           f'below says, then run {command}', command)
    for where, specs in groups:
        source = _SOURCES.get(where, 'gnsscam_ros/nodes/parameters.py')
        lines += [''] + comment_lines(f'-- {where} ({source})')
        for spec in specs:
            lines += _yaml_entry(spec)
    return '\n'.join(lines) + '\n'


def update_node_yaml(text: str, node: str) -> str:
    """``text`` (a node's YAML file) with its parameters rendered anew.

    Raises:
        ValueError: No ``ros__parameters:`` line under the node's name.
    """
    head = f'{node}:\n{YAML_PARAMETERS}'
    if head not in text:
        raise ValueError(f'no "{node}: ros__parameters:" block')
    return text[:text.index(head) + len(head)] + render_node_yaml(node)


def _rewrite(path: Path) -> bool:
    """Rewrite the generated part of one file; whether it changed."""
    if path.suffix != '.yaml':
        body = '\n'.join(render_parameter_reference().splitlines()[1:-1])
        return rewrite_marked(path, PARAMETER_SECTION, body)
    if path.stem not in NODE_PARAMETERS:
        raise ValueError(f'{path}: not the YAML file of a node ({", ".join(NODE_PARAMETERS)})')
    return rewrite_text(path, lambda old: update_node_yaml(old, path.stem))


def main(argv: list[str] | None = None) -> int:
    """Rewrite the parameter table of each file given; the exit code (module docstring)."""
    paths = sys.argv[1:] if argv is None else argv
    if not paths:
        print('usage: python -m gnsscam_ros.nodes.parameter_reference FILE ...',
              file=sys.stderr)
        return 2
    for name in paths:
        try:
            changed = _rewrite(Path(name))
        except ValueError as err:
            print(f'gnsscam_ros.nodes.parameter_reference: {err}', file=sys.stderr)
            return 2
        except OSError as err:
            print(f'gnsscam_ros.nodes.parameter_reference: cannot rewrite {name}: '
                  f'{err.strerror or err}', file=sys.stderr)
            return 4
        print(f'{name}: {"updated" if changed else "up to date"}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
