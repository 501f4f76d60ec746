"""Every endpoint a node creates is its registry topic (``msg_adapters.wire.TOPICS``): the
name, message type, reliability, durability and depth, and the node is named there as its
producer or consumer; the recorder subscribes with the registry's latching and depths."""
import pytest
from ros_harness import every_node_in_process, ros_domain_id  # skips without rclpy

import rclpy
from rclpy.context import Context
from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

from gnsscam_ros.live.record import DEFAULT_TOPICS, BagRecorder
from msg_adapters import wire
from msg_adapters.message_classes import message_class

pytestmark = pytest.mark.ros
#: Endpoints of rclpy itself, not of the gnsscam_ros graph.
_RCLPY_TOPICS = {'rosout', 'parameter_events'}
#: Node parameters that set an endpoint's depth: (node, topic) -> parameter.
_DEPTH_PARAMETERS = {('gnss_node', wire.GNSS): 'input_queue_depth',
                     ('camera_node', wire.IMAGE): 'input_queue_depth',
                     ('imu_node', wire.IMU): 'input_queue_depth',
                     ('imu_node', wire.TWIST): 'input_queue_depth',
                     ('imu_node', wire.DEAD_RECKONING): 'output_queue_depth',
                     ('fusion_node', wire.GNSS_MEASUREMENTS): 'input_queue_depth',
                     ('fusion_node', wire.MATCHES): 'input_queue_depth',
                     ('fusion_node', wire.DEAD_RECKONING): 'odometry_queue_depth'}


@pytest.fixture(scope='module')
def nodes():
    with every_node_in_process() as by_name:
        yield by_name


def _relative(node, topic_name: str) -> str:
    prefix = node.get_namespace().rstrip('/') + '/'
    return topic_name[len(prefix):] if topic_name.startswith(prefix) else topic_name


def _check(node, endpoint, topic: wire.Topic) -> None:
    qos = endpoint.qos_profile
    assert endpoint.msg_type is message_class(topic.msgtype), topic.name
    assert qos.reliability == {wire.RELIABLE: ReliabilityPolicy.RELIABLE,
                               wire.BEST_EFFORT: ReliabilityPolicy.BEST_EFFORT}[
                                   topic.reliability], topic.name
    assert (qos.durability == DurabilityPolicy.TRANSIENT_LOCAL) == topic.latched, topic.name
    parameter = _DEPTH_PARAMETERS.get((node.get_name(), topic.name))
    # A depth parameter's default is the registry's depth, except where a node's queue
    # must be deeper than the topic's (fusion_node's dead reckoning: a whole epoch).
    expected = topic.depth if parameter is None else node.param(parameter)
    assert qos.depth == expected, (node.get_name(), topic.name)


@pytest.mark.parametrize('name', ['gnss_node', 'camera_node', 'imu_node', 'fusion_node'])
def test_every_endpoint_of_a_node_is_its_registry_topic(nodes, name):
    node = nodes[name]
    published, subscribed = wire.topics_of(name)
    pubs = {_relative(node, p.topic_name): p for p in node.publishers}
    subs = {_relative(node, s.topic_name): s for s in node.subscriptions}
    assert set(pubs) - _RCLPY_TOPICS == {t.name for t in published}
    assert set(subs) - _RCLPY_TOPICS == {t.name for t in subscribed}
    for topic in published:
        _check(node, pubs[topic.name], topic)
    for topic in subscribed:
        _check(node, subs[topic.name], topic)


def test_depth_parameters_default_to_the_registry(nodes):
    for (name, topic), parameter in _DEPTH_PARAMETERS.items():
        if (name, topic) != ('fusion_node', wire.DEAD_RECKONING):
            assert nodes[name].param(parameter) == wire.TOPICS[topic].depth, (name, topic)


def test_the_recorder_takes_types_latching_and_depths_from_the_registry(tmp_path):
    ctx = Context()
    rclpy.init(context=ctx, domain_id=ros_domain_id())
    recorder = None
    try:
        recorder = BagRecorder(tmp_path / 'bag', context=ctx)
        subs = {_relative(recorder, s.topic_name): s for s in recorder.subscriptions}
        assert set(subs) - _RCLPY_TOPICS == set(DEFAULT_TOPICS)
        for name, sub in subs.items():
            if name in _RCLPY_TOPICS:
                continue
            topic = wire.TOPICS[name]
            assert DEFAULT_TOPICS[name] == (topic.msgtype, topic.latched)
            assert sub.qos_profile.depth == topic.record_depth, name
            assert ((sub.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL)
                    == topic.latched), name
    finally:
        if recorder is not None:
            recorder.abort()
            recorder.destroy_node()
        rclpy.shutdown(context=ctx)
