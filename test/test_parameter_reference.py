"""One parameter surface: every node parameter is declared from its metadata
(``core.parameters``; ``nodes.parameters``, ``nodes.parameter_reference``), under one name,
and the rendered parameter reference lists every parameter a node declares."""
import pytest
from ros_harness import every_node_in_process  # skips this module without rclpy

from test_parameter_docs import table_rows

from gnsscam_ros.core.engine import InputTiming
from gnsscam_ros.nodes import parameter_reference
from gnsscam_ros.nodes.parameters import specs_of

pytestmark = pytest.mark.ros
#: Parameters rclpy declares on every node by itself.
_RCLPY_PARAMETERS = {'use_sim_time', 'start_type_description_service'}


@pytest.fixture(scope='module')
def nodes():
    with every_node_in_process() as by_name:
        yield by_name


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


def test_timing_parameters_are_input_timing_fields_under_their_own_names(nodes):
    fusion = nodes['fusion_node']
    for spec in InputTiming.parameter_specs():
        assert getattr(fusion.engine.timing, spec.name) == fusion.param(spec.name)
