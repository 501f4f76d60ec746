"""msg_adapters: round trips and malformed-input errors, without a running ROS graph."""
import math

import numpy as np
import pytest
from ros_harness import deserialize_message, serialize_message  # skips without rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from sensor_msgs.msg import Image, NavSatFix, PointCloud2, PointField

import msg_adapters as ma
from gnsscam_ros.core.motion import DeadReckoningState
from gnsscam_ros.core.types import GnssEpoch
from gnsscam_ros.core.verdict import ERROR, OK, STALE, IntegrityVerdict

STAMP = 1_718_204_613_123_456_789


def _epoch(k=6, seed=0):
    rng = np.random.default_rng(seed)
    # Satellites at GPS orbit radii in random directions (the parsers refuse others).
    direction = rng.normal(0, 1, (k, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    return GnssEpoch(
        stamp_ns=STAMP, sv_pos_ecef_m=direction * rng.uniform(2.55e7, 2.7e7, (k, 1)),
        pr_m=rng.uniform(2e7, 2.5e7, k),
        var_m2=np.float32(rng.uniform(5, 20, k)).astype(float),
        sv_id=np.arange(1, k + 1), system=np.array([1, 4] * (k // 2) + [1] * (k % 2)),
        elevation_deg=np.float32(rng.uniform(5, 90, k)).astype(float),
        cn0_dbhz=np.float32(rng.uniform(25, 50, k)).astype(float))


def _assert_epoch_equal(a: GnssEpoch, b: GnssEpoch):
    assert a.stamp_ns == b.stamp_ns
    for name in ('sv_pos_ecef_m', 'pr_m', 'var_m2', 'sv_id', 'system', 'elevation_deg',
                 'cn0_dbhz'):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


# ------------------------------------------------------------------------- stamps
def test_stamps_round_trip_and_range():
    for ns in (0, 1, STAMP, (2 ** 31 - 1) * 10 ** 9 + 999_999_999):
        assert ma.stamp_to_ns(ma.ns_to_stamp(ns)) == ns
    with pytest.raises(ma.MessageError) as err:
        ma.ns_to_stamp(-1)
    assert err.value.reason == 'stamp'
    with pytest.raises(ValueError):                   # a MessageError is a ValueError
        ma.wire.split_ns(2 ** 31 * 10 ** 9)
    assert ma.wire.join_ns(*ma.wire.split_ns(STAMP + 7)) == STAMP + 7


def test_header_stamp_of_serialised_messages():
    raw = serialize_message(ma.sample_to_imu(ma.ImuSample(STAMP + 5, np.zeros(3), np.ones(3))))
    assert ma.header_stamp_ns(raw) == STAMP + 5
    with pytest.raises(ma.MessageError):
        ma.header_stamp_ns(b'\x00\x01\x00')


# --------------------------------------------------------------------------- wire
def test_wire_tie_order_is_the_dead_reckonings_rule():
    from gnsscam_ros.core import motion
    sources = {ma.wire.TWIST: motion.ODOMETRY, ma.wire.IMU: motion.IMU}
    dr = [sources[t] for t in ma.wire.TIE_ORDER if t in sources]
    assert tuple(dr) == motion.DR_SOURCES
    assert ma.wire.TIE_ORDER[-2:] == (ma.wire.IMAGE, ma.wire.GNSS)   # after the motion
    assert ma.service_bits([1, 2, 4, 8, 16, 32, 1]) == 1 | 2 | 4 | 8
    assert ma.service_bits([]) == 0


# --------------------------------------------------------------------- PointCloud2
def test_gnss_cloud_round_trip_is_exact_for_float32_fields():
    epoch = _epoch()
    msg = ma.gnss_epoch_to_pointcloud2(epoch)
    assert msg.header.frame_id == 'earth' and msg.width == 6 and msg.point_step == 48
    assert [f.name for f in msg.fields] == list(ma.GNSS_DTYPE.names)
    _assert_epoch_equal(ma.pointcloud2_to_gnss_epoch(msg), epoch)


def test_gnss_cloud_passes_nan_through_for_the_core_checks():
    epoch = _epoch()
    pr = epoch.pr_m.copy()
    pr[2] = np.nan
    bad = GnssEpoch(**{**epoch.__dict__, 'pr_m': pr})
    back = ma.pointcloud2_to_gnss_epoch(ma.gnss_epoch_to_pointcloud2(bad))
    assert np.isnan(back.pr_m[2]) and np.isfinite(np.delete(back.pr_m, 2)).all()


def test_gnss_cloud_empty():
    epoch = _epoch().subset(np.zeros(6, bool))
    back = ma.pointcloud2_to_gnss_epoch(ma.gnss_epoch_to_pointcloud2(epoch))
    assert back.n_sv == 0 and back.sv_pos_ecef_m.shape == (0, 3)


def _manual_cloud(points: np.ndarray, big_endian=False, height=1, pad=0, frame='earth'):
    """A cloud written by someone else: other field order, padding, byte order, rows."""
    dtype = points.dtype
    fields = []
    types = {np.dtype('f8'): PointField.FLOAT64, np.dtype('f4'): PointField.FLOAT32,
             np.dtype('u2'): PointField.UINT16, np.dtype('u1'): PointField.UINT8}
    for name in reversed(dtype.names):
        base = np.dtype(dtype.fields[name][0].type)
        fields.append(PointField(name=name, offset=dtype.fields[name][1],
                                 datatype=types[base], count=1))
    data = points.astype(dtype.newbyteorder('>') if big_endian else dtype)
    width = points.size // height
    rows = data.tobytes()
    step = dtype.itemsize * width
    raw = b''.join(rows[r * step:(r + 1) * step] + b'\0' * pad for r in range(height))
    msg = PointCloud2(height=height, width=width, fields=fields, is_bigendian=big_endian,
                      point_step=dtype.itemsize, row_step=step + pad, is_dense=True)
    msg.header.frame_id = frame
    msg.header.stamp = ma.ns_to_stamp(STAMP)
    msg.data = raw
    return msg


@pytest.mark.parametrize('big_endian,height,pad', [(False, 1, 0), (True, 1, 0),
                                                   (False, 2, 8), (True, 3, 4)])
def test_gnss_cloud_reader_handles_foreign_layouts(big_endian, height, pad):
    epoch = _epoch()
    ours = ma.gnss_epoch_to_pointcloud2(epoch)
    points = np.frombuffer(bytes(ours.data), dtype=ma.GNSS_DTYPE)
    msg = _manual_cloud(points, big_endian, height, pad)
    _assert_epoch_equal(ma.pointcloud2_to_gnss_epoch(msg), epoch)


def test_gnss_cloud_extra_fields_are_ignored():
    extra = np.dtype({'names': [*ma.GNSS_DTYPE.names, 'snr_extra'],
                      'formats': [ma.GNSS_DTYPE.fields[n][0] for n in ma.GNSS_DTYPE.names]
                      + ['<f8'], 'offsets': [ma.GNSS_DTYPE.fields[n][1]
                                             for n in ma.GNSS_DTYPE.names] + [48],
                      'itemsize': 56})
    pts = np.zeros(3, extra)
    pts['pseudorange'] = [1.0, 2.0, 3.0]
    pts['system'] = 1
    msg = ma.structured_to_pointcloud2(pts, STAMP, 'earth')
    np.testing.assert_array_equal(ma.pointcloud2_to_gnss_epoch(msg).pr_m, [1, 2, 3])


def _cloud_with(field_edit):
    msg = ma.gnss_epoch_to_pointcloud2(_epoch())
    field_edit(msg)
    return msg


@pytest.mark.parametrize('edit,reason,text', [
    (lambda m: m.fields.pop(3), 'fields', "'pseudorange' missing"),
    (lambda m: setattr(m.fields[4], 'datatype', PointField.FLOAT64), 'fields',
     "'variance' is FLOAT64"),
    (lambda m: setattr(m.fields[7], 'count', 2), 'fields', "'sv_id' is UINT16 x2"),
    (lambda m: setattr(m.header, 'frame_id', 'map'), 'frame', "frame 'map'"),
    (lambda m: setattr(m, 'data', bytes(m.data)[:-1]), 'size', 'data bytes'),
    (lambda m: setattr(m, 'row_step', 3), 'size', 'row_step'),
    (lambda m: setattr(m.fields[0], 'offset', 45), 'size', 'overruns'),
])
def test_gnss_cloud_malformed_is_refused_with_reason(edit, reason, text):
    with pytest.raises(ma.MessageError) as err:
        ma.pointcloud2_to_gnss_epoch(_cloud_with(edit))
    assert err.value.reason == reason and text in str(err.value)
    assert isinstance(err.value, ValueError)


def test_matches_round_trip_and_errors():
    m = ma.CameraMatches(stamp_ns=STAMP, position_m=np.array([[1.5, -2.25, 0.5],
                                                              [10.0, 20.0, 0.0]]),
                         score=np.array([0.75, 0.25]), image_id=np.array([7, 3]))
    back = ma.pointcloud2_to_matches(ma.matches_to_pointcloud2(m))
    np.testing.assert_array_equal(back.position_m, m.position_m)
    np.testing.assert_array_equal(back.score, m.score)
    np.testing.assert_array_equal(back.image_id, m.image_id)
    assert back.stamp_ns == STAMP and back.frame_id == 'map' and len(back) == 2
    empty = ma.CameraMatches(STAMP, np.zeros((0, 3)), np.zeros(0), np.zeros(0, int))
    assert len(ma.pointcloud2_to_matches(ma.matches_to_pointcloud2(empty))) == 0
    with pytest.raises(ma.MessageError):
        ma.matches_to_pointcloud2(ma.CameraMatches(STAMP, np.array([[np.nan, 0, 0]]),
                                                   np.array([0.5]), np.array([1])))
    bad = ma.matches_to_pointcloud2(m)
    raw = np.frombuffer(bytes(bad.data), ma.MATCH_DTYPE).copy()
    raw['x'][1] = np.inf
    bad.data = raw.tobytes()
    with pytest.raises(ma.MessageError) as err:
        ma.pointcloud2_to_matches(bad)
    assert err.value.reason == 'non_finite'
    with pytest.raises(ma.MessageError) as err:      # a GNSS cloud is not a match cloud
        ma.pointcloud2_to_matches(ma.gnss_epoch_to_pointcloud2(_epoch()), frame_id=None)
    assert err.value.reason == 'fields'


# ---------------------------------------------------------------------------- Image
@pytest.mark.parametrize('encoding,shape', [('mono8', (64, 65)), ('bgr8', (64, 65, 3)),
                                            ('rgb8', (67, 64, 3))])
def test_image_round_trip(encoding, shape):
    arr = np.random.default_rng(1).integers(0, 256, shape, dtype=np.uint8)
    msg = ma.array_to_image(arr, STAMP, encoding)
    assert isinstance(msg, Image) and msg.step == shape[1] * (1 if len(shape) == 2 else 3)
    back, enc = ma.image_to_array(msg)
    assert enc == encoding
    np.testing.assert_array_equal(back, arr)


def test_image_with_padded_rows():
    arr = (np.arange(64 * 65) % 251).astype(np.uint8).reshape(64, 65)
    msg = Image(height=64, width=65, encoding='mono8', step=68)
    msg.data = np.pad(arr, ((0, 0), (0, 3))).tobytes()
    np.testing.assert_array_equal(ma.image_to_array(msg)[0], arr)


@pytest.mark.parametrize('kwargs,reason', [
    (dict(height=0, width=0, encoding='bgr8', step=0, data=b''), 'empty'),
    (dict(height=2, width=2, encoding='16UC1', step=4, data=bytes(8)), 'encoding'),
    (dict(height=2, width=2, encoding='bayer_rggb8', step=2, data=bytes(4)), 'encoding'),
    (dict(height=64, width=64, encoding='bgr8', step=192, data=bytes(64 * 192 - 1)), 'size'),
    (dict(height=64, width=64, encoding='bgr8', step=128, data=bytes(64 * 128)), 'size'),
])
def test_image_malformed_is_refused(kwargs, reason):
    data = kwargs.pop('data')
    msg = Image(**kwargs)
    msg.data = data
    with pytest.raises(ma.MessageError) as err:
        ma.image_to_array(msg)
    assert err.value.reason == reason


def test_array_to_image_refuses_wrong_arrays():
    with pytest.raises(ma.MessageError):
        ma.array_to_image(np.zeros((2, 2), np.float32), STAMP)
    with pytest.raises(ma.MessageError):
        ma.array_to_image(np.zeros((2, 2, 3), np.uint8), STAMP, 'mono8')
    with pytest.raises(ma.MessageError):
        ma.array_to_image(np.zeros((0, 2), np.uint8), STAMP)


# ------------------------------------------------------------- pose, particles, fix
def test_pose_round_trip():
    cov3 = np.array([[4.0, 0.5, 0.1], [0.5, 3.0, 0.2], [0.1, 0.2, 9.0]])
    est = ma.PoseEstimate(STAMP, np.array([12.5, -3.25, 1.0]), 2.5,
                          ma.pose_covariance(cov3, 0.04))
    back = ma.msg_to_pose(ma.pose_to_msg(est))
    np.testing.assert_array_equal(back.position_m, est.position_m)
    np.testing.assert_array_equal(back.covariance, est.covariance)
    np.testing.assert_array_equal(back.position_covariance_m2, cov3)
    assert back.yaw_rad == pytest.approx(2.5, abs=1e-15) and back.frame_id == 'map'
    with pytest.raises(ma.MessageError):
        ma.pose_to_msg(ma.PoseEstimate(STAMP, np.array([np.nan, 0, 0]), 0.0, np.eye(6)))


def test_quaternion_yaw_wraps_and_refuses_nan():
    for yaw in (-3.1, -1.0, 0.0, 0.5, 3.1):
        assert ma.quaternion_to_yaw(ma.yaw_to_quaternion(yaw)) == pytest.approx(yaw, abs=1e-14)
    assert ma.quaternion_to_yaw(ma.yaw_to_quaternion(2 * np.pi + 0.25)) == pytest.approx(0.25)
    q = ma.yaw_to_quaternion(0.0)
    q.w = math.nan
    with pytest.raises(ma.MessageError):
        ma.quaternion_to_yaw(q)


def test_particles_round_trip():
    rng = np.random.default_rng(3)
    p = np.column_stack([rng.normal(0, 50, (100, 3)), rng.uniform(-np.pi, np.pi, 100)])
    msg = ma.particles_to_posearray(p, STAMP)
    assert len(msg.poses) == 100 and msg.header.frame_id == 'map'
    back = ma.posearray_to_particles(msg)
    np.testing.assert_array_equal(back[:, :3], p[:, :3])
    np.testing.assert_allclose(back[:, 3], p[:, 3], atol=1e-14)


@pytest.mark.parametrize('frame_id, n', [('map', 100), ('a', 0), ('odom_frame', 7)])
def test_particles_cdr_is_what_rclpy_serialises(frame_id, n):
    """The numpy-written PoseArray bytes are the message built pose by pose, as rclpy reads
    them (frame names of every length modulo the alignment, an empty set; padding bytes
    are unspecified in CDR, so the bytes themselves are not compared)."""
    from geometry_msgs.msg import Pose, PoseArray
    from std_msgs.msg import Header
    rng = np.random.default_rng(n)
    p = np.column_stack([rng.normal(0, 50, (n, 3)), rng.uniform(-np.pi, np.pi, n)])
    reference = PoseArray(header=Header(stamp=ma.ns_to_stamp(STAMP), frame_id=frame_id))
    for x, y, z, yaw in p:
        pose = Pose()
        pose.position.x, pose.position.y, pose.position.z = x, y, z
        pose.orientation.z, pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
        reference.poses.append(pose)
    data = ma.particles_to_posearray_cdr(p, STAMP, frame_id)
    decoded = deserialize_message(data, PoseArray)
    assert decoded.header == reference.header and len(decoded.poses) == n

    def rows(msg):
        return np.array([[q.position.x, q.position.y, q.position.z, q.orientation.x,
                          q.orientation.y, q.orientation.z, q.orientation.w]
                         for q in msg.poses]).reshape(-1, 7)

    np.testing.assert_array_equal(rows(decoded)[:, :5], rows(reference)[:, :5])
    # The quaternion: numpy's sin/cos against libm's (math); numpy < 1.25 computes float64
    # sin/cos with its own SIMD code, within an ulp or two of libm, not bit-equal.
    np.testing.assert_allclose(rows(decoded)[:, 5:], rows(reference)[:, 5:], rtol=0,
                               atol=5e-16)
    assert len(data) - len(serialize_message(reference)) in (0, 4)  # the empty set's pad
    with pytest.raises(ma.MessageError):
        ma.particles_to_posearray_cdr(p, -1, frame_id)


def test_navsatfix_round_trip_and_errors():
    cov = np.diag([4.0, 5.0, 16.0])
    fix = ma.GeodeticFix(STAMP, 50.11, 8.68, 150.5, cov, service=ma.service_bits([1, 4]))
    msg = ma.fix_to_navsatfix(fix)
    assert msg.position_covariance_type == NavSatFix.COVARIANCE_TYPE_KNOWN
    assert msg.status.service == 3
    back = ma.navsatfix_to_fix(msg)
    assert (back.lat_deg, back.lon_deg, back.alt_m) == (50.11, 8.68, 150.5)
    np.testing.assert_array_equal(back.covariance_enu_m2, cov)
    unknown = ma.navsatfix_to_fix(ma.fix_to_navsatfix(ma.GeodeticFix(STAMP, 1.0, 2.0, 3.0)))
    assert unknown.covariance_enu_m2 is None
    with pytest.raises(ma.MessageError):
        ma.fix_to_navsatfix(ma.GeodeticFix(STAMP, math.nan, 0.0, 0.0))
    msg.latitude = 91.0
    with pytest.raises(ma.MessageError):
        ma.navsatfix_to_fix(msg)


# --------------------------------------------------------------- IMU, twist, odometry
def test_imu_and_twist_round_trip_and_errors():
    s = ma.ImuSample(STAMP, np.array([0.5, -0.1, 9.81]), np.array([0.0, 0.01, -0.2]))
    msg = ma.sample_to_imu(s)
    back = ma.imu_to_sample(msg)
    np.testing.assert_array_equal(back.accel_mps2, s.accel_mps2)
    np.testing.assert_array_equal(back.gyro_rps, s.gyro_rps)
    msg.angular_velocity.z = math.nan
    with pytest.raises(ma.MessageError) as err:
        ma.imu_to_sample(msg)
    assert err.value.reason == 'non_finite'
    msg.angular_velocity.z = 0.0
    msg.angular_velocity_covariance[0] = -1.0
    with pytest.raises(ma.MessageError):
        ma.imu_to_sample(msg)
    t = ma.TwistSample(STAMP, 8.5, -0.05, 0.0025, 1e-4)
    tmsg = ma.sample_to_twist(t)
    assert ma.twist_to_sample(tmsg) == t
    tmsg.twist.twist.linear.x = math.inf
    with pytest.raises(ma.MessageError):
        ma.twist_to_sample(tmsg)


def test_dead_reckoning_round_trip():
    s = DeadReckoningState(STAMP, 105.25, -20.5, 1.2, 9.5, 0.05, 0.0025, 1e-4, 0.75, 0.003)
    msg = ma.dead_reckoning_to_odometry(s)
    assert msg.header.frame_id == 'odom' and msg.child_frame_id == 'base_link'
    back = ma.odometry_to_dead_reckoning(msg)
    for name in ('stamp_ns', 'x_m', 'y_m', 'speed_mps', 'yaw_rate_rps', 'speed_var',
                 'yaw_rate_var', 'distance_var_m2', 'yaw_var_rad2'):
        assert getattr(back, name) == getattr(s, name), name
    assert back.yaw_rad == pytest.approx(1.2, abs=1e-15)
    wrapped = ma.odometry_to_dead_reckoning(ma.dead_reckoning_to_odometry(
        DeadReckoningState(STAMP, 0, 0, 2 * np.pi + 0.5, 0, 0, 0, 0, 0, 0)))
    assert wrapped.yaw_rad == pytest.approx(0.5)
    msg.pose.pose.position.x = math.nan
    with pytest.raises(ma.MessageError):
        ma.odometry_to_dead_reckoning(msg)


def test_global_odometry_round_trip_and_errors():
    cov = ma.pose_covariance(np.array([[4.0, 0.5, 0.0], [0.5, 2.0, 0.0], [0.0, 0.0, 9.0]]),
                             0.01)
    odom = ma.GlobalOdometry(STAMP, np.array([12.5, -3.25, 1.5]), -2.5, cov, 9.5, -0.05,
                             0.0025, 1e-4, frame_id='map', child_frame_id='base_link')
    msg = ma.global_odometry_to_msg(odom)
    assert (msg.header.frame_id, msg.child_frame_id) == ('map', 'base_link')
    assert ma.stamp_to_ns(msg.header.stamp) == STAMP
    twist_cov = np.array(msg.twist.covariance).reshape(6, 6)
    # Only speed and yaw rate are estimated; the other axes say "not estimated".
    assert twist_cov[0, 0] == 0.0025 and twist_cov[5, 5] == 1e-4
    assert np.all(np.diag(twist_cov)[1:5] == ma.geometry.UNESTIMATED_VAR)
    assert np.count_nonzero(twist_cov - np.diag(np.diag(twist_cov))) == 0
    back = ma.odometry_to_global(msg)
    for name in ('stamp_ns', 'speed_mps', 'yaw_rate_rps', 'speed_var', 'yaw_rate_var',
                 'frame_id', 'child_frame_id'):
        assert getattr(back, name) == getattr(odom, name), name
    np.testing.assert_array_equal(back.position_m, odom.position_m)
    np.testing.assert_array_equal(back.pose_covariance, cov)
    assert back.yaw_rad == pytest.approx(-2.5, abs=1e-15)
    with pytest.raises(ma.MessageError, match='finite'):
        ma.global_odometry_to_msg(ma.GlobalOdometry(STAMP, np.zeros(3), 0.0, cov, math.nan,
                                                    0.0, 0.0, 0.0))
    with pytest.raises(ma.MessageError, match='6, 6'):
        ma.global_odometry_to_msg(ma.GlobalOdometry(STAMP, np.zeros(3), 0.0, np.eye(3), 0.0,
                                                    0.0, 0.0, 0.0))
    msg.twist.twist.linear.x = math.inf
    with pytest.raises(ma.MessageError):
        ma.odometry_to_global(msg)


# ---------------------------------------------------------------------- integrity
def _verdict(level=OK, bound=0.05, **kw):
    """A core verdict (what fusion_node publishes), with a protection level that backs an
    OK unless given."""
    kw.setdefault('protection_level_m', 6.25)
    return IntegrityVerdict(stamp_ns=STAMP, level=level, message='m', risk_bound=bound,
                            empirical_risk=0.01, divergence_risk=bound - 0.01,
                            alert_limit_m=8.0, target_risk=0.1, epoch_stamp_ns=STAMP, **kw)


def test_integrity_risk_round_trip_is_exact():
    verdict = _verdict(bound=0.1 / 3, epoch_status='updated',
                       risk_bounds_by_limit={16.0: 0.01 / 3}, details={'n_satellites': 11})
    msg = ma.integrity_risk_to_msg(verdict)
    assert isinstance(msg, DiagnosticArray) and len(msg.status) == 1
    assert msg.status[0].level == DiagnosticStatus.OK
    back = ma.parse_integrity_risk(msg)
    assert back == ma.IntegrityRisk(
        stamp_ns=STAMP, level=ma.OK, message='m', risk_bound=0.1 / 3, empirical_risk=0.01,
        divergence_risk=0.1 / 3 - 0.01, alert_limit_m=8.0, target_risk=0.1,
        epoch_stamp_ns=STAMP, protection_level_m=6.25, extra={'n_satellites': '11'},
        epoch_status='updated', risk_bounds_by_limit={16.0: 0.01 / 3})
    assert back.integrity_ok and not back.stale
    err = ma.parse_integrity_risk(ma.integrity_risk_to_msg(_verdict(ERROR, 0.4)))
    assert err.level == ma.ERROR and not err.integrity_ok and err.level_name == 'ERROR'
    stale = ma.parse_integrity_risk(ma.integrity_risk_to_msg(
        IntegrityVerdict(STAMP, STALE, 'no gnss', 8.0, 0.1)))
    assert stale.stale and not stale.integrity_ok and math.isnan(stale.risk_bound)
    assert stale.epoch_stamp_ns is None and math.isnan(stale.protection_level_m)
    assert stale.epoch_status is None and stale.risk_bounds_by_limit == {}


def test_integrity_typed_fields_keep_the_wire_keys():
    """epoch_status and risk_bounds_by_limit travel as 'status' and 'risk_bound_<L>m' (the
    keys of older bags), and come back typed, out of extra."""
    verdict = _verdict(epoch_status='propagated',
                       risk_bounds_by_limit={16.0: 0.25, 2.5: 0.5},
                       details={'inverse_bernoulli': 'exact'})
    values = ma.status_values(ma.integrity_risk_to_msg(verdict).status[0])
    assert values['status'] == 'propagated'
    assert values['risk_bound_16m'] == '0.25' and values['risk_bound_2.5m'] == '0.5'
    back = ma.parse_integrity_risk(ma.integrity_risk_to_msg(verdict))
    assert back.epoch_status == 'propagated'
    assert back.risk_bounds_by_limit == {16.0: 0.25, 2.5: 0.5}
    assert back.extra == {'inverse_bernoulli': 'exact'}
    # No GNSS epoch behind the verdict: None, 'no_gnss' on the wire.
    none = ma.integrity_risk_to_msg(_verdict(ERROR, 0.4))
    assert ma.status_values(none.status[0])['status'] == 'no_gnss'
    assert ma.parse_integrity_risk(none).epoch_status is None
    # A message without a status (another producer) has no epoch status either.
    none.status[0].values = [kv for kv in none.status[0].values if kv.key != 'status']
    assert ma.parse_integrity_risk(none).epoch_status is None
    bad = ma.integrity_risk_to_msg(verdict)
    bad.status[0].values.append(KeyValue(key='risk_bound_32m', value='high'))
    with pytest.raises(ma.MessageError) as err:
        ma.parse_integrity_risk(bad)
    assert err.value.reason == 'value'


def _risk(**kw):
    return ma.IntegrityRisk(stamp_ns=STAMP, level=ma.OK, message='m', risk_bound=0.05,
                            empirical_risk=0.01, divergence_risk=0.04, alert_limit_m=8.0,
                            target_risk=0.1, epoch_stamp_ns=STAMP, **kw)


def test_integrity_risk_built_with_wire_keys_in_extra():
    """An IntegrityRisk built with 'status' and 'risk_bound_<L>m' in extra (as older
    consumers did) gets the typed fields."""
    legacy = _risk(extra={'status': 'updated', 'n_satellites': 9, 'risk_bound_16m': 0.02})
    assert legacy.epoch_status == 'updated' and legacy.risk_bounds_by_limit == {16.0: 0.02}
    assert legacy.extra == {'n_satellites': 9}
    typed = _risk(epoch_status='updated', risk_bounds_by_limit={16.0: 0.02},
                  extra={'n_satellites': 9})
    assert legacy == typed
    assert _risk(extra={'status': 'no_gnss'}).epoch_status is None
    # Typed fields win over the same keys in extra.
    both = _risk(epoch_status='rejected', risk_bounds_by_limit={16.0: 0.5},
                 extra={'status': 'updated', 'risk_bound_16m': 0.02, 'risk_bound_32m': 0.01})
    assert both.epoch_status == 'rejected'
    assert both.risk_bounds_by_limit == {16.0: 0.5, 32.0: 0.01} and both.extra == {}


def test_integrity_risk_refuses_an_unbacked_ok():
    ma.integrity_risk_to_msg(_verdict(OK, 0.1))             # backed: encodes
    with pytest.raises(ma.MessageError, match='bound'):
        ma.integrity_risk_to_msg(_verdict(OK, 0.3))        # bound above target
    with pytest.raises(ma.MessageError, match='bound'):
        ma.integrity_risk_to_msg(_verdict(OK, math.nan))
    with pytest.raises(ma.MessageError, match='protection level'):
        ma.integrity_risk_to_msg(_verdict(OK, protection_level_m=8.5))
    with pytest.raises(ma.MessageError, match='protection level'):
        ma.integrity_risk_to_msg(_verdict(OK, protection_level_m=math.inf))
    with pytest.raises(ma.MessageError, match='not OK, ERROR or STALE'):
        ma.integrity_risk_to_msg(_verdict('WARN'))


def test_parse_integrity_risk_errors():
    with pytest.raises(ma.MessageError) as err:
        ma.parse_integrity_risk(DiagnosticArray())
    assert err.value.reason == 'fields'
    msg = ma.integrity_risk_to_msg(_verdict())
    msg.status[0].values = [kv for kv in msg.status[0].values if kv.key != 'target_risk']
    with pytest.raises(ma.MessageError, match='target_risk'):
        ma.parse_integrity_risk(msg)
    msg = ma.integrity_risk_to_msg(_verdict())
    msg.status[0].values.append(KeyValue(key='risk_bound', value='abc'))
    msg.status[0].values = [msg.status[0].values[-1]] + msg.status[0].values[1:]
    with pytest.raises(ma.MessageError):
        ma.parse_integrity_risk(msg)
    msg = ma.integrity_risk_to_msg(_verdict())
    msg.status[0].level = DiagnosticStatus.WARN
    with pytest.raises(ma.MessageError):
        ma.parse_integrity_risk(msg)


def test_diagnostic_helpers():
    status = ma.make_status('n', ma.WARN, 'msg', {'a': 1, 'b': 0.5, 'c': True, 'd': 'x'})
    assert ma.level_to_int(status.level) == ma.WARN
    assert ma.status_values(status) == {'a': '1', 'b': '0.5', 'c': 'true', 'd': 'x'}
    arr = ma.make_diagnostic_array(STAMP, [status])
    assert ma.stamp_to_ns(arr.header.stamp) == STAMP
