"""Motion loss and dead-reckoning resets are integrity events: the nodes (issue 10, item 4).

The offline version is test_motion_integrity.py; here the same faults go through the real
graph in-process (gnss_node + imu_node + fusion_node, DDS between them): the test publishes
raw ``gnss/pseudoranges``, ``imu/data`` and ``odom/twist`` of an emulated drive in stamp
order, each message delivered before the next, and reads ``integrity_risk``, ``pose`` and
``diagnostics``.

* IMU and odometry stop for 20 s of drive time while GNSS continues: every verdict of the
  gap is ERROR with 'motion unknown' (or STALE), the protection level is finite and grows,
  fusion_node's diagnostics warn about the dead reckoning;
* imu_node destroyed and started again mid-drive (its dead reckoning begins again at the
  odom origin): fusion_node counts one reset, the epoch whose interval holds it is ERROR
  with 'motion unknown', and the jump back to the origin is not integrated;
* in both runs no verdict is OK with a horizontal error above its protection level, and
  OK verdicts do occur before the fault (settling time shortened, alert limit 25 m).

Everything the assertions read is a function of the inputs and the seed: an epoch is only
published once the dead reckoning has reached it (or, in the gap, once fusion_node has
given up waiting), so the filter sees the same motion whatever the wall-clock timing.
"""
import math

import numpy as np
import pytest
from ros_harness import RosGraph  # skips this module without rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped, TwistWithCovarianceStamped
from sensor_msgs.msg import Imu, PointCloud2
from test_nodes import overrides

import msg_adapters as ma
from gnsscam_ros.core.filter import PROPAGATED, UPDATED
from gnsscam_ros.core.frames import LocalFrame
from gnsscam_ros.core.motion import dead_reckon
from gnsscam_ros.datasets.emulated.drive import make_emulated_drive
from gnsscam_ros.nodes.fusion_node import FusionNode
from gnsscam_ros.nodes.gnss_node import GnssNode
from gnsscam_ros.nodes.imu_node import ImuNode

# Every test here runs ROS nodes in a graph of its own.
pytestmark = pytest.mark.ros

S = 1_000_000_000
DURATION_S = 90.0
# Seed 3 starts slowly and waits at a light: the heading is acquired (100 m) at ~38 s and
# integrity settled from ~49 s.
GAP_S = (55.0, 75.0)        # dead reckoning lost, drive time after the first epoch
RESTART_S = 52.0            # imu_node restarted, drive time after the first epoch
IMU_PARAMS = dict(source_timeout_s=120.0, input_queue_depth=1000)


@pytest.fixture(scope='module')
def drive():
    return make_emulated_drive(3, duration_s=DURATION_S)


@pytest.fixture
def graph():
    g = RosGraph()
    yield g
    g.close()


def fusion_params(drive, **extra):
    """Small and quick, and able to certify before the fault: 300 particles, integrity
    settled 10 s after heading acquisition, alert limit 25 m."""
    return overrides(
        n_particles=300, acquisition_particles=3000, seed=11, use_map_origin=True,
        map_origin_llh=[float(v) for v in drive.origin_llh], alert_limit_m=25.0,
        integrity_settling_s=10.0, max_published_particles=10, gnss_timeout_s=60.0,
        odometry_wait_s=10.0, odometry_timeout_s=0.5, **extra)


class DriveRun:
    """Publishes a drive into the graph in stamp order and collects the outputs."""

    def __init__(self, g: RosGraph, drive):
        self.g, self.drive = g, drive
        self.gnss = g.add(GnssNode(context=g.ctx))
        self.imu = g.add(ImuNode(context=g.ctx, parameter_overrides=overrides(**IMU_PARAMS)))
        self.fusion = g.add(FusionNode(context=g.ctx, parameter_overrides=fusion_params(drive)))
        self.pub_gnss = g.publisher(PointCloud2, 'gnss/pseudoranges')
        self.pub_imu = g.publisher(Imu, 'imu/data')
        self.pub_odo = g.publisher(TwistWithCovarianceStamped, 'odom/twist')
        self.risks = g.collect(DiagnosticArray, 'integrity_risk')
        self.poses = g.collect(PoseWithCovarianceStamped, 'pose')
        self.diagnostics = g.collect(DiagnosticArray, 'diagnostics')
        g.connect(self.pub_gnss, self.pub_imu, self.pub_odo)
        self.wait_internal_links()
        odo, imu = drive.odometry, drive.imu
        self.events = sorted([(int(t), 0, k) for k, t in enumerate(odo.stamp_ns)]
                             + [(int(t), 1, k) for k, t in enumerate(imu.stamp_ns)])
        self.next_event = 0
        self.start_ns = drive.gnss[0].stamp_ns

    def wait_internal_links(self):
        self.g.spin_until(lambda: self.imu.pub.get_subscription_count() > 0
                          and self.fusion.sub_dr.get_publisher_count() > 0
                          and self.gnss.pub_measurements.get_subscription_count() > 0,
                          what='internal connections')

    def feed_until(self, stamp_ns, skip=lambda t: False, before=False):
        """Publish IMU and odometry samples up to ``stamp_ns`` (inclusive; exclusive with
        ``before``), each received before the next; ``skip(stamp)`` ones are lost."""
        odo, imu = self.drive.odometry, self.drive.imu
        g = self.g
        while self.next_event < len(self.events):
            stamp, kind, k = self.events[self.next_event]
            if stamp > stamp_ns or (before and stamp == stamp_ns):
                break
            self.next_event += 1
            if skip(stamp - self.start_ns):
                continue
            node = self.imu
            if kind == 0:
                n = node.stats.get('received_odom_twist')
                self.pub_odo.publish(ma.sample_to_twist(ma.TwistSample(
                    stamp, odo.speed_mps[k], odo.yaw_rate_rps[k], odo.speed_var[k],
                    odo.yaw_rate_var[k])))
                g.spin_until(lambda: node.stats.get('received_odom_twist') > n, what='odom')
            else:
                n = node.stats.get('received_imu')
                self.pub_imu.publish(ma.sample_to_imu(ma.ImuSample(
                    stamp, imu.accel_mps2[k], imu.gyro_rps[k])))
                g.spin_until(lambda: node.stats.get('received_imu') > n, what='imu')

    def wait_dead_reckoning_delivered(self):
        """Every state imu_node published has reached fusion_node."""
        self.g.spin_until(lambda: self.fusion.stats.get('received_dead_reckoning')
                          >= self.sent_states + self.imu.stats.get('published_dead_reckoning'),
                          what='dead reckoning delivered')

    sent_states = 0            # states published by imu_nodes destroyed before this one

    def epoch(self, epoch, covered=True):
        """Publish one GNSS epoch and wait for its integrity_risk (and pose)."""
        t_k = epoch.stamp_ns
        if covered:
            self.g.spin_until(lambda: (self.fusion.engine.motion.newest_stamp_ns or -1) >= t_k,
                              what='dead reckoning at the epoch')
        else:
            self.wait_dead_reckoning_delivered()
        self.pub_gnss.publish(ma.gnss_epoch_to_pointcloud2(epoch))
        self.g.spin_until(lambda: self.fusion.last_result is not None
                          and self.fusion.last_result.stamp_ns == t_k, what='the filter epoch')
        # integrity_risk is published before pose: wait for the pose of an estimate.
        pose = self.fusion.last_result.status in (UPDATED, PROPAGATED)
        self.g.spin_until(lambda: any(ma.parse_integrity_risk(m).epoch_stamp_ns == t_k
                                      for m in self.risks[-3:])
                          and (not pose or any(ma.stamp_to_ns(m.header.stamp) == t_k
                                               for m in self.poses[-3:])),
                          what='the outputs of the epoch')
        return self.fusion.last_result

    def diagnostic_now(self):
        """fusion_node's status, published now and read back from ``diagnostics``."""
        n = len(self.diagnostics)
        self.fusion.publish_diagnostics()

        def mine():
            return [s for m in self.diagnostics[n:] for s in m.status
                    if s.name == 'fusion_node: status']
        self.g.spin_until(lambda: mine(), what='fusion_node diagnostics')
        status = mine()[0]
        return ma.level_to_int(status.level), status.message, ma.status_values(status)

    def verdicts(self):
        """``{epoch stamp: IntegrityRisk}`` of every epoch verdict, and the horizontal
        error of each pose against the truth."""
        risks = {}
        for m in self.risks:
            r = ma.parse_integrity_risk(m)
            if r.epoch_stamp_ns is not None and r.epoch_status is not None:
                assert r.epoch_stamp_ns not in risks, 'one verdict per epoch'
                risks[r.epoch_stamp_ns] = r
        frame = LocalFrame(*self.drive.origin_llh)
        truth = frame.ecef_to_enu(self.drive.truth.ecef_m)
        error = {}
        for m in self.poses:
            t = ma.stamp_to_ns(m.header.stamp)
            p = ma.msg_to_pose(m).position_m
            true = [np.interp(t, self.drive.truth.stamp_ns, truth[:, j]) for j in (0, 1)]
            error[t] = float(np.hypot(p[0] - true[0], p[1] - true[1]))
        return risks, error


def check_never_ok_beyond_the_level(risks, error):
    """No OK verdict with the error above its protection level; OK and ERROR carry a
    finite level. Returns the stamps of the OK verdicts."""
    ok = []
    for t, r in risks.items():
        if r.level in (ma.OK, ma.ERROR):
            assert r.protection_level_m is not None and math.isfinite(r.protection_level_m), r
        if r.level == ma.OK:
            ok.append(t)
            assert error[t] <= r.protection_level_m, (t, error[t], r.protection_level_m)
    return sorted(ok)


@pytest.mark.slow
def test_dead_reckoning_lost_mid_drive(graph, drive):
    run = DriveRun(graph, drive)
    lost = lambda dt_ns: GAP_S[0] * S < dt_ns < GAP_S[1] * S      # noqa: E731
    gap_levels = []
    warned = []
    for epoch in drive.gnss:
        t = epoch.stamp_ns - run.start_ns
        run.feed_until(epoch.stamp_ns, skip=lost)
        in_gap = GAP_S[0] * S < t <= GAP_S[1] * S
        run.epoch(epoch, covered=not in_gap)
        if in_gap:
            gap_levels.append(run.fusion.last_result.protection_level_m)
            if t in (int((GAP_S[0] + 2) * S), int(GAP_S[1] * S)):
                warned.append(run.diagnostic_now())
    risks, error = run.verdicts()
    assert len(risks) == len(drive.gnss)
    ok = check_never_ok_beyond_the_level(risks, error)
    # Meaningful: the filter certified before the dead reckoning was lost.
    assert any(t - run.start_ns <= GAP_S[0] * S for t in ok), 'no OK before the gap'
    gap = {t: r for t, r in risks.items() if GAP_S[0] * S < t - run.start_ns <= GAP_S[1] * S}
    assert len(gap) == 20
    for t, r in gap.items():
        assert r.level == ma.STALE or (r.level == ma.ERROR and 'motion unknown' in r.message
                                       and float(r.extra['motion_unknown_s']) > 0), r
    # The level grows with the gap (a vehicle at up to max_speed_mps whose heading is
    # lost); GNSS keeps it from growing without bound, so not every epoch is above the last.
    before = risks[max(t for t in risks if t - run.start_ns <= GAP_S[0] * S)]
    levels = [r.protection_level_m for _, r in sorted(gap.items()) if r.level == ma.ERROR]
    assert len(levels) >= 15
    assert all(pl > 2.0 * before.protection_level_m for pl in levels), (before, levels)
    assert levels[-1] > 3.0 * before.protection_level_m
    # fusion_node's diagnostics say so while it lasts.
    assert len(warned) == 2
    for level, message, values in warned:
        assert level == ma.WARN and 'dead reckoning' in message, message
        assert float(values['motion_unknown_s']) > 0
    # After the gap the dead reckoning is back: the epochs have known motion again.
    assert float(risks[drive.gnss[-1].stamp_ns].extra['motion_unknown_s']) == 0.0


@pytest.mark.slow
def test_imu_node_restarted_mid_drive(graph, drive):
    run = DriveRun(graph, drive)
    g = graph
    restart_ns = run.start_ns + int(RESTART_S * S)
    assert restart_ns in {e.stamp_ns for e in drive.gnss}
    before = [s for s in dead_reckon(drive.imu, drive.odometry) if s.stamp_ns < restart_ns]
    travelled_m = math.hypot(before[-1].x_m, before[-1].y_m)
    assert travelled_m > 120.0        # where the old dead reckoning had got to
    restarted = None
    for epoch in drive.gnss:
        if restarted is None and epoch.stamp_ns >= restart_ns:
            # Everything before the restart reaches the old imu_node and fusion_node ...
            run.feed_until(restart_ns, before=True)
            run.wait_dead_reckoning_delivered()
            assert run.fusion.engine.motion.newest_stamp_ns == restart_ns - S // 10
            # ... then it is killed and a new one starts: the same topics, a fresh
            # dead reckoning at the odom origin.
            old = run.imu
            run.sent_states += old.stats.get('published_dead_reckoning')
            g.executor.remove_node(old)
            g.nodes.remove(old)
            old.destroy_node()
            g.spin_until(lambda: run.pub_imu.get_subscription_count() == 0
                         and run.pub_odo.get_subscription_count() == 0, what='old imu gone')
            run.imu = g.add(ImuNode(context=g.ctx,
                                    parameter_overrides=overrides(**IMU_PARAMS)))
            g.connect(run.pub_imu, run.pub_odo)
            run.wait_internal_links()
            restarted = epoch.stamp_ns
        run.feed_until(epoch.stamp_ns)
        run.epoch(epoch)
        if epoch.stamp_ns == restarted:
            warned = run.diagnostic_now()
    assert restarted == restart_ns
    assert run.fusion.engine.motion.resets == 1
    assert run.fusion.stats.get('dead_reckoning_resets') == 1
    level, message, values = warned
    assert level == ma.WARN and 'dead reckoning' in message, message
    assert values['dead_reckoning_resets'] == '1'
    assert float(values['motion_unknown_s']) > 0

    risks, error = run.verdicts()
    assert len(risks) == len(drive.gnss)
    ok = check_never_ok_beyond_the_level(risks, error)
    assert any(t < restart_ns for t in ok), 'no OK before the restart'
    # The epoch whose interval holds the restart: motion unknown (0.1 s), never OK.
    at = risks[restart_ns]
    assert at.level == ma.ERROR and 'motion unknown' in at.message, at
    assert float(at.extra['motion_unknown_s']) == pytest.approx(0.1)
    assert at.extra['dead_reckoning_resets'] == '1'
    # After it the motion is known again (a 0.1 s gap does not lose the heading, so the
    # filter does not settle again) ...
    after = [r for t, r in sorted(risks.items()) if restart_ns < t <= restart_ns + 10 * S]
    assert after and all(float(r.extra['motion_unknown_s']) == 0.0 for r in after)
    # ... and the jump back to the origin was not integrated: the error stays small,
    # far below the distance from the odom origin.
    assert max(error.values()) < min(30.0, travelled_m / 4)
