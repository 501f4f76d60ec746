"""The nodes in-process (fresh context per test).

* config/*.yaml = code defaults, loaded through ``--params-file``;
* malformed messages are refused and counted while the nodes keep running;
* run-time parameter updates (alert limit, target risk) and refusals with a reason;
* STALE integrity without GNSS, never a stale OK; camera frame drops are counted.
"""
import math
from pathlib import Path

import numpy as np
import pytest
from ros_harness import RosGraph, ros_domain_id  # skips without rclpy
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped, TwistWithCovarianceStamped
from nav_msgs.msg import Odometry
from rclpy.context import Context
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image, Imu, NavSatFix, PointCloud2

import msg_adapters as ma
from gnsscam_ros.core.filter import PROPAGATED, UPDATED, FilterConfig
from gnsscam_ros.core.motion import DeadReckoningConfig, DeadReckoningState, dead_reckon
from gnsscam_ros.core.types import GnssEpoch
from gnsscam_ros.datasets.emulated.drive import make_emulated_drive
from gnsscam_ros.nodes import camera_node, fusion_node, gnss_node, imu_node
from gnsscam_ros.nodes.camera_node import CameraNode
from gnsscam_ros.nodes.node_base import InputFileError, ParameterError
from gnsscam_ros.nodes.fusion_node import FusionNode
from gnsscam_ros.nodes.gnss_node import GnssNode
from gnsscam_ros.nodes.imu_node import ImuNode
from gnsscam_ros.vision.database import MapDatabase, PositionTable
from gnsscam_ros.vision.features import OrbExtractor, OrbParams
from gnsscam_ros.vision.synthetic import synthetic_scene

# Every test here runs ROS nodes in a graph of its own.
pytestmark = pytest.mark.ros

CONFIG = Path(__file__).resolve().parents[1] / 'config'
NODE_MODULES = {'gnss_node': gnss_node, 'imu_node': imu_node, 'camera_node': camera_node,
                'fusion_node': fusion_node}
S = 1_000_000_000


def overrides(**values):
    return [Parameter(k, value=v) for k, v in values.items()]


def quantised(epoch: GnssEpoch) -> GnssEpoch:
    """The epoch as it travels: variance, C/N0 and elevation are FLOAT32 on the wire."""
    f32 = {k: np.float32(getattr(epoch, k)).astype(float)
           for k in ('var_m2', 'cn0_dbhz', 'elevation_deg')}
    return GnssEpoch(**{**epoch.__dict__, **f32})


def small_database(images, positions_m) -> MapDatabase:
    ext = OrbExtractor(OrbParams(nfeatures=500))
    return MapDatabase.build(
        [ext.descriptors(im) for im in images], [f'im{i}.png' for i in range(len(images))],
        PositionTable.from_columns(('east_m', 'north_m', 'up_m'), np.asarray(positions_m)),
        orb_params=OrbParams(nfeatures=500), branching=8, depth=3, iterations=4, seed=0)


@pytest.fixture(scope='module')
def drive():
    d = make_emulated_drive(21, faults=3, bias_m=80.0, duration_s=12.0)
    d.gnss = [quantised(e) for e in d.gnss]
    return d


# ============================================================================ config
@pytest.mark.parametrize('name', sorted(NODE_MODULES))
def test_config_file_documents_code_defaults(name):
    text = (CONFIG / f'{name}.yaml').read_text()
    params = yaml.safe_load(text)[name]['ros__parameters']
    defaults = NODE_MODULES[name].DEFAULTS
    assert list(params) == list(defaults)
    for key, value in defaults.items():
        assert params[key] == value and type(params[key]) is type(value), key
        # Every key carries a comment with its default just above it.
        lines = text.splitlines()
        k = lines.index(f'    {key}: {lines_value(lines, key)}')
        comment = []
        while lines[k - 1].startswith('    #'):
            k -= 1
            comment.insert(0, lines[k][5:].strip())
        assert 'Default:' in ' '.join(comment), key


def lines_value(lines, key):
    return next(ln.split(': ', 1)[1] for ln in lines if ln.startswith(f'    {key}: '))


def test_fusion_parameters_are_filter_config_defaults():
    cfg = FilterConfig()
    for name in fusion_node.FILTER_PARAMETERS:
        assert fusion_node.DEFAULTS[name] == getattr(cfg, name), name
    assert set(fusion_node.FILTER_PARAMETERS) | set(fusion_node.NOT_PARAMETERS) == set(
        cfg.as_flat())


def test_params_files_load_through_ros_args(tmp_path):
    override = tmp_path / 'override.yaml'
    override.write_text('fusion_node:\n  ros__parameters:\n    alert_limit_m: 16.0\n'
                        '    n_particles: 300\n')
    args = ['--ros-args'] + [a for n in NODE_MODULES
                             for a in ('--params-file', str(CONFIG / f'{n}.yaml'))]
    args += ['--params-file', str(override)]
    ctx = Context()
    rclpy.init(context=ctx, domain_id=ros_domain_id(), args=args)
    nodes = []
    try:
        nodes = [GnssNode(context=ctx), ImuNode(context=ctx), CameraNode(context=ctx),
                 FusionNode(context=ctx)]
        fusion = nodes[-1]
        assert fusion.engine.config.alert_limit_m == 16.0
        assert fusion.engine.config.n_particles == 300
        assert fusion.engine.config.target_risk == FilterConfig().target_risk
        assert nodes[1].dead_reckoner.config == DeadReckoningConfig()
    finally:
        for node in nodes:
            node.destroy_node()
        rclpy.shutdown(context=ctx)


def test_node_spinner_serves_each_node_and_stops_the_group_when_one_fails():
    from gnsscam_ros.nodes.runtime import NodeSpinner
    ctx = Context()
    rclpy.init(context=ctx, domain_id=ros_domain_id())
    ticks = {'a': 0, 'b': 0}
    a = rclpy.create_node('spin_a', context=ctx)
    b = rclpy.create_node('spin_b', context=ctx)

    def tick_a():
        ticks['a'] += 1

    def tick_b():
        ticks['b'] += 1
        if ticks['b'] == 5:
            raise RuntimeError('node b failed')

    a.create_timer(0.01, tick_a)
    b.create_timer(0.01, tick_b)
    spinner = NodeSpinner([a, b], ctx)
    try:
        spinner.wait()                      # returns once b's callback raised
        assert ticks['b'] == 5 and ticks['a'] > 0
        assert not ctx.ok()                 # the failure shut the group down
    finally:
        spinner.stop()
        a.destroy_node()
        b.destroy_node()
        rclpy.try_shutdown(context=ctx)


@pytest.mark.slow
def test_diagnostics_report_matched_links_for_the_replay(graph):
    g = graph
    imu = g.add(ImuNode(context=g.ctx))
    fusion = g.add(FusionNode(context=g.ctx))
    reports = g.collect(DiagnosticArray, 'diagnostics')
    # Before anything is connected the counts exist and say so.
    assert imu.link_counts()['publishers_imu/data'] == 0
    g.spin_until(lambda: imu.link_counts()['subscribers_odometry/dead_reckoning'] >= 1
                 and fusion.link_counts()['publishers_odometry/dead_reckoning'] >= 1,
                 what='imu_node -> fusion_node matched')
    links = fusion.link_counts()
    assert {'publishers_gnss/measurements', 'publishers_camera/matches',
            'subscribers_integrity_risk', 'subscribers_pose'} <= set(links)
    assert not any('rosout' in k or 'parameter_events' in k or k.endswith('diagnostics')
                   for k in links)

    def reported():
        for msg in reports:
            for st in msg.status:
                values = ma.status_values(st)
                if (st.name == 'fusion_node: status'
                        and int(values.get('publishers_odometry/dead_reckoning', 0)) >= 1):
                    return True
        return False

    g.spin_until(reported, 5.0, 'the link counts in fusion_node diagnostics')


# ================================================================ malformed messages
def _bad_cloud(epoch):
    msg = ma.gnss_epoch_to_pointcloud2(epoch)
    msg.fields[4].datatype = 8                       # variance as FLOAT64: wrong type
    return msg


@pytest.mark.slow
def test_malformed_messages_are_refused_and_counted(graph, drive):
    g = graph
    images = [synthetic_scene(i, seed=9) for i in range(3)]
    db = small_database(images, [[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [20.0, 0.0, 0.0]])
    gnss = g.add(GnssNode(context=g.ctx))
    imu = g.add(ImuNode(context=g.ctx))
    cam = g.add(CameraNode(context=g.ctx, database=db))
    fusion = g.add(FusionNode(context=g.ctx, parameter_overrides=overrides(
        n_particles=100, odometry_wait_s=0.0)))
    pub_gnss = g.publisher(PointCloud2, 'gnss/pseudoranges')
    pub_imu = g.publisher(Imu, 'imu/data')
    pub_odo = g.publisher(TwistWithCovarianceStamped, 'odom/twist')
    pub_cam = g.publisher(Image, 'camera/image_raw')
    pub_dr = g.publisher(Odometry, 'odometry/dead_reckoning')
    pub_matches = g.publisher(PointCloud2, 'camera/matches')
    diagnostics = g.collect(DiagnosticArray, 'diagnostics')
    g.connect(pub_gnss, pub_imu, pub_odo, pub_cam, pub_dr, pub_matches)
    e0, e1 = drive.gnss[0], drive.gnss[1]

    def send(pub, msg, node, key):
        n = node.stats.get(key)
        pub.publish(msg)
        g.spin_until(lambda: node.stats.get(key) > n, what=key)

    # GNSS: wrong field type, wrong frame, NaN satellite, out-of-order stamp.
    send(pub_gnss, _bad_cloud(e1), gnss, 'received_pseudoranges')
    wrong_frame = ma.gnss_epoch_to_pointcloud2(e1, frame_id='map')
    send(pub_gnss, wrong_frame, gnss, 'received_pseudoranges')
    pr = e1.pr_m.copy()
    pr[0] = np.nan
    send(pub_gnss, ma.gnss_epoch_to_pointcloud2(GnssEpoch(**{**e1.__dict__, 'pr_m': pr})),
         gnss, 'received_pseudoranges')
    send(pub_gnss, ma.gnss_epoch_to_pointcloud2(e0), gnss, 'received_pseudoranges')
    assert gnss.stats.rejected == {'fields': 1, 'frame': 1, 'out_of_order': 1}
    assert gnss.stats.get('satellites_rejected_non_finite') == 1
    g.spin_until(lambda: fusion.last_result is not None, what='the NaN epoch reaching fusion')
    assert fusion.last_result.n_satellites in (0, e1.n_sv - 1)

    # IMU and odometry: NaN, out of order; then a good sample is still used.
    bad_imu = ma.sample_to_imu(ma.ImuSample(e1.stamp_ns, np.array([np.nan, 0, 9.8]),
                                            np.zeros(3)))
    send(pub_imu, bad_imu, imu, 'received_imu')
    send(pub_imu, ma.sample_to_imu(ma.ImuSample(e1.stamp_ns, np.zeros(3), np.zeros(3))), imu,
         'received_imu')
    send(pub_imu, ma.sample_to_imu(ma.ImuSample(e0.stamp_ns, np.zeros(3), np.zeros(3))), imu,
         'received_imu')
    send(pub_odo, ma.sample_to_twist(ma.TwistSample(e1.stamp_ns, math.inf, 0.0)), imu,
         'received_odom_twist')
    assert imu.stats.rejected == {'non_finite': 2, 'out_of_order': 1}
    assert imu.stats.get('published_dead_reckoning') == 1

    # Camera: empty image, wrong encoding, wrong size, out-of-order stamp; good frames match.
    # A refused frame is answered with an empty camera/matches (its stamp); only the
    # out-of-order one gets no answer (camera/matches stays in stamp order).
    good = ma.array_to_image(images[1], e1.stamp_ns)
    empty = Image(height=0, width=0, encoding='bgr8', step=0)
    empty.header.stamp = ma.ns_to_stamp(e1.stamp_ns + 1)
    wrong_enc = ma.array_to_image(images[1], e1.stamp_ns + 2)
    wrong_enc.encoding = '32FC1'
    short = ma.array_to_image(images[1], e1.stamp_ns + 3)
    short.data = bytes(short.data)[:-10]
    older = ma.array_to_image(images[2], e0.stamp_ns)
    good_again = ma.array_to_image(images[1], e1.stamp_ns + 4)
    answers = g.collect(PointCloud2, 'camera/matches')
    g.spin_until(lambda: cam.pub.get_subscription_count() >= 2, what='the answers collector')
    for msg in (good, empty, wrong_enc, short, older, good_again):
        send(pub_cam, msg, cam, 'received_images')
        g.spin_until(lambda: cam.stats.get('published_matches')
                     + cam.stats.rejected.get('out_of_order', 0)
                     + cam.stats.get('dropped_frames') >= cam.stats.get('received_images'),
                     what='the matcher')
    assert cam.stats.rejected == {'empty': 1, 'encoding': 1, 'size': 1, 'out_of_order': 1}
    assert cam.stats.get('published_matches') == 5
    assert cam.stats.get('frames_without_match') == 3
    g.spin_until(lambda: len(answers) == 5, what='the answers')
    assert [ma.stamp_to_ns(m.header.stamp) - e1.stamp_ns for m in answers] == [0, 1, 2, 3, 4]
    widths = [m.width for m in answers]
    assert widths[1:4] == [0, 0, 0] and widths[0] > 0 and widths[4] > 0, widths

    # fusion: malformed internal streams.
    bad_dr = ma.dead_reckoning_to_odometry(DeadReckoningState(e1.stamp_ns + 5, 0, 0, 0, 0, 0,
                                                              0, 0, 0, 0))
    bad_dr.pose.pose.orientation.w = math.nan
    send(pub_dr, bad_dr, fusion, 'received_dead_reckoning')
    bad_matches = ma.gnss_epoch_to_pointcloud2(e1, frame_id='map')   # not a match cloud
    pub_matches.publish(bad_matches)   # camera_node publishes here too: wait for the refusal
    g.spin_until(lambda: fusion.stats.rejected.get('fields') == 1, what='the refusal')
    assert fusion.stats.rejected.get('non_finite') == 1

    # Everyone is still running and reports the refusals on diagnostics.
    send(pub_gnss, ma.gnss_epoch_to_pointcloud2(drive.gnss[2]), gnss,
         'received_pseudoranges')
    assert gnss.stats.get('published_measurements') == 2     # the NaN epoch and this one
    for node in (gnss, imu, cam, fusion):
        node.publish_diagnostics()
    g.spin_until(lambda: {s.name for m in diagnostics for s in m.status} >= {
        f'{n}: status' for n in ('gnss_node', 'imu_node', 'camera_node', 'fusion_node')},
        what='diagnostics')
    latest = {s.name: ma.status_values(s) for m in diagnostics for s in m.status}
    assert latest['gnss_node: status']['rejected_total'] == '3'
    assert latest['camera_node: status']['rejected_out_of_order'] == '1'
    assert 'processing_p50_ms' in latest['imu_node: status']


# ====================================================================== parameters
@pytest.mark.slow
def test_parameters_update_at_run_time_or_are_refused_with_a_reason(graph, drive):
    g = graph
    fusion = g.add(FusionNode(context=g.ctx, parameter_overrides=overrides(n_particles=100)))
    risks = g.collect(DiagnosticArray, 'integrity_risk')
    pub = g.publisher(PointCloud2, 'gnss/measurements')
    g.connect(pub)

    def epoch(k):
        n = len(risks)
        pub.publish(ma.gnss_epoch_to_pointcloud2(drive.gnss[k]))
        g.spin_until(lambda: len(risks) > n, what='integrity_risk')
        return ma.parse_integrity_risk(risks[-1])

    first = epoch(0)
    assert first.alert_limit_m == 8.0 and first.target_risk == 0.1
    ok = fusion.set_parameters([Parameter('alert_limit_m', value=16.0),
                                Parameter('target_risk', value=0.3)])
    assert all(r.successful for r in ok)
    assert fusion.engine.config.alert_limit_m == 16.0
    second = epoch(1)
    assert (second.alert_limit_m, second.target_risk) == (16.0, 0.3)

    for name, value, text in (('target_risk', 1.5, 'target_risk'),
                              ('n_posteriors', 0, 'n_posteriors'),
                              ('likelihood', 'gaussian', 'likelihood must be one of'),
                              ('camera_gate_m', -1.0, 'camera_gate_m'),
                              ('seed', 3, 'read-only')):
        result = fusion.set_parameters([Parameter(name, value=value)])[0]
        assert not result.successful and text in result.reason, (name, result.reason)
    result = fusion.set_parameters([Parameter('alert_limit_m', value='far')])[0]
    assert not result.successful                 # wrong type
    assert fusion.engine.config.alert_limit_m == 16.0 and fusion.engine.config.target_risk == 0.3

    # The same refusal through the parameter service, as `ros2 param set` would see it.
    from rcl_interfaces.srv import SetParameters
    client = g.probe.create_client(SetParameters, '/fusion_node/set_parameters')
    g.spin_until(client.service_is_ready, what='the parameter service')
    future = client.call_async(SetParameters.Request(parameters=[
        Parameter('measurement_var_m2', value=0.0).to_parameter_msg()]))
    g.spin_until(future.done, what='the service answer')
    answer = future.result().results[0]
    assert not answer.successful and 'measurement_var_m2' in answer.reason
    future = client.call_async(SetParameters.Request(parameters=[
        Parameter('alert_limit_m', value=4.0).to_parameter_msg()]))
    g.spin_until(future.done, what='the service answer')
    assert future.result().results[0].successful
    assert epoch(2).alert_limit_m == 4.0


# =================================================================== stale reports
@pytest.mark.slow
def test_integrity_is_stale_without_gnss_and_never_a_stale_ok(graph, drive):
    g = graph
    g.add(FusionNode(context=g.ctx, parameter_overrides=overrides(
        n_particles=100, gnss_timeout_s=0.3, stale_report_period_s=0.1, seed=2,
        inverse_bernoulli='approx', target_risk=0.9)))
    risks = g.collect(DiagnosticArray, 'integrity_risk')
    pub = g.publisher(PointCloud2, 'gnss/measurements')
    g.connect(pub)
    g.spin_until(lambda: len(risks) >= 2, what='stale reports before any GNSS')
    before = [ma.parse_integrity_risk(m) for m in risks]
    assert all(r.stale and r.epoch_stamp_ns is None for r in before)
    n_before = len(risks)
    for epoch in drive.gnss[:6]:
        # Each epoch's verdict before the next epoch (not a fixed pause: a loaded machine
        # may take longer than any pause chosen here).
        pub.publish(ma.gnss_epoch_to_pointcloud2(epoch))
        g.spin_until(lambda: any(ma.parse_integrity_risk(m).epoch_stamp_ns == epoch.stamp_ns
                                 for m in risks[n_before:]), what='the epoch verdict')
    during = [ma.parse_integrity_risk(m) for m in risks[n_before:]]
    assert any(r.level in (ma.OK, ma.ERROR) for r in during)
    # No dead reckoning at all: the motion is unknown, so never OK, and the message says
    # why (even with a target that the bound alone would meet).
    updated = [r for r in during if r.epoch_status == 'updated']
    assert len(updated) >= 2 and all(r.level == ma.ERROR for r in updated)
    assert all('motion unknown' in r.message and float(r.extra['motion_unknown_s']) > 0
               for r in updated[1:])             # the first fix has no interval
    assert all(math.isfinite(r.protection_level_m) for r in updated)
    n_stop = len(risks)
    g.spin_until(lambda: len(risks) >= n_stop + 3, what='stale reports after GNSS stopped')
    after = [ma.parse_integrity_risk(m) for m in risks[n_stop:]]
    assert all(r.stale and not r.integrity_ok for r in after)
    assert after[-1].epoch_stamp_ns == drive.gnss[5].stamp_ns
    assert all(math.isnan(r.risk_bound) for r in after)


# =============================================================== camera keeps up
def test_camera_without_database_reports_warn_matching_off(graph):
    """Running without a camera map is supported: diagnostics say WARN (it reported ERROR,
    a failure, for as long as the node ran), also while images arrive."""
    g = graph
    cam = g.add(CameraNode(context=g.ctx, parameter_overrides=overrides(
        diagnostics_period_s=0.1)))
    reports = g.collect(DiagnosticArray, 'diagnostics')
    pub = g.publisher(Image, 'camera/image_raw')
    g.connect(pub)
    pub.publish(ma.array_to_image(synthetic_scene(0, seed=3), S))
    g.spin_until(lambda: cam.stats.get('frames_without_match') == 1, what='the frame')
    n_before = len(reports)
    g.spin_until(lambda: len(reports) >= n_before + 2, what='diagnostics')
    statuses = [s for m in reports for s in m.status if s.name == 'camera_node: status']
    assert statuses
    levels = {(int.from_bytes(s.level, 'little') if isinstance(s.level, bytes) else s.level,
               s.message) for s in statuses}
    assert levels == {(ma.WARN, 'no map database: matching off')}


def test_camera_without_database_answers_every_frame_with_empty_matches(graph):
    """No map database (the default): each frame is refused and answered with an empty
    camera/matches of its stamp, which fusion_node takes as a frame without a match (a
    replay takes it as the acknowledgement of the image)."""
    g = graph
    cam = g.add(CameraNode(context=g.ctx))
    fusion = g.add(FusionNode(context=g.ctx, parameter_overrides=overrides(n_particles=100)))
    pub = g.publisher(Image, 'camera/image_raw')
    answers = g.collect(PointCloud2, 'camera/matches')
    g.connect(pub)
    g.spin_until(lambda: cam.pub.get_subscription_count() >= 2, what='camera/matches readers')
    image = synthetic_scene(0, seed=3)
    stamps = [S + k * S // 10 for k in range(5)]
    for stamp in stamps:
        pub.publish(ma.array_to_image(image, stamp))
        g.spin_until(lambda: len(answers) > stamps.index(stamp), what='the answer')
    assert [ma.stamp_to_ns(m.header.stamp) for m in answers] == stamps
    assert all(m.width == 0 and m.header.frame_id == 'map' for m in answers)
    assert all(len(ma.pointcloud2_to_matches(m)) == 0 for m in answers)
    assert cam.stats.rejected == {'no_database': 5}
    assert cam.stats.get('frames_without_match') == 5
    g.spin_until(lambda: fusion.stats.get('camera_without_match') == 5, what='fusion')
    assert not fusion.stats.rejected and fusion.engine.camera == []


@pytest.mark.slow
def test_camera_drops_the_oldest_frames_and_counts_them(graph):
    g = graph
    images = [synthetic_scene(i, seed=4) for i in range(4)]
    db = small_database(images, np.zeros((4, 3)))
    cam = g.add(CameraNode(context=g.ctx, database=db, parameter_overrides=overrides(
        queue_size=1, input_queue_depth=200)))
    pub = g.publisher(Image, 'camera/image_raw')
    matches = g.collect(PointCloud2, 'camera/matches')
    g.connect(pub)
    frames = [ma.array_to_image(images[k % 4], (k + 1) * S // 100) for k in range(40)]
    for msg in frames:                                  # 40 frames in a burst
        pub.publish(msg)
    g.spin_until(lambda: cam.stats.get('received_images') == 40, what='all frames received')
    g.spin_until(lambda: cam.stats.get('published_matches') + cam.stats.get('dropped_frames')
                 == 40, what='the matcher to finish')
    g.spin_until(lambda: len(matches) == cam.stats.get('published_matches'), what='matches')
    dropped = cam.stats.get('dropped_frames')
    assert dropped > 0 and not cam.stats.rejected
    stamps = [ma.stamp_to_ns(m.header.stamp) for m in matches]
    assert stamps == sorted(stamps) and stamps[-1] == frames[-1].header.stamp.nanosec + (
        frames[-1].header.stamp.sec * S)              # the newest frame is never dropped
    values = cam.stats.values()
    assert values['dropped_frames'] == dropped and values['processing_count'] == len(matches)


# ================================================== outputs for ROS users (issue 14 item 5)
LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _integrity_status(reports):
    """The newest ``fusion_node: integrity`` status of the collected diagnostics."""
    found = [s for m in reports for s in m.status if s.name == 'fusion_node: integrity']
    return found[-1] if found else None


@pytest.mark.slow
def test_odometry_global_map_origin_and_integrity_on_diagnostics(graph, drive):
    g = graph
    fusion = g.add(FusionNode(context=g.ctx, parameter_overrides=overrides(
        n_particles=100, seed=3, gnss_timeout_s=60.0, odometry_wait_s=10.0,
        odometry_timeout_s=60.0, diagnostics_period_s=3600.0)))
    pub_gnss = g.publisher(PointCloud2, 'gnss/measurements')
    pub_dr = g.publisher(Odometry, 'odometry/dead_reckoning')
    risks = g.collect(DiagnosticArray, 'integrity_risk')
    poses = g.collect(PoseWithCovarianceStamped, 'pose')
    odoms = g.collect(Odometry, 'odometry/global')
    reports = g.collect(DiagnosticArray, 'diagnostics')
    g.connect(pub_gnss, pub_dr)
    g.spin_until(lambda: fusion.pub_odometry.get_subscription_count() > 0
                 and fusion._diag_pub.get_subscription_count() > 0, what='output readers')

    # Before any verdict the integrity status on diagnostics is STALE, never OK.
    fusion.publish_diagnostics()
    g.spin_until(lambda: _integrity_status(reports) is not None, what='diagnostics')
    assert ma.level_to_int(_integrity_status(reports).level) == ma.STALE
    assert not fusion.origin_published            # no map frame yet: no map/origin

    states = dead_reckon(drive.imu, drive.odometry, DeadReckoningConfig())
    sent = 0
    epochs = drive.gnss[:6]
    for epoch in epochs:
        # The dead reckoning runs 0.25 s ahead of the epoch: the twist must still be the
        # state at (or before) the epoch, not the newest one.
        while sent < len(states) and states[sent].stamp_ns <= epoch.stamp_ns + S // 4:
            n = fusion.stats.get('received_dead_reckoning')
            pub_dr.publish(ma.dead_reckoning_to_odometry(states[sent]))
            sent += 1
            g.spin_until(lambda: fusion.stats.get('received_dead_reckoning') > n)
        n = len(risks)
        pub_gnss.publish(ma.gnss_epoch_to_pointcloud2(epoch))
        g.spin_until(lambda: len(risks) > n, what='integrity_risk')
        status = fusion.last_result.status
        if status in (UPDATED, PROPAGATED):
            g.spin_until(lambda: len(odoms) == len(poses) and poses
                         and ma.stamp_to_ns(poses[-1].header.stamp) == epoch.stamp_ns,
                         what='pose and odometry/global of the epoch')
        # The diagnostics status mirrors this epoch's integrity_risk.
        risk = ma.parse_integrity_risk(risks[-1])
        fusion.publish_diagnostics()
        g.spin_until(lambda: (st := _integrity_status(reports)) is not None
                     and ma.status_values(st).get('epoch_stamp') == str(epoch.stamp_ns),
                     what='the integrity status of the epoch')
        st = _integrity_status(reports)
        values = ma.status_values(st)
        assert ma.level_to_int(st.level) == risk.level and st.message == risk.message
        assert float(values['alert_limit_m']) == risk.alert_limit_m
        pl = float(values['protection_level_m'])
        assert pl == risk.protection_level_m or (math.isnan(pl)
                                                 and math.isnan(risk.protection_level_m))
    assert len(poses) >= len(epochs) - 1
    assert {ma.parse_integrity_risk(m).level for m in risks} <= {ma.OK, ma.ERROR, ma.STALE}

    # odometry/global: the pose of the same epoch, map -> base_link, with the dead
    # reckoning's speed and yaw rate at the epoch.
    by_stamp = {s.stamp_ns: s for s in states}
    for pose_msg, odom_msg in zip(poses, odoms):
        pose, odom = ma.msg_to_pose(pose_msg), ma.odometry_to_global(odom_msg)
        assert odom.stamp_ns == pose.stamp_ns
        assert (odom_msg.header.frame_id, odom_msg.child_frame_id) == ('map', 'base_link')
        np.testing.assert_array_equal(odom.position_m, pose.position_m)
        np.testing.assert_array_equal(odom.pose_covariance, pose.covariance)
        assert odom.yaw_rad == pose.yaw_rad
        assert odom.pose_covariance[3, 3] == odom.pose_covariance[4, 4] >= 1e6
        state = by_stamp[odom.stamp_ns]           # the state at the (whole-second) epoch
        assert (odom.speed_mps, odom.yaw_rate_rps, odom.speed_var, odom.yaw_rate_var) == (
            state.speed_mps, state.yaw_rate_rps, state.speed_var, state.yaw_rate_var)
    assert any(o.twist.twist.linear.x > 1.0 for o in odoms)   # the vehicle moves

    # map/origin: latched; a subscriber that comes after the first fix still gets it.
    assert fusion.origin_published
    late = []
    g.probe.create_subscription(NavSatFix, 'map/origin', late.append, LATCHED)
    g.spin_until(lambda: late, 10.0, 'map/origin at a late subscriber')
    g.spin_for(0.2)
    assert len(late) == 1
    origin = ma.navsatfix_to_fix(late[0])
    lat, lon, alt = fusion.engine.frame.origin_llh
    assert (origin.lat_deg, origin.lon_deg, origin.alt_m) == (lat, lon, alt)
    assert late[0].header.frame_id == 'map' and origin.status == 0
    assert late[0].position_covariance_type == NavSatFix.COVARIANCE_TYPE_UNKNOWN
    assert origin.stamp_ns == epochs[0].stamp_ns        # the first fix anchored the frame


def test_configured_map_origin_is_latched_from_the_start(graph):
    g = graph
    origin = [48.858, 2.2945, 35.0]
    fusion = g.add(FusionNode(context=g.ctx, parameter_overrides=overrides(
        n_particles=100, use_map_origin=True, map_origin_llh=origin)))
    late = []
    # Subscribed only once the origin went out: the latched copy is what arrives.
    g.spin_until(lambda: fusion.origin_published, 10.0, 'map/origin published')
    g.probe.create_subscription(NavSatFix, 'map/origin', late.append, LATCHED)
    g.spin_until(lambda: late, 10.0, 'map/origin before any GNSS')
    fix = ma.navsatfix_to_fix(late[0])
    assert [fix.lat_deg, fix.lon_deg, fix.alt_m] == origin


# ============================================== start-up parameters (issue 14 item 6)
def test_integers_are_accepted_for_float_parameters_at_start_and_at_run_time():
    g = RosGraph(args=['--ros-args', '-p', 'alert_limit_m:=16', '-p', 'camera_gate_m:=30'])
    try:
        fusion = g.add(FusionNode(context=g.ctx, parameter_overrides=overrides(
            n_particles=100, gnss_timeout_s=5)))
        assert fusion.engine.config.alert_limit_m == 16.0
        assert type(fusion.param('alert_limit_m')) is float
        assert fusion.param('gnss_timeout_s') == 5.0 and fusion.param('camera_gate_m') == 30.0
        result = fusion.set_parameters([Parameter('alert_limit_m', value=12)])[0]
        assert result.successful, result.reason
        assert fusion.engine.config.alert_limit_m == 12.0
        assert type(fusion.param('alert_limit_m')) is float
        # An integer parameter still refuses a float, a float one a string.
        assert not fusion.set_parameters([Parameter('n_posteriors', value=2.5)])[0].successful
        assert not fusion.set_parameters([Parameter('alert_limit_m', value='x')])[0].successful
    finally:
        g.close()


@pytest.mark.parametrize('node_class, values, error, text', [
    (FusionNode, {'likelihood': 'gauss'}, ParameterError,
     "fusion_node: invalid filter configuration: likelihood must be one of"),
    (FusionNode, {'n_particles': 0}, ParameterError,
     'fusion_node: parameter n_particles = 0 refused: out of range [2, 10000000]'),
    (FusionNode, {'alert_limit_m': 'far'}, ParameterError,
     "fusion_node: parameter alert_limit_m: expected a number, got 'far'"),
    (ImuNode, {'yaw_rate_source': 'compass'}, ParameterError,
     'imu_node: invalid dead-reckoning configuration: yaw_rate_source'),
    (CameraNode, {'database_path': '/nonexistent/map.npz'}, InputFileError,
     'camera_node: database_path: /nonexistent/map.npz: no such database file'),
])
def test_a_bad_start_up_parameter_is_one_clear_error(graph, node_class, values, error, text):
    with pytest.raises(error) as info:
        node_class(context=graph.ctx, parameter_overrides=overrides(**values))
    assert str(info.value).startswith(text) and '\n' not in str(info.value)
