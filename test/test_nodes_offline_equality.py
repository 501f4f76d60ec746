"""An emulated sequence through the gnss, camera and imu topics gives the same pose,
particles and integrity_risk as the epoch engine run offline on the same input (same
seed): the promise "the nodes reproduce the offline run".

The drive is long enough for the filter to settle (heading acquisition, then
``integrity_settling_s``) and say OK at some epochs and ERROR at others, so that the
verdicts are compared level against level, not ERROR against ERROR; its measurements are
open-sky-like (no NLOS), where the settled filter's protection level meets the alert
limit at some epochs.
"""
import math

import numpy as np
import pytest
import ros_harness  # noqa: F401  (first: without rclpy it skips this module, saying why)
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped, TwistWithCovarianceStamped
from sensor_msgs.msg import Image, Imu, NavSatFix, PointCloud2

import msg_adapters as ma
from gnsscam_ros.core.engine import EpochEngine, InputTiming, best_match
from gnsscam_ros.core.filter import PROPAGATED, UPDATED, FilterConfig
from gnsscam_ros.core.frames import LocalFrame
from gnsscam_ros.core.gnss import check_epoch
from gnsscam_ros.core.motion import DeadReckoningConfig, dead_reckon
from gnsscam_ros.datasets.emulated.drive import make_emulated_drive
from gnsscam_ros.evaluation.runner import engine_reports
from gnsscam_ros.nodes import gnss_node
from gnsscam_ros.nodes.camera_node import CameraNode
from gnsscam_ros.nodes.fusion_node import FusionNode, yaw_variance
from gnsscam_ros.nodes.gnss_node import GnssNode
from gnsscam_ros.nodes.imu_node import ImuNode
from gnsscam_ros.vision.synthetic import synthetic_scene
from test_nodes import overrides, quantised, small_database

# Every test here runs ROS nodes in a graph of its own.
pytestmark = pytest.mark.ros

SEED, N_PARTICLES = 7, 200


@pytest.fixture(scope='module')
def drive():
    d = make_emulated_drive(21, faults=3, bias_m=80.0, nlos=False, duration_s=60.0)
    d.gnss = [quantised(e) for e in d.gnss]
    return d


class Pipeline:
    """The four nodes in one graph, a publisher per input topic and the collected outputs."""

    def __init__(self, g, db_path, origin):
        self.g = g
        self.gnss = g.add(GnssNode(context=g.ctx))
        self.imu = g.add(ImuNode(context=g.ctx, parameter_overrides=overrides(
            source_timeout_s=60.0, input_queue_depth=1000)))
        self.cam = g.add(CameraNode(context=g.ctx, parameter_overrides=overrides(
            database_path=str(db_path), top_k=3)))
        self.fusion = g.add(FusionNode(context=g.ctx, parameter_overrides=overrides(
            n_particles=N_PARTICLES, seed=SEED, use_map_origin=True, map_origin_llh=origin,
            max_published_particles=0, gnss_timeout_s=60.0, odometry_wait_s=10.0,
            odometry_timeout_s=60.0)))
        self.pub_gnss = g.publisher(PointCloud2, 'gnss/pseudoranges')
        self.pub_imu = g.publisher(Imu, 'imu/data')
        self.pub_odo = g.publisher(TwistWithCovarianceStamped, 'odom/twist')
        self.pub_cam = g.publisher(Image, 'camera/image_raw')
        self.risks = g.collect(DiagnosticArray, 'integrity_risk')
        self.poses = g.collect(PoseWithCovarianceStamped, 'pose')
        self.clouds = g.collect(PoseArray, 'particles')
        self.fixes = g.collect(NavSatFix, 'fix')
        self.matches = g.collect(PointCloud2, 'camera/matches')
        g.connect(self.pub_gnss, self.pub_imu, self.pub_odo, self.pub_cam)
        g.spin_until(lambda: self.fusion.sub_dr.handle is not None
                     and self.imu.pub.get_subscription_count() > 0
                     and self.gnss.pub_measurements.get_subscription_count() > 0
                     and self.cam.pub.get_subscription_count() > 0,
                     what='internal connections')

    def send_motion(self, drive, events, t_k) -> None:
        """Odometry and IMU samples up to ``t_k``, each delivered before the next."""
        odo, imu_s, imu, g = drive.odometry, drive.imu, self.imu, self.g
        while events and events[0][0] <= t_k:
            stamp, kind, k = events.pop(0)
            if kind == 0:
                n = imu.stats.get('received_odom_twist')
                self.pub_odo.publish(ma.sample_to_twist(ma.TwistSample(
                    stamp, odo.speed_mps[k], odo.yaw_rate_rps[k], odo.speed_var[k],
                    odo.yaw_rate_var[k])))
                g.spin_until(lambda: imu.stats.get('received_odom_twist') > n)
            else:
                n = imu.stats.get('received_imu')
                self.pub_imu.publish(ma.sample_to_imu(ma.ImuSample(
                    stamp, imu_s.accel_mps2[k], imu_s.gyro_rps[k])))
                g.spin_until(lambda: imu.stats.get('received_imu') > n)

    def send_image(self, image, stamp_ns) -> None:
        n = self.fusion.stats.get('received_matches')
        self.pub_cam.publish(ma.array_to_image(image, stamp_ns))
        self.g.spin_until(lambda: self.fusion.stats.get('received_matches') > n,
                          what='matches')

    def run_epoch(self, epoch) -> str:
        """Publish one GNSS epoch once the dead reckoning reached it; wait for its outputs."""
        g, fusion, t_k = self.g, self.fusion, epoch.stamp_ns
        g.spin_until(lambda: (fusion.engine.motion.newest_stamp_ns or -1) >= t_k,
                     what='dead reckoning at the epoch')
        self.pub_gnss.publish(ma.gnss_epoch_to_pointcloud2(epoch))
        g.spin_until(lambda: fusion.last_result is not None
                     and fusion.last_result.stamp_ns == t_k, what='the filter epoch')
        status = fusion.last_result.status
        n_est = 1 if status in (UPDATED, PROPAGATED) else 0

        def stamped(msgs) -> int:
            return sum(ma.stamp_to_ns(m.header.stamp) == t_k for m in msgs)

        g.spin_until(lambda: sum(ma.parse_integrity_risk(m).epoch_stamp_ns == t_k
                                 for m in self.risks) == 1
                     and stamped(self.poses) == n_est and stamped(self.clouds) == n_est
                     and stamped(self.fixes) == int(status == UPDATED),
                     what='outputs of the epoch')
        return status


def offline_run(drive, frame, matches):
    """The epoch engine offline on the same input and seed: (result, particles, yaw var)
    of every epoch."""
    engine = EpochEngine(FilterConfig(n_particles=N_PARTICLES), frame=frame,
                         rng=np.random.default_rng(SEED),
                         timing=InputTiming(gnss_queue_size=None))
    states = dead_reckon(drive.imu, drive.odometry, DeadReckoningConfig())
    camera = []
    for i, m in enumerate(matches):
        parsed = ma.pointcloud2_to_matches(m)
        camera.append(best_match(parsed.stamp_ns, parsed.position_m, parsed.score, i))
    gd = gnss_node.DEFAULTS
    checked = [epoch.subset(check_epoch(epoch, gd['min_satellites'], gd['elevation_mask_deg'],
                                        gd['cn0_mask_dbhz']).keep) for epoch in drive.gnss]
    return [(report.result, report.verdict, report.cloud.particles.copy(),
             yaw_variance(report.cloud.particles[:, 3], report.cloud.log_w))
            for report in engine_reports(engine, checked, states, camera)]


def check_outputs_equal(pipe, offline, results, frame) -> dict:
    """Every published output of the nodes equals the offline epoch's; the number of
    epochs of each integrity level compared."""
    assert len(offline) == len(results), (len(offline), len(results))
    levels = {ma.OK: 0, ma.ERROR: 0, ma.STALE: 0}
    by_stamp = {}
    for m in pipe.risks:
        risk = ma.parse_integrity_risk(m)
        by_stamp[risk.epoch_stamp_ns] = risk
    pose_by = {ma.stamp_to_ns(m.header.stamp): ma.msg_to_pose(m) for m in pipe.poses}
    cloud_by = {ma.stamp_to_ns(m.header.stamp): ma.posearray_to_particles(m)
                for m in pipe.clouds}
    fix_by = {ma.stamp_to_ns(m.header.stamp): ma.navsatfix_to_fix(m) for m in pipe.fixes}
    for (r, verdict, particles, yaw_var), status in zip(offline, results):
        assert r.status == status
        risk = by_stamp[r.stamp_ns]
        levels[risk.level] += 1
        if r.status != UPDATED:
            assert risk.level == ma.STALE and math.isnan(risk.risk_bound)
            continue
        assert risk.level == (ma.OK if verdict.ok else ma.ERROR)
        np.testing.assert_allclose(
            [risk.risk_bound, risk.empirical_risk, risk.divergence_risk],
            [r.risk.risk_bound[0], r.risk.empirical_risk[0], r.risk.divergence_risk[0]],
            rtol=1e-9, atol=1e-12)
        assert risk.alert_limit_m == 8.0 and risk.target_risk == 0.1
        pose = pose_by[r.stamp_ns]
        np.testing.assert_allclose(pose.position_m, r.position_enu_m, rtol=0, atol=1e-9)
        np.testing.assert_allclose(pose.position_covariance_m2, r.covariance_m2, rtol=1e-9,
                                   atol=1e-9)
        assert pose.yaw_rad == pytest.approx(r.yaw_rad, abs=1e-9)
        assert pose.covariance[5, 5] == pytest.approx(yaw_var, rel=1e-9)
        cloud = cloud_by[r.stamp_ns]
        assert cloud.shape == particles.shape
        np.testing.assert_allclose(cloud[:, :3], particles[:, :3], rtol=0, atol=1e-9)
        dyaw = np.angle(np.exp(1j * (cloud[:, 3] - particles[:, 3])))
        assert np.abs(dyaw).max() < 1e-9
        lat, lon, alt = frame.enu_to_geodetic(r.position_enu_m)
        fix = fix_by[r.stamp_ns]
        assert (fix.lat_deg, fix.lon_deg) == pytest.approx((lat, lon), abs=1e-12)
    return levels


@pytest.mark.slow
def test_nodes_equal_offline_core_run(graph, drive, tmp_path):
    origin = list(drive.origin_llh)
    frame = LocalFrame(*origin)
    truth_enu = frame.ecef_to_enu(drive.truth.ecef_m)
    epochs = drive.gnss
    # Camera: images just before epochs 48..52 (settled), database geotagged at the truth.
    cam_stamps = [epochs[k].stamp_ns - 400_000_000 for k in range(48, 53)]
    cam_pos = [[np.interp(t, drive.truth.stamp_ns, truth_enu[:, j]) for j in range(3)]
               for t in cam_stamps]
    images = [synthetic_scene(i, seed=5) for i in range(len(cam_stamps))]
    db_path = tmp_path / 'map.npz'
    small_database(images, cam_pos).save(db_path)
    pipe = Pipeline(graph, db_path, origin)

    events = sorted([(int(t), 0, k) for k, t in enumerate(drive.odometry.stamp_ns)]
                    + [(int(t), 1, k) for k, t in enumerate(drive.imu.stamp_ns)])
    sent_images, results = 0, []
    for epoch in epochs:
        # Inputs in stamp order, each delivered before the next (as a live system would).
        pipe.send_motion(drive, events, epoch.stamp_ns)
        while sent_images < len(cam_stamps) and cam_stamps[sent_images] <= epoch.stamp_ns:
            pipe.send_image(images[sent_images], cam_stamps[sent_images])
            sent_images += 1
        results.append(pipe.run_epoch(epoch))
    assert results.count(UPDATED) >= len(epochs) - 1, results
    assert len(pipe.matches) == len(cam_stamps) and not pipe.cam.stats.rejected
    assert [ma.pointcloud2_to_matches(m).image_id[0] for m in pipe.matches] == list(
        range(len(cam_stamps)))                    # each image finds itself first

    offline = offline_run(drive, frame, pipe.matches)
    assert any(r.camera_alpha is not None for r, _, _, _ in offline), \
        'the camera matches reached the filter'
    levels = check_outputs_equal(pipe, offline, results, frame)
    # Both verdicts occurred, and were compared: OK (settled, PL within the alert limit)
    # and ERROR (settling, or the PL above it).
    assert levels[ma.OK] >= 1 and levels[ma.ERROR] >= 1, (
        levels, sorted({r.integrity_reason.split(' (')[0] for r, _, _ in offline}))
    values = pipe.fusion.stats.values()
    assert values['processing_count'] == len(epochs) and values['rejected_total'] == 0
