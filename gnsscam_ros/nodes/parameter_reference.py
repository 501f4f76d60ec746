"""The parameter reference of every node, as a markdown table generated from the
parameter metadata (``core.parameters``), and fusion_node's parameter groups.

:func:`render_parameter_reference` renders the table with its markers
``<!-- parameters:begin -->`` and ``<!-- parameters:end -->``, so that a document embeds
it; ``python -m gnsscam_ros.nodes.parameter_reference FILE ...`` rewrites that section of
each file (atomically). Exit codes: 0 written or current, 2 no file given or the markers
missing, 4 a file that cannot be read or written.
"""
from __future__ import annotations

import sys

from gnsscam_ros.core.config import FilterConfig
from gnsscam_ros.core.engine import InputTiming
from gnsscam_ros.core.parameters import PARAMETER_SECTION, render_parameter_table
from gnsscam_ros.io.marked import rewrite_marked

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


def main(argv: list[str] | None = None) -> int:
    """Rewrite the parameter table of each file given; the exit code (module docstring)."""
    paths = sys.argv[1:] if argv is None else argv
    if not paths:
        print('usage: python -m gnsscam_ros.nodes.parameter_reference FILE ...',
              file=sys.stderr)
        return 2
    body = '\n'.join(render_parameter_reference().splitlines()[1:-1])
    for name in paths:
        try:
            changed = rewrite_marked(name, PARAMETER_SECTION, body)
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
