"""One parameter surface: every node parameter is declared from its metadata
(``core.parameters``; ``nodes.parameters``, ``nodes.parameter_reference``), under one name,
and the rendered parameter reference lists every parameter a node declares."""
import pytest
from ros_harness import ros_domain_id  # skips this module without rclpy

import rclpy
from rclpy.context import Context

from gnsscam_ros.core.engine import InputTiming
from gnsscam_ros.core.parameters import PARAMETER_SECTION
from gnsscam_ros.io.marked import marked_section
from gnsscam_ros.nodes import parameter_reference
from gnsscam_ros.nodes.camera_node import CameraNode
from gnsscam_ros.nodes.fusion_node import FusionNode
from gnsscam_ros.nodes.gnss_node import GnssNode
from gnsscam_ros.nodes.imu_node import ImuNode
from gnsscam_ros.nodes.parameters import specs_of

pytestmark = pytest.mark.ros
#: Parameters rclpy declares on every node by itself.
_RCLPY_PARAMETERS = {'use_sim_time', 'start_type_description_service'}


def table_rows() -> dict[tuple[str, str], list[str]]:
    """``{(node, parameter): cells}`` of the rendered reference."""
    text = parameter_reference.render_parameter_reference()
    body = marked_section(text, PARAMETER_SECTION).splitlines()
    rows = {}
    for line in body[2:]:
        cells = [c.strip() for c in line.strip('|').split(' | ')]
        node = cells[-1].split(':', 1)[0]
        key = (node, cells[0].strip('`'))
        assert key not in rows, f'{key} twice in the reference'
        rows[key] = cells
    return rows


@pytest.fixture(scope='module')
def nodes():
    ctx = Context()
    rclpy.init(context=ctx, domain_id=ros_domain_id())
    made = []
    try:
        made = [cls(context=ctx) for cls in (GnssNode, CameraNode, ImuNode, FusionNode)]
        yield {node.get_name(): node for node in made}
    finally:
        for node in made:
            node.destroy_node()
        rclpy.shutdown(context=ctx)


@pytest.mark.parametrize('name', sorted(parameter_reference.NODE_PARAMETERS))
def test_the_reference_lists_every_parameter_a_node_declares(nodes, name):
    node = nodes[name]
    declared = set(node._parameters) - _RCLPY_PARAMETERS
    listed = {param for node_name, param in table_rows() if node_name == name}
    assert declared == listed
    for spec in specs_of(parameter_reference.NODE_PARAMETERS[name]):
        # Declared with the metadata's default (no restated default) and read-only flag.
        value = node.param(spec.name)
        assert value == (list(spec.default) if isinstance(spec.default, tuple)
                         else spec.default), spec.name
        descriptor = node.describe_parameter(spec.name)
        assert descriptor.read_only == spec.read_only, spec.name
        assert spec.doc.split('.')[0] in descriptor.description, spec.name


def test_the_reference_shows_units_ranges_and_provenance():
    rows = table_rows()
    name, default, unit, admissible, meaning, provenance, where = rows[
        ('fusion_node', 'error_correlation_time_s')]
    assert (default, unit, admissible) == ('`10.0`', 's', '>= 0')
    assert 'smartLoc' in provenance and 'Correlation time' in meaning
    assert where == 'fusion_node: FilterConfig.gnss'
    assert rows[('fusion_node', 'odometry_wait_s')][3] == 'in [0, 10]'
    assert rows[('fusion_node', 'odometry_wait_s')][-1] == 'fusion_node: InputTiming'
    assert rows[('imu_node', 'yaw_rate_source')][3] == 'one of odometry, imu'


def test_timing_parameters_are_input_timing_fields_under_their_own_names(nodes):
    fusion = nodes['fusion_node']
    for spec in InputTiming.parameter_specs():
        assert getattr(fusion.engine.timing, spec.name) == fusion.param(spec.name)


def test_the_command_rewrites_the_marked_section(tmp_path):
    doc = tmp_path / 'params.md'
    doc.write_text('# Parameters\n<!-- parameters:begin -->\n<!-- parameters:end -->\n')
    assert parameter_reference.main([str(doc)]) == 0
    assert doc.read_text() == '# Parameters\n' + parameter_reference.render_parameter_reference()
    assert parameter_reference.main([str(tmp_path / 'missing.md')]) == 4
    (tmp_path / 'plain.md').write_text('no markers\n')
    assert parameter_reference.main([str(tmp_path / 'plain.md')]) == 2
