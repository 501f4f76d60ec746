"""Replay of a converted bag through the nodes, recording and evaluation (live.replay,
live.record, evaluation.demo).

* end to end: an emulated drive -> bag -> replay at R = 0 through the four nodes ->
  recorded result bag -> ``evaluate_result_bag`` equals the offline run of the same drive
  and seed (estimates to 1e-6 m, the same RMSE, P_FA, P_MI), and is close to
  ``evaluate_drive``; no GNSS epoch dropped, nothing unacknowledged;
* camera: the matches flow (every frame acknowledged by camera/matches, the filter fuses
  them) and the camera path equals the offline run with the same database;
* rate scaling (R = 2 on a 4 s bag takes ~2 s), ``--start``, ``--topics``;
* missing and corrupt bags -> clear errors (library and CLI exit code), the recorder
  never overwrites and removes its partial bag; SIGINT stops the CLIs cleanly.
"""
import shutil
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from ros_harness import RosGraph, ros_env, wait_until  # skips without rclpy
import rclpy
from sensor_msgs.msg import Imu

from gnsscam_ros.bags.convert import convert_drive
from gnsscam_ros.bags.errors import BagExistsError, BagReadError
from gnsscam_ros.bags.read import bag_topics, read_drive, read_results
from gnsscam_ros.live.replay_through_nodes import replay_through_nodes
from gnsscam_ros.live.player import BagReplayer
from gnsscam_ros.live.record import BagRecorder
from gnsscam_ros.live.replay import main as replay_main
from gnsscam_ros.core.filter import FilterConfig
from gnsscam_ros.datasets.emulated.drive import make_emulated_drive
from gnsscam_ros.datasets.emulated.views import route_range_of
from gnsscam_ros.evaluation.bag_eval import evaluate_result_bag
from gnsscam_ros.evaluation.demo import node_series, offline_run
from gnsscam_ros.evaluation.evaluate import evaluate_drive
from gnsscam_ros.evaluation.runner import offline_camera_matches, summarize

# Every test here runs ROS nodes in a graph of its own.
pytestmark = pytest.mark.ros

ROOT = Path(__file__).resolve().parents[1]
SEED, N_PARTICLES = 7, 400


def fusion_params(drive, **extra) -> dict:
    return {'fusion_node': {'n_particles': N_PARTICLES, 'seed': SEED, 'use_map_origin': True,
                            'map_origin_llh': [float(v) for v in drive.origin_llh], **extra}}


@pytest.fixture(scope='module')
def emulated_bag(tmp_path_factory):
    """A 60 s emulated drive with faults (GNSS, IMU, odometry, truth; no camera): long
    enough for the filter to settle and say OK at some epochs (open-sky-like measurements,
    no NLOS), ERROR at others."""
    folder = tmp_path_factory.mktemp('replay')
    drive = make_emulated_drive(21, faults=6, bias_m=100.0, nlos=False, duration_s=60.0)
    convert_drive(drive, folder / 'bag')
    return folder / 'bag'


@pytest.fixture(scope='module')
def short_bag(tmp_path_factory):
    """A 4 s emulated drive."""
    folder = tmp_path_factory.mktemp('replay_short')
    convert_drive(make_emulated_drive(5, duration_s=4.0), folder / 'bag')
    return folder / 'bag'


@pytest.fixture
def ctx():
    """A fresh rclpy context of its own domain (nothing subscribes: the replay plays to
    nobody)."""
    g = RosGraph()
    yield g.ctx
    g.close()


# ================================================================= end to end (GNSS)
@pytest.mark.slow
def test_replay_through_nodes_equals_offline_evaluation(emulated_bag, tmp_path):
    drive = read_drive(emulated_bag)
    result_bag = tmp_path / 'result'
    summary, record = replay_through_nodes(emulated_bag, result_bag, rate=0.0,
                                           parameters=fusion_params(drive), layout='threads')
    # Lossless: every GNSS epoch got its integrity_risk back, nothing timed out.
    assert summary.gnss_epochs == len(drive.gnss) == 61
    assert summary.gnss_epochs_processed == summary.gnss_epochs
    assert summary.dropped_gnss_epochs == 0
    assert not any(summary.unacknowledged.values()), summary.unacknowledged
    assert set(summary.flow_control.values()) == {'on'}
    assert summary.start == 'links matched'          # the nodes reported every link
    assert summary.node_diagnostics['fusion_node: status'].get('dropped_epochs', '0') == '0'
    counts = {k: v[1] for k, v in bag_topics(emulated_bag).items()}
    assert summary.published == counts
    assert record.counts['/integrity_risk'] == len(drive.gnss)
    assert record.counts['/ground_truth/pose'] == counts['/ground_truth/pose']
    # map/origin: the dataset's (replayed) and fusion_node's (its map frame, at the same
    # map_origin_llh here), both latched.
    assert record.counts['/map/origin'] == 2 and record.counts['/dataset/info'] == 1
    assert record.counts['/odometry/global'] == record.counts['/pose'] > 0

    # The recorded run equals the offline run of the same drive, seed and configuration.
    config = FilterConfig(n_particles=N_PARTICLES)
    nodes = evaluate_result_bag(result_bag)            # self-contained: truth recorded
    off_record, frame = offline_run(drive, config, SEED)
    offline = summarize(off_record, config)
    # Both verdicts occur, so that the equalities below compare OK and ERROR epochs (a run
    # all ERROR makes P_FA 1 and P_MI 0 whatever the nodes computed).
    declared_ok = int(off_record.integrity_ok.sum())
    assert 0 < declared_ok < len(off_record.stamp_ns), declared_ok
    assert offline['integrity']['8']['false_alarms'] < offline['epochs'] - offline[
        'integrity']['8']['faults'], offline['integrity']['8']
    series = node_series(result_bag, frame)
    np.testing.assert_array_equal(series['stamp_ns'], off_record.stamp_ns)
    np.testing.assert_allclose(series['estimate_enu_m'], off_record.estimate_enu_m, rtol=0,
                               atol=1e-6)
    np.testing.assert_allclose(series['risk_bound'], off_record.risk_bound['exact'][:, 0],
                               rtol=1e-9, atol=1e-12)
    assert nodes['epochs'] == offline['epochs'] == len(off_record.stamp_ns)
    for key in ('rmse_2d_m', 'rmse_3d_m', 'p95_2d_m', 'max_2d_m'):
        assert nodes[key] == pytest.approx(offline[key], rel=1e-7), key
    mine, theirs = nodes['integrity']['8'], offline['integrity']['8']
    for key in ('p_fa', 'p_mi', 'false_alarms', 'missed_identifications', 'faults'):
        assert mine[key] == theirs[key], key
    assert mine['mean_risk_bound'] == pytest.approx(theirs['mean_risk_bound'], rel=1e-9)
    # The protection level the nodes published is the offline one, epoch by epoch: the
    # counts exactly; its percentiles, like the estimates above, to rounding (the last
    # digit of the median differed with numpy 1.24).
    for key in ('mi_rate', 'mi_epochs', 'availability'):
        assert nodes['protection_level'][key] == offline['protection_level'][key], key
    for key in ('median_m', 'p95_m'):
        assert nodes['protection_level'][key] == pytest.approx(
            offline['protection_level'][key], rel=1e-9), key
    # The reference risk differs in kind: a bag holds the published particle cloud, not
    # the M posteriors with their bias hypotheses, so the failure ratio is not compared.
    # evaluate_drive integrates the odometry itself (integrate_odometry, equal to the dead
    # reckoning to ~1e-9 m); the filter amplifies that, so only closeness is expected.
    standard = evaluate_drive(drive, config, seed=SEED)
    assert nodes['rmse_2d_m'] == pytest.approx(standard['rmse_2d_m'], rel=0.1)
    assert nodes['rmse_3d_m'] == pytest.approx(standard['rmse_3d_m'], rel=0.1)
    # And the dataset bag gives the same metrics as the recorded truth, plus the baseline.
    with_truth_bag = evaluate_result_bag(result_bag, emulated_bag)
    assert with_truth_bag['rmse_2d_m'] == nodes['rmse_2d_m']
    assert with_truth_bag['baseline_wls']['epochs'] == len(drive.gnss)


# ===================================================================== camera path
class SceneCamera:
    """Synthetic street images at 2 Hz (seeded facades; ORB finds features on them)."""

    def __init__(self, stamps_ns):
        from gnsscam_ros.vision.synthetic import synthetic_scene
        self.stamp_ns = np.asarray(stamps_ns, dtype=np.int64)
        self._scene = synthetic_scene

    def image(self, i):
        return self._scene(int(i), seed=11)


@pytest.mark.slow
def test_camera_matches_flow_and_equal_offline(tmp_path):
    from gnsscam_ros.core.frames import LocalFrame
    from gnsscam_ros.vision.database import MapDatabase, PositionTable
    from gnsscam_ros.vision.features import OrbExtractor, OrbParams
    drive = make_emulated_drive(21, faults=3, bias_m=80.0, duration_s=14.0)
    t0 = drive.gnss[0].stamp_ns
    camera = SceneCamera(t0 + np.arange(1, 28) * 500_000_000)      # 27 frames at 2 Hz
    frame = LocalFrame(*drive.origin_llh)
    truth_enu = frame.ecef_to_enu(drive.truth.ecef_m)
    positions = np.column_stack([np.interp(camera.stamp_ns, drive.truth.stamp_ns,
                                           truth_enu[:, j]) for j in range(3)])
    ext = OrbExtractor(OrbParams(nfeatures=500))
    images = [camera.image(i) for i in range(len(camera.stamp_ns))]
    db = MapDatabase.build([ext.descriptors(im) for im in images],
                           [f'im{i}.png' for i in range(len(images))],
                           PositionTable.from_columns(('east_m', 'north_m', 'up_m'), positions),
                           orb_params=OrbParams(nfeatures=500), branching=8, depth=3,
                           iterations=4, seed=0)
    convert_drive(drive, tmp_path / 'bag', camera=camera)
    data = read_drive(tmp_path / 'bag')
    summary, record = replay_through_nodes(
        tmp_path / 'bag', tmp_path / 'result', parameters=fusion_params(data),
        database=db, layout='threads',
        record_topics=['pose', 'fix', 'particles', 'integrity_risk', 'ground_truth/pose',
                       'map/origin', 'camera/matches:sensor_msgs/msg/PointCloud2'])
    assert summary.published['/camera/image_raw'] == len(images)
    assert summary.flow_control['camera/image_raw'] == 'on'
    assert summary.unacknowledged['camera/image_raw'] == 0
    assert record.counts['/camera/matches'] == len(images)      # every frame matched
    assert summary.dropped_gnss_epochs == 0
    risks = read_results(tmp_path / 'result', particles=False).integrity
    fused = [r for r in risks if 'camera_images' in r.extra]
    assert fused, 'the filter fused camera matches'
    # The camera path equals the offline run with the same database and matches.
    matches = offline_camera_matches(data.camera, db)
    assert [m.frame_id for m in matches] == list(range(len(images)))
    config = FilterConfig(n_particles=N_PARTICLES)
    off_record, off_frame = offline_run(data, config, SEED, matches)
    assert off_record.camera_epochs == len(fused)
    series = node_series(tmp_path / 'result', off_frame)
    np.testing.assert_allclose(series['estimate_enu_m'], off_record.estimate_enu_m, rtol=0,
                               atol=1e-6)


@pytest.mark.slow
def test_route_range_limits_the_database_to_the_drive():
    from gnsscam_ros.datasets.emulated.scenario import scenario_of
    from gnsscam_ros.datasets.emulated.views import database_poses
    drive = make_emulated_drive(3, duration_s=60.0)
    scenario = scenario_of(drive)
    s0, s1 = route_range_of(scenario, drive)
    assert s0 == 0.0 and 0.0 < s1 < scenario.route.length_m
    assert len(database_poses(scenario, route_range_m=(s0, s1))) < len(
        database_poses(scenario))


# ============================================================ timing, start, topics
@pytest.mark.slow
def test_rate_scales_the_original_timing(short_bag, ctx):
    replayer = BagReplayer(short_bag, rate=2.0, wait_s=0.0, context=ctx)
    try:
        summary = replayer.play()
    finally:
        replayer.destroy_node()
    # Paced: never faster than asked (a loaded machine can only make it slower, so the
    # upper bound of the wall time is a benchmark's business, not a test's).
    assert summary.bag_span_s == pytest.approx(4.0, abs=0.02)
    assert summary.wall_s >= 2.0 - 0.05
    assert summary.speed <= 2.0 * 1.03
    # Nobody listens: flow control is off for every stream, with the reason.
    assert all(v == 'off: no subscriber' for v in summary.flow_control.values())
    assert summary.start == ''
    fast = BagReplayer(short_bag, rate=0.0, wait_s=0.0, context=ctx)
    try:
        unpaced = fast.play()               # rate 0: as fast as it can, every message
    finally:
        fast.destroy_node()
    assert unpaced.published == summary.published


@pytest.mark.slow
def test_start_skips_bag_time_but_keeps_the_once_only_topics(short_bag, ctx):
    replayer = BagReplayer(short_bag, rate=0.0, start_s=2.0, wait_s=0.0, context=ctx)
    try:
        summary = replayer.play()
    finally:
        replayer.destroy_node()
    drive = read_drive(short_bag)
    t0 = drive.gnss[0].stamp_ns
    assert summary.first_stamp_ns >= t0 + 2_000_000_000
    assert summary.published['/map/origin'] == 1 and summary.published['/dataset/info'] == 1
    assert summary.gnss_epochs == sum(e.stamp_ns >= t0 + 2_000_000_000 for e in drive.gnss)


@pytest.mark.slow
def test_topics_filter_plays_only_the_named_topics(short_bag, tmp_path, ctx):
    topics = ['imu/data:sensor_msgs/msg/Imu', 'odom/twist',
              'gnss/pseudoranges:sensor_msgs/msg/PointCloud2']
    recorder = BagRecorder(tmp_path / 'rec', topics=topics, context=ctx)
    executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
    executor.add_node(recorder)
    spin = threading.Thread(target=executor.spin, daemon=True)
    spin.start()
    replayer = BagReplayer(short_bag, rate=0.0, topics=['imu/data', '/odom/twist'],
                           wait_s=5.0, require_subscribers=('imu/data', 'odom/twist'),
                           context=ctx)
    try:
        summary = replayer.play()
        counts = {k: v[1] for k, v in bag_topics(short_bag).items()}
        wait_until(lambda: recorder.count('imu/data') >= counts['/imu/data'], 5.0,
                   'every IMU message recorded')
    finally:
        replayer.destroy_node()
        executor.shutdown()
        spin.join(timeout=5)
    rec = recorder.close()
    recorder.destroy_node()
    assert set(summary.published) == {'/imu/data', '/odom/twist'}
    assert summary.published['/imu/data'] == counts['/imu/data']
    assert rec.counts['/imu/data'] == counts['/imu/data']
    assert rec.counts['/odom/twist'] == counts['/odom/twist']
    assert rec.counts['/gnss/pseudoranges'] == 0          # not played
    with pytest.raises(ValueError, match='no topic .camera/image_raw'):
        BagReplayer(short_bag, topics=['camera/image_raw'], context=ctx)


# ===================================================================== bad input
def test_missing_and_corrupt_bags_give_clear_errors(short_bag, tmp_path, ctx, capsys):
    missing = tmp_path / 'nothing'
    with pytest.raises(BagReadError, match='no such bag'):
        BagReplayer(missing, context=ctx)
    assert replay_main([str(missing), '--wait', '0']) == 3
    assert 'no such bag' in capsys.readouterr().err
    # A truncated MCAP file: refused when opened or while playing, never half-silently.
    broken = tmp_path / 'broken'
    shutil.copytree(short_bag, broken)
    mcap = next(broken.glob('*.mcap'))
    data = mcap.read_bytes()
    mcap.write_bytes(data[:len(data) // 2])
    with pytest.raises(BagReadError, match='broken'):
        replayer = BagReplayer(broken, rate=0.0, wait_s=0.0, context=ctx)
        try:
            replayer.play()
        finally:
            replayer.destroy_node()
    not_a_bag = tmp_path / 'not_a_bag'
    not_a_bag.mkdir()
    (not_a_bag / 'metadata.yaml').write_text('this: is not rosbag2 metadata\n')
    assert replay_main([str(not_a_bag), '--wait', '0']) == 3
    assert 'not_a_bag' in capsys.readouterr().err


def test_recorder_never_overwrites_and_cleans_up(tmp_path, ctx):
    existing = tmp_path / 'exists'
    existing.mkdir()
    with pytest.raises(BagExistsError):
        BagRecorder(existing, context=ctx)
    recorder = BagRecorder(tmp_path / 'aborted', context=ctx)
    recorder.abort()
    recorder.destroy_node()
    assert not any(p.name.startswith('.aborted') for p in tmp_path.iterdir())
    assert not (tmp_path / 'aborted').exists()


# ============================================================================= CLIs
@pytest.mark.slow
def test_clis_stop_cleanly_on_sigint(emulated_bag, tmp_path):
    graph = RosGraph()
    imu = graph.collect(Imu, 'imu/data')
    env = ros_env(tmp_path, graph.domain)
    record = subprocess.Popen([sys.executable, '-m', 'gnsscam_ros.live.record', '--out',
                               str(tmp_path / 'rec'), 'imu/data:sensor_msgs/msg/Imu'],
                              env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True)
    # The recorder listens before anything is played (the probe is the other subscriber).
    graph.spin_until(lambda: graph.probe.count_subscribers('/imu/data') >= 2
                     or record.poll() is not None, 120.0, 'the recorder subscribing')
    assert record.poll() is None, record.communicate()[1]
    replay = subprocess.Popen([sys.executable, '-m', 'gnsscam_ros.live.replay',
                               str(emulated_bag), '--rate', '1', '--wait', '0'],
                              env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True)
    try:
        # Interrupted while it plays: after 10 s of the 40 s bag's IMU samples (the
        # recorder, another process, discovers the replay's publishers meanwhile).
        graph.spin_until(lambda: len(imu) >= 1000 or replay.poll() is not None, 120.0,
                         'the replay publishing')
        assert replay.poll() is None, replay.communicate()[1]
        replay.send_signal(signal.SIGINT)
        out, err = replay.communicate(timeout=20)
        assert replay.returncode == 0, err
        assert 'interrupted' in out and 'replayed' in out          # the partial summary
        assert '40.0 s of bag time' not in out
        record.send_signal(signal.SIGINT)
        out, err = record.communicate(timeout=20)
        assert record.returncode == 0, err
    finally:
        for proc in (replay, record):
            if proc.poll() is None:
                proc.kill()
        graph.close()
    counts = {k: v[1] for k, v in bag_topics(tmp_path / 'rec').items()}
    assert 0 < counts['/imu/data'] < 4001          # part of the drive, and a valid bag
    assert not any(p.name.startswith('.rec') for p in tmp_path.iterdir())


# ============================================== default nodes without a map database
@pytest.mark.slow
def test_default_camera_bag_flows_through_a_default_pipeline_node(tmp_path):
    """Issue 14: a converted emulated bag (camera included, as gnsscam_convert does by
    default) replayed into pipeline_node with its defaults (camera_node without a map
    database). camera_node answers every frame with an empty camera/matches, so the
    replay's flow control is never held up waiting for matches (it once waited 3 x 30 s
    and the GNSS epochs waited behind it), and every epoch gets a verdict."""
    from diagnostic_msgs.msg import DiagnosticArray
    from gnsscam_ros.bags.convert_cli import main as convert_main
    from msg_adapters import STALE, parse_integrity_risk
    bag = tmp_path / 'bag'
    assert convert_main(['emulated', '--seed', '3', '--duration-s', '8', '--out', str(bag),
                         '--quiet']) == 0
    counts = {k: v[1] for k, v in bag_topics(bag).items()}
    frames, epochs = counts['/camera/image_raw'], counts['/gnss/pseudoranges']
    assert frames >= 70 and epochs == 9
    graph = RosGraph()
    env = ros_env(tmp_path, graph.domain)
    verdicts = []
    listener = graph.probe.create_subscription(
        DiagnosticArray, 'integrity_risk', lambda m: verdicts.append(parse_integrity_risk(m)),
        100)
    spin = threading.Thread(target=graph.executor.spin, daemon=True)
    spin.start()
    pipeline = subprocess.Popen([sys.executable, '-m', 'gnsscam_ros.nodes.pipeline'], env=env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        # The listener must be matched before the first verdict (volatile topic).
        wait_until(lambda: listener.get_publisher_count() > 0 or pipeline.poll() is not None,
                   60.0, 'pipeline_node publishing integrity_risk')
        assert pipeline.poll() is None, pipeline.communicate()[1]
        replay = subprocess.run([sys.executable, '-m', 'gnsscam_ros.live.replay', str(bag),
                                 '--rate', '4', '--wait', '60', '--json',
                                 str(tmp_path / 'replay.json')],
                                env=env, capture_output=True, text=True, timeout=600)
        assert replay.returncode == 0, replay.stderr
        wait_until(lambda: len({v.epoch_stamp_ns for v in verdicts if not v.stale})
                   >= epochs - 1, 10.0, 'a verdict for every epoch')
    finally:
        pipeline.send_signal(signal.SIGINT)
        try:
            _, pipeline_err = pipeline.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            pipeline.kill()
            _, pipeline_err = pipeline.communicate()
        graph.close()
        spin.join(timeout=5)
    assert pipeline.returncode == 0, pipeline_err
    import json
    summary = json.loads((tmp_path / 'replay.json').read_text())
    # Not held up: every image acknowledged (no 30 s timeouts), flow control stayed on.
    assert summary['published']['/camera/image_raw'] == frames
    assert summary['unacknowledged'] == {'gnss/pseudoranges': 0, 'camera/image_raw': 0,
                                         'imu/data': 0, 'odom/twist': 0}
    assert set(summary['flow_control'].values()) == {'on'}
    assert 'no camera/matches' not in replay.stderr
    # Every GNSS epoch produced an integrity_risk, and a valid verdict (not STALE) for all
    # but the first fix, seen by an independent listener.
    assert summary['gnss_epochs'] == summary['gnss_epochs_processed'] == epochs
    assert summary['dropped_gnss_epochs'] == 0
    valid = {v.epoch_stamp_ns for v in verdicts if v.level != STALE}
    assert len(valid) >= epochs - 1
    # The frames were refused for want of a database and answered, not matched.
    camera = summary['node_diagnostics']['camera_node: status']
    assert int(camera['rejected_no_database']) > 0
    assert int(camera['frames_without_match']) > 0
    assert int(summary['node_diagnostics']['fusion_node: status']['camera_without_match']) > 0
