"""Validation at the boundary: the documented limits of msg_adapters.limits (valid data at
the edges accepted, beyond refused, sizes refused before anything is decoded), the stamp
gate, the loss counter of the node inputs, and (ROS graph) single malformed messages of
every kind refused, counted by reason on diagnostics, with the later valid outputs of the
nodes unchanged; a replay started again adopted as a new time base; undecodable messages
counted.
"""
import math
from types import SimpleNamespace

import numpy as np
import pytest
from ros_harness import serialize_message  # skips this module without rclpy
from sensor_msgs.msg import Image, PointCloud2

import msg_adapters as ma
from gnsscam_ros.core.motion import DeadReckoningState
from gnsscam_ros.core.types import GnssEpoch
from gnsscam_ros.nodes.node_base import SequenceGaps
from msg_adapters import limits as lim
from msg_adapters.stamp_gate import ADVANCE, BEHIND, NEW_BASE, StampGate

S = 1_000_000_000
T0 = 1_718_204_613 * S


def _epoch(k=8, radius=2.6e7, pr=2.2e7, stamp_ns=T0):
    rng = np.random.default_rng(3)
    direction = rng.normal(0, 1, (k, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    return GnssEpoch(stamp_ns=stamp_ns, sv_pos_ecef_m=direction * radius,
                     pr_m=np.full(k, float(pr)), var_m2=np.full(k, 10.0),
                     sv_id=np.arange(1, k + 1), system=np.ones(k, dtype=np.int64),
                     elevation_deg=np.full(k, 30.0), cn0_dbhz=np.full(k, 40.0))


def _with(epoch, **changes):
    return GnssEpoch(**{**epoch.__dict__, **changes})


def _refused(reason, parse, *args, **kwargs):
    with pytest.raises(ma.MessageError) as err:
        parse(*args, **kwargs)
    assert err.value.reason == reason, str(err.value)
    return str(err.value)


def _accepted_or_refused(reason, parse, msg, rtol=0.0, **expected):
    """``parse(msg)`` refuses ``msg`` for ``reason``; when ``reason`` is None it takes it
    and gives the values sent: every ``expected`` attribute of the result, to ``rtol``
    (FLOAT32 fields on the wire: 1e-7)."""
    if reason is not None:
        return _refused(reason, parse, msg)
    assert expected, 'an accepted edge value must be compared with what was sent'
    parsed = parse(msg)
    for name, value in expected.items():
        np.testing.assert_allclose(np.asarray(getattr(parsed, name), float).ravel(),
                                   np.asarray(value, float).ravel(), rtol=rtol, atol=0,
                                   err_msg=name)
    return parsed


class _Untouchable:
    """A message whose arrays must not be read: the sizes are refused before."""

    def __init__(self, **fields):
        self.__dict__.update(fields)

    @property
    def data(self):
        raise AssertionError('the data was read before the sizes were checked')

    @property
    def fields(self):
        raise AssertionError('the fields were read before the sizes were checked')


# ============================================================================ stamps
@pytest.mark.parametrize('sec, nanosec, ok', [
    (0, 0, True), (2 ** 31 - 1, 999_999_999, True), (2 ** 31 - 1, 2 ** 32 - 1, False),
    (5, 1_000_000_000, False), (-1, 0, False), (-2 ** 31, 0, False)])
def test_stamps_must_be_valid_builtin_interfaces_time(sec, nanosec, ok):
    stamp = SimpleNamespace(sec=sec, nanosec=nanosec)
    if ok:
        ns = ma.stamp_to_ns(stamp)
        assert ma.stamp_to_ns(ma.ns_to_stamp(ns)) == ns          # re-encodes
    else:
        _refused('stamp', ma.stamp_to_ns, stamp)


@pytest.mark.parametrize('make, parse', [
    (lambda: ma.gnss_epoch_to_pointcloud2(_epoch()), ma.pointcloud2_to_gnss_epoch),
    (lambda: ma.sample_to_imu(ma.ImuSample(T0, np.zeros(3), np.zeros(3))), ma.imu_to_sample),
    (lambda: ma.sample_to_twist(ma.TwistSample(T0, 1.0, 0.1)), ma.twist_to_sample),
    (lambda: ma.dead_reckoning_to_odometry(DeadReckoningState(T0, 1, 2, 0, 1, 0, 0, 0, 0, 0)),
     ma.odometry_to_dead_reckoning),
    (lambda: ma.matches_to_pointcloud2(ma.CameraMatches(T0, np.zeros((1, 3)), np.ones(1),
                                                        np.zeros(1, int))),
     ma.pointcloud2_to_matches),
    (lambda: ma.array_to_image(np.zeros((64, 64), np.uint8), T0), ma.image_to_array),
])
@pytest.mark.parametrize('sec, nanosec', [(2 ** 31 - 1, 2 ** 32 - 1), (-5, 0)])
def test_every_input_parser_refuses_an_invalid_stamp(make, parse, sec, nanosec):
    msg = make()
    parse(msg)
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
    _refused('stamp', parse, msg)


# ============================================================================== GNSS
@pytest.mark.parametrize('radius, reason', [
    # At the edges (a hair inside: the direction vectors are rounded to unit length).
    (lim.MIN_MESSAGE_SATELLITE_RADIUS_M * (1 + 1e-12), None),
    (lim.MAX_MESSAGE_SATELLITE_RADIUS_M * (1 - 1e-12), None),
    (lim.MIN_MESSAGE_SATELLITE_RADIUS_M * 0.999, 'range'),
    (lim.MAX_MESSAGE_SATELLITE_RADIUS_M * 1.001, 'range')])
def test_satellite_radius_limits(radius, reason):
    epoch = _epoch(radius=radius)
    msg = ma.gnss_epoch_to_pointcloud2(epoch)
    _accepted_or_refused(reason, ma.pointcloud2_to_gnss_epoch, msg,
                         sv_pos_ecef_m=epoch.sv_pos_ecef_m, pr_m=epoch.pr_m)


def test_one_satellite_coordinate_of_1e160_or_a_flipped_exponent_is_refused():
    epoch = _epoch()
    for value in (1e160, -1e160, np.float64(2.6e7).view(np.int64) ^ (1 << 61)):
        sv = epoch.sv_pos_ecef_m.copy()
        sv[3, 1] = value if isinstance(value, float) else np.int64(value).view(np.float64)
        text = _refused('range', ma.pointcloud2_to_gnss_epoch,
                        ma.gnss_epoch_to_pointcloud2(_with(epoch, sv_pos_ecef_m=sv)))
        assert 'satellite' in text


@pytest.mark.parametrize('pr, reason', [
    (lim.MIN_MESSAGE_PSEUDORANGE_M, None), (lim.MAX_MESSAGE_PSEUDORANGE_M, None),
    (lim.MIN_MESSAGE_PSEUDORANGE_M - 1.0, 'range'), (lim.MAX_MESSAGE_PSEUDORANGE_M + 1.0, 'range'),
    (1e300, 'range')])
def test_pseudorange_limits(pr, reason):
    epoch = _epoch(pr=pr)
    msg = ma.gnss_epoch_to_pointcloud2(epoch)
    _accepted_or_refused(reason, ma.pointcloud2_to_gnss_epoch, msg, pr_m=np.full(
        epoch.n_sv, pr))


def test_markers_of_a_missing_measurement_pass_to_the_core_checks_only_from_the_receiver():
    epoch = _epoch()
    pr, var, el, cn0 = (epoch.pr_m.copy(), epoch.var_m2.copy(), epoch.elevation_deg.copy(),
                        epoch.cn0_dbhz.copy())
    pr[0], pr[1], var[2] = np.nan, -1.0, 0.0        # receivers' "no measurement"
    el[3], cn0[4] = np.nan, np.nan                  # unknown: kept by the masks
    msg = ma.gnss_epoch_to_pointcloud2(_with(epoch, pr_m=pr, var_m2=var, elevation_deg=el,
                                             cn0_dbhz=cn0))
    back = ma.pointcloud2_to_gnss_epoch(msg)
    assert np.isnan(back.pr_m[0]) and back.pr_m[1] == -1.0 and back.var_m2[2] == 0.0
    # gnss/measurements carries checked satellites only: the same message is refused.
    _refused('non_finite', ma.pointcloud2_to_gnss_epoch, msg, checked=True)
    clean = _with(epoch, elevation_deg=el, cn0_dbhz=cn0)        # NaN elevation/C/N0 stay
    ma.pointcloud2_to_gnss_epoch(ma.gnss_epoch_to_pointcloud2(clean), checked=True)
    _refused('range', ma.pointcloud2_to_gnss_epoch,
             ma.gnss_epoch_to_pointcloud2(_with(epoch, var_m2=var)), checked=True)


@pytest.mark.parametrize('field, value, reason', [
    ('variance', lim.MAX_VARIANCE * 1.01, 'range'), ('cn0', 101.0, 'range'),
    ('cn0', -1.0, 'range'), ('elevation', 90.5, 'range'), ('elevation', np.inf, 'non_finite'),
    ('variance', lim.MAX_VARIANCE * 0.99, None), ('elevation', -90.0, None)])
def test_other_satellite_fields(field, value, reason):
    epoch = _epoch()
    name = {'variance': 'var_m2', 'cn0': 'cn0_dbhz', 'elevation': 'elevation_deg'}[field]
    values = getattr(epoch, name).copy()
    values[1] = value
    msg = ma.gnss_epoch_to_pointcloud2(_with(epoch, **{name: values}))
    _accepted_or_refused(reason, ma.pointcloud2_to_gnss_epoch, msg, rtol=1e-7,
                         **{name: values})


def test_checked_epochs_refuse_duplicates_and_unknown_systems_the_receiver_gets_them_dropped():
    epoch = _epoch()
    twice = _with(epoch, sv_id=np.r_[epoch.sv_id[:-1], epoch.sv_id[0]])
    unknown = _with(epoch, system=np.r_[epoch.system[:-1], 99])
    other_system = _with(epoch, system=np.r_[epoch.system[:-1], 8])    # same id, Galileo
    for msg, reason in ((twice, 'duplicate_satellites'), (unknown, 'unknown_system')):
        cloud = ma.gnss_epoch_to_pointcloud2(msg)
        _refused(reason, ma.pointcloud2_to_gnss_epoch, cloud, checked=True)
        # From the receiver: passed on, gnss_node drops and counts them per satellite.
        assert ma.pointcloud2_to_gnss_epoch(cloud).n_sv == epoch.n_sv
    ma.pointcloud2_to_gnss_epoch(ma.gnss_epoch_to_pointcloud2(other_system), checked=True)
    moved = ma.gnss_epoch_to_pointcloud2(epoch, frame_id='map')
    _refused('frame', ma.pointcloud2_to_gnss_epoch, moved, checked=True)


def test_satellite_count_is_refused_before_anything_is_decoded():
    ok = ma.gnss_epoch_to_pointcloud2(_epoch(k=lim.MAX_MESSAGE_SATELLITES))
    assert ma.pointcloud2_to_gnss_epoch(ok).n_sv == lim.MAX_MESSAGE_SATELLITES
    ma.check_serialized_gnss(serialize_message(ok))
    huge = _Untouchable(header=ok.header, width=1000, height=1, point_step=48, row_step=48000,
                        is_bigendian=False)
    _refused('size', ma.pointcloud2_to_gnss_epoch, huge)
    # In the serialised message, from its header fields: 10,000 satellites of which only
    # the sizes are written (the data the header promises is not even there).
    raw = serialize_message(PointCloud2(header=ok.header, height=100, width=100))
    _refused('size', ma.check_serialized_gnss, raw)
    assert ma.wire.header_dims(serialize_message(ok)) == (1, lim.MAX_MESSAGE_SATELLITES)
    assert ma.wire.header_dims(b'\x00\x07\x00\x00' + bytes(40)) is None     # not plain CDR


# ============================================================================ motion
@pytest.mark.parametrize('accel, gyro, reason', [
    ([lim.MAX_ACCEL_MPS2, -9.8, 0], [0, 0, lim.MAX_MESSAGE_YAW_RATE_RPS], None),
    ([0, 0, -lim.MAX_ACCEL_MPS2], [lim.MAX_GYRO_RPS, -lim.MAX_GYRO_RPS, 0], None),
    ([lim.MAX_ACCEL_MPS2 + 0.1, 0, 0], [0, 0, 0], 'range'),
    ([0, 0, 0], [lim.MAX_GYRO_RPS + 0.1, 0, 0], 'range'),
    ([0, 0, 0], [0, 0, lim.MAX_MESSAGE_YAW_RATE_RPS + 0.01], 'range'),
    ([1.7e308, 0, 0], [0, 0, 0], 'range'),
    ([0, np.nan, 0], [0, 0, 0], 'non_finite')])
def test_imu_limits(accel, gyro, reason):
    msg = ma.sample_to_imu(ma.ImuSample(T0, np.array(accel, float), np.array(gyro, float)))
    _accepted_or_refused(reason, ma.imu_to_sample, msg, accel_mps2=accel, gyro_rps=gyro)


@pytest.mark.parametrize('speed, yaw_rate, var, reason', [
    (lim.MAX_SPEED_MPS, -lim.MAX_MESSAGE_YAW_RATE_RPS, lim.MAX_VARIANCE, None),
    (-lim.MAX_SPEED_MPS, 0.0, 0.0, None),                 # variance 0: not reported
    (1.0, 0.0, -1.0, 'range'),                             # a negative variance is none
    (1.0, 0.0, -1e-12, None),                              # a rounded zero is one
    (1.7e308, 0.0, 0.0, 'range'), (lim.MAX_SPEED_MPS + 0.01, 0.0, 0.0, 'range'),
    (0.0, lim.MAX_MESSAGE_YAW_RATE_RPS + 0.01, 0.0, 'range'), (0.0, 0.0, 1e300, 'range'),
    (math.inf, 0.0, 0.0, 'non_finite')])
def test_odometry_twist_limits(speed, yaw_rate, var, reason):
    msg = ma.sample_to_twist(ma.TwistSample(T0, speed, yaw_rate, var, var))
    if reason is None:
        assert ma.twist_to_sample(msg).speed_mps == speed
    else:
        _refused(reason, ma.twist_to_sample, msg)


@pytest.mark.parametrize('x, speed, var, reason', [
    (lim.MAX_POSITION_M, lim.MAX_SPEED_MPS, lim.MAX_VARIANCE, None),
    (-lim.MAX_POSITION_M, 0.0, 0.0, None),
    (1e300, 0.0, 0.0, 'range'), (lim.MAX_POSITION_M * 1.001, 0.0, 0.0, 'range'),
    (0.0, lim.MAX_SPEED_MPS * 1.01, 0.0, 'range'), (0.0, 0.0, -1.0, 'range'),
    (0.0, 0.0, lim.MAX_VARIANCE * 1.01, 'range')])
def test_dead_reckoning_limits(x, speed, var, reason):
    state = DeadReckoningState(T0, x, -x, 0.3, speed, 0.1, var, var, var, var)
    msg = ma.dead_reckoning_to_odometry(state)
    if reason is None:
        assert ma.odometry_to_dead_reckoning(msg).x_m == x
    else:
        _refused(reason, ma.odometry_to_dead_reckoning, msg)


def _changed(msg, root, changes: dict):
    """``msg`` with fields below ``root`` set: ``{'a.b.c': value}``, a number as the last
    part sets that element of the covariance of ``a.b``."""
    for path, value in changes.items():
        *parents, leaf = path.split('.')
        obj = root
        for p in parents:
            obj = getattr(obj, p)
        if leaf.isdigit():
            cov = np.array(obj.covariance, float)
            cov[int(leaf)] = value
            obj.covariance = cov
        else:
            setattr(obj, leaf, value)
    return msg


def _twist(**changes):
    msg = ma.sample_to_twist(ma.TwistSample(T0, 5.0, 0.1, 0.01, 1e-4))
    return _changed(msg, msg.twist, changes)


@pytest.mark.parametrize('changes, reason', [
    ({'twist.linear.y': lim.MAX_SPEED_MPS, 'twist.angular.x': -lim.MAX_GYRO_RPS}, None),
    ({'twist.linear.z': lim.MAX_SPEED_MPS * 1.01}, 'range'),
    ({'twist.angular.y': lim.MAX_GYRO_RPS + 0.1}, 'range'),
    ({'twist.angular.x': math.nan}, 'non_finite'),
    ({'7': 2.0}, None),                          # a variance the node does not use
    ({'21': 1e11}, None),                        # sqrt(1e11)^2 != 1e11: no correlation
    ({'7': -2.0}, 'range'),
    ({'7': 0.01, '1': 0.005}, None),             # correlation 0.5 of speed and lateral speed
    ({'7': 0.01, '1': 0.02}, 'range'),           # correlation 2
    ({'31': 1e-3}, 'range'),                     # off-diagonal where a variance is 0
    ({'31': 1e-12}, None),                       # within the tolerance
    ({'14': math.inf}, 'non_finite')])
def test_every_twist_component_and_the_whole_covariance_are_checked(changes, reason):
    msg = _twist(**changes)
    # Only the forward speed, the yaw rate and their variances reach the node.
    _accepted_or_refused(reason, ma.twist_to_sample, msg, speed_mps=5.0, yaw_rate_rps=0.1,
                         speed_var=0.01, yaw_rate_var=1e-4)


def _imu(**changes):
    msg = ma.sample_to_imu(ma.ImuSample(T0, np.array([0.1, 0.0, 9.8]), np.zeros(3)))
    for name, (index, value) in changes.items():
        if name == 'orientation':
            msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w = value
            continue
        cov = np.array(getattr(msg, name), float)
        cov[index] = value
        setattr(msg, name, cov)
    return msg


@pytest.mark.parametrize('changes, reason', [
    ({}, None),
    # Orientation marked unavailable (REP 145): its values are not judged.
    ({'orientation': (None, (5.0, 0.0, 0.0, 0.0))}, None),
    # Reported: a unit quaternion with a covariance.
    ({'orientation_covariance': (0, 0.01)}, None),
    ({'orientation_covariance': (0, 0.01), 'orientation': (None, (0.0, 0.0, 0.6, 0.8))},
     None),
    ({'orientation_covariance': (0, 0.01), 'orientation': (None, (0.0, 0.0, 0.0, 2.0))},
     'range'),
    ({'orientation_covariance': (0, -2.0)}, 'range'),
    ({'linear_acceleration_covariance': (0, -1.0)}, 'value'),     # marked unavailable
    ({'angular_velocity_covariance': (0, -1.0)}, 'value'),
    ({'angular_velocity_covariance': (4, -0.5)}, 'range'),
    ({'linear_acceleration_covariance': (3, 1.0)}, 'range'),      # off-diagonal, var 0
    ({'angular_velocity_covariance': (8, math.nan)}, 'non_finite')])
def test_imu_covariances_and_a_reported_orientation_are_checked(changes, reason):
    msg = _imu(**changes)
    _accepted_or_refused(reason, ma.imu_to_sample, msg, accel_mps2=[0.1, 0.0, 9.8],
                         gyro_rps=np.zeros(3))


def _odometry(**changes):
    state = DeadReckoningState(T0, 10.0, -3.0, 0.3, 5.0, 0.1, 0.01, 1e-4, 1.0, 1e-3)
    msg = ma.dead_reckoning_to_odometry(state)
    return _changed(msg, msg, changes)


@pytest.mark.parametrize('changes, reason', [
    ({}, None),
    ({'pose.pose.orientation.z': 1e300}, 'range'),          # the fuzz kit's case
    ({'pose.pose.orientation.w': 0.0, 'pose.pose.orientation.z': 0.0}, 'range'),
    ({'pose.pose.orientation.z': 1.004 * math.sin(0.15),   # |q|^2 = 1.008: within
      'pose.pose.orientation.w': 1.004 * math.cos(0.15)}, None),   # tf2's 1e-2
    ({'pose.pose.orientation.x': math.nan}, 'non_finite'),
    ({'pose.pose.position.z': lim.MAX_POSITION_M * 1.01}, 'range'),
    ({'twist.twist.linear.y': 1e6}, 'range'),
    ({'twist.twist.angular.x': lim.MAX_GYRO_RPS * 2}, 'range'),
    ({'pose.14': -1.0}, 'range'),                            # z variance negative
    ({'twist.0': -0.01}, 'range'),
    ({'pose.1': 0.5}, None),                                 # x-y correlation 0.5
    ({'pose.1': 5.0}, 'range'),
    ({'twist.5': 1.0}, 'range'),
    ({'header.frame_id': 'map'}, 'frame'),
    ({'child_frame_id': 'imu'}, 'frame')])
def test_dead_reckoning_frames_quaternion_and_covariances(changes, reason):
    msg = _odometry(**changes)
    # A quaternion within tf2's tolerance of unit length gives the same heading.
    _accepted_or_refused(reason, ma.odometry_to_dead_reckoning, msg, rtol=1e-12, x_m=10.0,
                         y_m=-3.0, yaw_rad=0.3, speed_mps=5.0, yaw_rate_rps=0.1)
    # Other frames when the node is configured so; None takes any.
    moved = _odometry(**{'header.frame_id': 'odom_2', 'child_frame_id': 'car'})
    ma.odometry_to_dead_reckoning(moved, frame_id='odom_2', child_frame_id='car')
    ma.odometry_to_dead_reckoning(moved, frame_id=None, child_frame_id=None)


# ============================================================================ camera
def _matches(position, score=0.5, k=1):
    return ma.matches_to_pointcloud2(ma.CameraMatches(
        T0, np.tile(np.asarray(position, float), (k, 1)), np.full(k, score),
        np.arange(k)))


def test_camera_match_limits():
    ma.pointcloud2_to_matches(_matches([lim.MAX_POSITION_M, -lim.MAX_POSITION_M, 0.0], 1.0))
    ma.pointcloud2_to_matches(_matches([0, 0, 0], 0.0, k=lim.MAX_MATCHES))
    _refused('range', ma.pointcloud2_to_matches, _matches([1e300, 0, 0]))
    _refused('range', ma.pointcloud2_to_matches, _matches([0, 0, 0], 1.5))
    _refused('range', ma.pointcloud2_to_matches, _matches([0, 0, 0], -0.1))
    big = _matches([0, 0, 0], k=lim.MAX_MATCHES + 1)
    _refused('size', ma.pointcloud2_to_matches, big)
    moved = _matches([0, 0, 0])
    moved.header.frame_id = 'earth'
    _refused('frame', ma.pointcloud2_to_matches, moved)
    _refused('size', ma.check_serialized_matches, serialize_message(big))
    huge = _Untouchable(header=big.header, width=10 ** 6, height=1, point_step=32,
                        row_step=32 * 10 ** 6, is_bigendian=False)
    _refused('size', ma.pointcloud2_to_matches, huge)


@pytest.mark.parametrize('width, height, reason', [
    (lim.MAX_IMAGE_WIDTH_PX, lim.MAX_IMAGE_HEIGHT_PX, None),
    (lim.MIN_IMAGE_SIDE_PX, lim.MIN_IMAGE_SIDE_PX, None),
    (8000, 8000, 'size'), (lim.MAX_IMAGE_WIDTH_PX + 1, 480, 'size'),
    (640, lim.MAX_IMAGE_HEIGHT_PX + 1, 'size'), (lim.MIN_IMAGE_SIDE_PX - 1, 480, 'size'),
    (1, 1, 'size')])
def test_image_sides_are_refused_from_the_header_fields(width, height, reason):
    header = ma.make_header(T0, 'camera')
    # The serialised message: only the header fields are read (no pixels are sent).
    raw = serialize_message(Image(header=header, height=height, width=width, encoding='bgr8',
                                  step=3 * width))
    fake = _Untouchable(header=header, height=height, width=width, encoding='bgr8',
                        step=3 * width)
    if reason is None:
        ma.check_serialized_image(raw)
        ma.check_image_size(width, height)
    else:
        _refused(reason, ma.check_serialized_image, raw)
        _refused(reason, ma.check_image, fake)


def test_bytes_of_a_message_are_bounded_before_decoding():
    # A cloud of few points whose points are huge, an image whose rows are huge, an IMU
    # message with a megabyte frame name: refused from their sizes.
    cloud = ma.gnss_epoch_to_pointcloud2(_epoch(k=4))
    wide = _Untouchable(header=cloud.header, width=4, height=1, row_step=4 * 10 ** 6,
                        point_step=10 ** 6, is_bigendian=False)
    _refused('size', ma.pointcloud2_to_gnss_epoch, wide)
    _refused('size', ma.check_serialized_gnss, serialize_message(cloud) + bytes(10 ** 6))
    image = Image(header=ma.make_header(T0, 'camera'), height=64, width=64, encoding='mono8',
                  step=lim.MAX_IMAGE_STEP_BYTES + 1)
    image.data = bytes(64 * image.step)
    _refused('size', ma.check_image, image)
    imu = ma.sample_to_imu(ma.ImuSample(T0, np.zeros(3), np.zeros(3)))
    ma.check_serialized_size(serialize_message(imu), 'imu/data')
    imu.header.frame_id = 'x' * 10 ** 6
    _refused('size', ma.check_serialized_size, serialize_message(imu), 'imu/data')


# ======================================================================= stamp gate
W = lim.STAMP_WINDOW_NS
K = lim.NEW_TIME_BASE_MESSAGES


def test_gate_refuses_a_single_far_stamp_and_takes_the_stream_after_it():
    gate = StampGate()
    assert gate.admit(T0) == ADVANCE
    assert gate.admit(T0 + W) == ADVANCE                    # the edge of the window
    with pytest.raises(ma.MessageError) as err:
        gate.admit(T0 + W + 10 ** 9 * 10 ** 6)              # far future
    assert err.value.reason == 'stamp_jump'
    with pytest.raises(ma.MessageError):
        gate.admit(T0 - 10 * W)                             # far past
    assert gate.admit(T0 + W + S) == ADVANCE                # the stream goes on
    assert gate.newest_ns == T0 + W + S and gate.time_base_changes == 0
    assert gate.admit(T0 + W) == BEHIND                     # the node judges the order


def test_gate_adopts_a_consistent_new_time_base_after_k_messages():
    gate = StampGate()
    for k in range(20):
        gate.admit(T0 + k * S)
    new = T0 + 10_000 * S
    for k in range(K - 1):
        with pytest.raises(ma.MessageError):
            gate.admit(new + k * S)
    assert gate.admit(new + (K - 1) * S) == NEW_BASE
    assert gate.newest_ns == new + (K - 1) * S and gate.time_base_changes == 1
    assert gate.admit(new + K * S) == ADVANCE
    with pytest.raises(ma.MessageError):                    # the old stream is the jump now
        gate.admit(T0 + 21 * S)


def test_gate_takes_a_new_time_base_only_once_it_has_been_received_for_a_while():
    """A burst of consistent far stamps arriving within milliseconds (garbage, a replayed
    buffer) is not a new clock: the run must also span NEW_TIME_BASE_SPAN_S of receipt
    time, and the stream that goes on afterwards is never interrupted."""
    span = lim.NEW_TIME_BASE_SPAN_S
    gate = StampGate()
    for k in range(20):
        assert gate.admit(T0 + k * S, received_s=100.0 + k) == ADVANCE
    future = T0 + 10_000 * S
    for k in range(3 * K):               # three times the messages, within 10 ms
        with pytest.raises(ma.MessageError):
            gate.admit(future + k * 1000, received_s=119.0 + k * span / 1000)
    assert gate.admit(T0 + 20 * S, received_s=120.0) == ADVANCE
    assert gate.time_base_changes == 0
    # A clock that keeps sending the new base: adopted at the first message at least
    # NEW_TIME_BASE_SPAN_S after its run began (and after K messages).
    verdicts = []
    for k in range(3 * K):
        try:
            verdicts.append(gate.admit(future + k * S, received_s=121.0 + k * span / 4))
        except ma.MessageError:
            verdicts.append('refused')
    first = verdicts.index(NEW_BASE)
    assert first == max(K - 1, 4) and verdicts[first + 1:] == [ADVANCE] * (3 * K - first - 1)


def test_gate_rewind_within_the_window_is_a_new_time_base_too():
    """A bag replayed again: its stamps are behind the stream (out of order for the node)
    but consistent with each other, so the node is not blocked for the length of the bag."""
    gate = StampGate()
    for k in range(30):
        gate.admit(T0 + k * S)
    verdicts = [gate.admit(T0 + k * S) for k in range(K)]
    assert verdicts == [BEHIND] * (K - 1) + [NEW_BASE]


def test_gate_never_adopts_scattered_or_interrupted_garbage():
    gate = StampGate()
    rng = np.random.default_rng(0)
    t = T0
    for _ in range(200):
        t += S // 10
        assert gate.admit(t) == ADVANCE
        for _ in range(K - 1):           # up to K-1 consistent jumps between valid ones
            with pytest.raises(ma.MessageError):
                gate.admit(t + int(rng.integers(2, 50)) * W)
    for _ in range(50):                  # jumps that do not agree with each other
        with pytest.raises(ma.MessageError):
            gate.admit(t + int(rng.choice([-1, 1])) * int(rng.integers(2, 10 ** 6)) * W)
    assert gate.time_base_changes == 0 and gate.newest_ns == t


def test_gate_reset_takes_the_next_stamp_as_the_start():
    gate = StampGate()
    gate.admit(T0)
    gate.reset()
    assert gate.admit(T0 + 100 * W) == ADVANCE and gate.newest_ns == T0 + 100 * W


# =================================================================== input losses
def test_sequence_gaps_count_lost_messages_per_publisher():
    gaps = SequenceGaps()
    assert [gaps.observe(n) for n in (1, 2, 3, 7, 8)] == [0, 0, 0, 3, 0]
    # A second publisher (numbers below the first's), interleaved; one loss each.
    assert [gaps.observe(n) for n in (1, 9, 2, 11, 4, 12)] == [0, 0, 0, 1, 1, 0]
    # A restarted publisher starts again at 1; middleware without numbers gives 0/None.
    assert [gaps.observe(n) for n in (1, 2, None, 0, 3)] == [0, 0, 0, 0, 0]


# ===================================================================== ROS graph
def _overrides(**values):
    from rclpy.parameter import Parameter
    return [Parameter(k, value=v) for k, v in values.items()]


@pytest.fixture(scope='module')
def short_drive():
    from gnsscam_ros.datasets.emulated.drive import make_emulated_drive
    d = make_emulated_drive(21, faults=0, duration_s=6.0)
    f32 = ('var_m2', 'cn0_dbhz', 'elevation_deg')       # FLOAT32 on the wire
    d.gnss = [GnssEpoch(**{**e.__dict__, **{k: np.float32(getattr(e, k)).astype(float)
                                            for k in f32}}) for e in d.gnss]
    return d


def _stamped(msg, sec, nanosec=0):
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
    return msg


def _garbage(epoch, dr_state):
    """One malformed message of every kind of the fault campaign: ``(topic, message,
    node, reason)``; ``message`` is a message or serialised bytes."""
    from nav_msgs.msg import Odometry  # noqa: F401 - the type of the dead-reckoning topic
    gnss, t = ma.gnss_epoch_to_pointcloud2, epoch.stamp_ns
    sv = epoch.sv_pos_ecef_m.copy()
    sv[0, 2] = 1e160
    bad_sv = _with(epoch, sv_pos_ecef_m=sv)
    many = _with(epoch, stamp_ns=t, **{
        name: np.resize(getattr(epoch, name), (1000,) + getattr(epoch, name).shape[1:])
        for name in ('sv_pos_ecef_m', 'pr_m', 'var_m2', 'sv_id', 'system', 'elevation_deg',
                     'cn0_dbhz')})
    twist = ma.sample_to_twist(ma.TwistSample(t, 1.7e308, 0.0))
    dr_far = ma.dead_reckoning_to_odometry(dr_state)
    dr_far.pose.pose.position.x = 1e300
    match_far = ma.matches_to_pointcloud2(ma.CameraMatches(t, np.array([[1e300, 0.0, 0.0]]),
                                                           np.ones(1), np.zeros(1, int)))
    big_image = Image(header=ma.make_header(t, 'camera'), height=8000, width=8000,
                      encoding='bgr8', step=24000)        # the header of an 8000 x 8000 frame
    imu_far = ma.sample_to_imu(ma.ImuSample(t, np.array([1e300, 0.0, 9.8]), np.zeros(3)))
    undecodable = b'\x00\x01\x00\x00' + b'\xff' * 24
    # Values inside every range that are still no valid message: a negative variance, a
    # frame the topic is not in, a satellite twice or of no known system on the checked
    # link, an orientation that is no rotation.
    twist_negative_var = ma.sample_to_twist(ma.TwistSample(t, 1.0, 0.0, -1.0, -1.0))
    match_moved = ma.matches_to_pointcloud2(ma.CameraMatches(
        t, np.zeros((1, 3)), np.ones(1), np.zeros(1, int)))
    match_moved.header.frame_id = 'earth'
    twice = gnss(_with(epoch, sv_id=np.r_[epoch.sv_id[:-1], epoch.sv_id[0]],
                       system=np.r_[epoch.system[:-1], epoch.system[0]]))
    unknown = gnss(_with(epoch, system=np.full(epoch.n_sv, 99)))
    dr_spin = ma.dead_reckoning_to_odometry(dr_state)
    dr_spin.pose.pose.orientation.z = 1e300
    dr_moved = ma.dead_reckoning_to_odometry(dr_state)
    dr_moved.header.frame_id = 'map'
    out = []
    for topic, node in (('gnss/pseudoranges', 'gnss_node'),
                        ('gnss/measurements', 'fusion_node')):
        out += [(topic, _stamped(gnss(epoch), 2 ** 31 - 1), node, 'stamp_jump'),
                (topic, _stamped(gnss(epoch), 5, 2 ** 32 - 1), node, 'stamp'),
                (topic, _stamped(gnss(epoch), -1), node, 'stamp'),
                (topic, gnss(bad_sv), node, 'range'),
                (topic, gnss(many), node, 'size'),
                (topic, undecodable, node, 'undecodable')]
    out += [('odom/twist', twist, 'imu_node', 'range'),
            ('odom/twist', twist, 'imu_node', 'range'),
            ('odom/twist', _stamped(ma.sample_to_twist(ma.TwistSample(t, 1.0, 0.0)),
                                    2 ** 31 - 1, 2 ** 32 - 1), 'imu_node', 'stamp'),
            ('odom/twist', _stamped(ma.sample_to_twist(ma.TwistSample(t, 1.0, 0.0)),
                                    2 ** 31 - 1), 'imu_node', 'stamp_jump'),
            ('imu/data', imu_far, 'imu_node', 'range'),
            ('odometry/dead_reckoning', dr_far, 'fusion_node', 'range'),
            ('odom/twist', twist_negative_var, 'imu_node', 'range'),
            ('camera/matches', match_moved, 'fusion_node', 'frame'),
            ('gnss/measurements', twice, 'fusion_node', 'duplicate_satellites'),
            ('gnss/measurements', unknown, 'fusion_node', 'unknown_system'),
            ('odometry/dead_reckoning', dr_spin, 'fusion_node', 'range'),
            ('odometry/dead_reckoning', dr_moved, 'fusion_node', 'frame'),
            ('camera/matches', match_far, 'fusion_node', 'range'),
            ('camera/image_raw', big_image, 'camera_node', 'size'),
            ('camera/image_raw', _stamped(ma.array_to_image(np.zeros((64, 64), np.uint8), t),
                                          -3), 'camera_node', 'stamp'),
            ('camera/image_raw', undecodable, 'camera_node', 'undecodable')]
    return out


def _run_graph(drive, with_garbage: bool):
    """The nodes on an odometry + GNSS stream in lock step (each message handled before
    the next), malformed messages of every kind injected after the third epoch; the
    outputs per epoch and the nodes' diagnostics."""
    from ros_harness import RosGraph
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseWithCovarianceStamped, TwistWithCovarianceStamped
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import Imu

    from gnsscam_ros.nodes.camera_node import CameraNode
    from gnsscam_ros.nodes.fusion_node import FusionNode
    from gnsscam_ros.nodes.gnss_node import GnssNode
    from gnsscam_ros.nodes.imu_node import ImuNode

    g = RosGraph()
    try:
        nodes = {
            'gnss_node': g.add(GnssNode(context=g.ctx)),
            'imu_node': g.add(ImuNode(context=g.ctx, parameter_overrides=_overrides(
                source_timeout_s=60.0))),
            'camera_node': g.add(CameraNode(context=g.ctx)),
            'fusion_node': g.add(FusionNode(context=g.ctx, parameter_overrides=_overrides(
                n_particles=200, seed=7, use_map_origin=True,
                map_origin_llh=list(drive.origin_llh), gnss_timeout_s=60.0,
                odometry_wait_s=10.0, odometry_timeout_s=60.0)))}
        fusion = nodes['fusion_node']
        types = {'gnss/pseudoranges': PointCloud2, 'gnss/measurements': PointCloud2,
                 'odom/twist': TwistWithCovarianceStamped, 'imu/data': Imu,
                 'odometry/dead_reckoning': Odometry, 'camera/matches': PointCloud2,
                 'camera/image_raw': Image}
        pubs = {topic: g.publisher(t, topic) for topic, t in types.items()}
        received = {topic: (nodes[node], node_input.received)
                    for node in nodes for topic, node_input in nodes[node].inputs.items()}
        risks = g.collect(DiagnosticArray, 'integrity_risk')
        poses = g.collect(PoseWithCovarianceStamped, 'pose')
        diagnostics = g.collect(DiagnosticArray, 'diagnostics')
        g.connect(*pubs.values())
        g.spin_until(lambda: nodes['gnss_node'].pub_measurements.get_subscription_count() > 0
                     and nodes['imu_node'].pub.get_subscription_count() > 0,
                     what='internal connections')

        def send(topic, msg):
            node, key = received[topic]
            n = node.stats.get(key)
            pubs[topic].publish(msg)
            g.spin_until(lambda: node.stats.get(key) > n, what=f'{topic} received')

        odo = drive.odometry
        k_odo, results = 0, []
        for i, epoch in enumerate(drive.gnss):
            t = epoch.stamp_ns
            while k_odo < len(odo.stamp_ns) and odo.stamp_ns[k_odo] <= t:
                send('odom/twist', ma.sample_to_twist(ma.TwistSample(
                    int(odo.stamp_ns[k_odo]), odo.speed_mps[k_odo], odo.yaw_rate_rps[k_odo],
                    odo.speed_var[k_odo], odo.yaw_rate_var[k_odo])))
                k_odo += 1
            g.spin_until(lambda: (fusion.engine.motion.newest_stamp_ns or -1) >= t
                         or i == 0, what='dead reckoning at the epoch')
            if with_garbage and i == 3:
                dr = fusion.engine.motion.states[-1]
                for topic, msg, _, _ in _garbage(epoch, dr):
                    send(topic, msg)
            send('gnss/pseudoranges', ma.gnss_epoch_to_pointcloud2(epoch))
            g.spin_until(lambda: fusion.last_result is not None
                         and fusion.last_result.stamp_ns == t, what='the filter epoch')
            g.spin_until(lambda: any(ma.parse_integrity_risk(m).epoch_stamp_ns == t
                                     for m in risks), what='integrity_risk of the epoch')
            results.append(fusion.last_result.status)
        # Reports made now, after everything was handled (a periodic one from before
        # would miss the last counts).
        n_before = len(diagnostics)
        for node in nodes.values():
            node.publish_diagnostics()
        g.spin_until(lambda: {s.name for m in diagnostics[n_before:] for s in m.status}
                     >= {f'{n}: status' for n in nodes}, what='diagnostics')
        latest = {s.name.split(':')[0]: ma.status_values(s) for m in diagnostics[n_before:]
                  for s in m.status if s.name.endswith(': status')}
        outputs = {
            'status': results,
            'pose': {ma.stamp_to_ns(m.header.stamp): ma.msg_to_pose(m) for m in poses},
            'risk': {r.epoch_stamp_ns: (r.level, r.risk_bound) for r in
                     (ma.parse_integrity_risk(m) for m in risks)}}
        return outputs, latest, {name: dict(n.stats.rejected) for name, n in nodes.items()}
    finally:
        g.close()


@pytest.mark.slow
@pytest.mark.ros
def test_single_malformed_messages_are_refused_counted_and_change_no_output(short_drive):
    clean, _, clean_rejected = _run_graph(short_drive, with_garbage=False)
    dirty, diagnostics, rejected = _run_graph(short_drive, with_garbage=True)
    assert clean['status'] == dirty['status'] and len(clean['status']) == 7
    assert clean['status'].count('updated') >= 5, clean['status']
    expected: dict = {}
    dr_dummy = DeadReckoningState(T0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    for _, _, node, reason in _garbage(short_drive.gnss[3], dr_dummy):
        expected.setdefault(node, {}).setdefault(reason, 0)
        expected[node][reason] += 1
    for node, reasons in expected.items():
        got = {k: v - clean_rejected[node].get(k, 0) for k, v in rejected[node].items()}
        assert {k: v for k, v in got.items() if v} == reasons, (node, rejected[node])
        values = diagnostics[node]
        for reason, n in reasons.items():
            assert int(values[f'rejected_{reason}']) == n + clean_rejected[node].get(reason, 0)
    # Every later output is the clean run's: same poses, same integrity verdicts (the last
    # epoch's pose is published after its verdict, which is what the run waits for: it may
    # not have arrived when the outputs are taken).
    last = short_drive.gnss[-1].stamp_ns
    common = clean['pose'].keys() & dirty['pose'].keys()
    assert (clean['pose'].keys() ^ dirty['pose'].keys()) <= {last} and len(common) >= 5
    # To rounding: numpy 1.24's SIMD reductions may depend on the arrays' alignment, so
    # two runs of the same code may differ in the last bit (seen once in a covariance);
    # a refused message that reached the filter would move the estimate by metres.
    for stamp in common:
        pose = clean['pose'][stamp]
        np.testing.assert_allclose(dirty['pose'][stamp].position_m, pose.position_m,
                                   rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(dirty['pose'][stamp].covariance, pose.covariance,
                                   rtol=1e-12, atol=1e-9)
    assert (clean['risk'].keys() ^ dirty['risk'].keys()) <= {last}
    for stamp in clean['risk'].keys() & dirty['risk'].keys():
        level, bound = clean['risk'][stamp]
        other_level, other_bound = dirty['risk'][stamp]
        assert other_level == level
        assert other_bound == bound or (math.isnan(bound) and math.isnan(other_bound))


def no_receipt_span(node) -> None:
    """Let the node's stamp gates adopt a new time base without a receipt span."""
    for handler in node.inputs.values():
        handler.gate.span_s = 0.0


@pytest.mark.slow
@pytest.mark.ros
def test_a_replay_started_again_is_a_new_time_base_not_a_permanent_block(graph, short_drive):
    from gnsscam_ros.nodes.gnss_node import GnssNode
    g = graph
    gnss = g.add(GnssNode(context=g.ctx))
    # The passes are published as fast as they go: no receipt span (the gate's own test
    # holds the span rule).
    no_receipt_span(gnss)
    pub = g.publisher(PointCloud2, 'gnss/pseudoranges')
    g.connect(pub)
    epochs = short_drive.gnss
    assert len(epochs) > K

    def play(sequence):
        for epoch in sequence:
            n = gnss.stats.get('received_pseudoranges')
            pub.publish(ma.gnss_epoch_to_pointcloud2(epoch))
            g.spin_until(lambda: gnss.stats.get('received_pseudoranges') > n)

    for rewind in range(3):
        play(epochs)
        # The stamps of a pass repeat the previous one: the first K-1 are out of order
        # (within the window) and the K-th makes the new time base.
        assert gnss.stats.get('time_base_changed') == rewind
        assert gnss.stats.rejected.get('out_of_order', 0) == rewind * (K - 1)
        assert gnss.stats.get('published_measurements') == len(epochs) + rewind * (
            len(epochs) - K + 1)
    # Far in the past (another recording): refused as jumps, then adopted the same way.
    old = [_with(e, stamp_ns=e.stamp_ns - 10 ** 6 * S) for e in epochs]
    play(old)
    assert gnss.stats.rejected.get('stamp_jump') == K - 1
    assert gnss.stats.get('time_base_changed') == 3


@pytest.mark.slow
@pytest.mark.ros
def test_fusion_resets_its_engine_on_a_new_time_base(graph, short_drive):
    from gnsscam_ros.nodes.fusion_node import FusionNode
    g = graph
    fusion = g.add(FusionNode(context=g.ctx, parameter_overrides=_overrides(n_particles=50)))
    no_receipt_span(fusion)
    pub = g.publisher(PointCloud2, 'gnss/measurements')
    g.connect(pub)

    def play(sequence):
        for epoch in sequence:
            n = fusion.stats.get('received_measurements')
            pub.publish(ma.gnss_epoch_to_pointcloud2(epoch))
            g.spin_until(lambda: fusion.stats.get('received_measurements') > n)

    epochs = short_drive.gnss[:K + 1]
    play(epochs)
    play(epochs)
    assert fusion.stats.get('time_base_changed') == 1
    # The engine dropped what it held of the old time base and waits for a new fix.
    assert fusion.engine.counts.get('time_base_resets') == 1
    calls = []
    fusion.engine.reset_time_base = calls.append
    play(epochs)
    assert fusion.stats.get('time_base_changed') == 2
    assert calls == [f'gnss/measurements: new time base at {epochs[K - 1].stamp_ns} ns']


@pytest.mark.slow
@pytest.mark.ros
def test_messages_overwritten_in_a_full_input_queue_are_counted(graph, short_drive):
    """fusion_node's gnss/measurements queue holds 10 messages: while its executor does not
    take them (a slow epoch), older ones are overwritten; every message is either received
    or counted as lost."""
    from rclpy.duration import Duration

    from gnsscam_ros.nodes.fusion_node import FusionNode
    g = graph
    fusion = g.add(FusionNode(context=g.ctx, parameter_overrides=_overrides(
        n_particles=50, input_queue_depth=10)))
    pub = g.publisher(PointCloud2, 'gnss/measurements')
    g.connect(pub)
    epoch = short_drive.gnss[0]
    # One message taken first: the count starts at the first message seen (one published
    # before the subscription matched is not a loss).
    pub.publish(ma.gnss_epoch_to_pointcloud2(epoch))
    g.spin_until(lambda: fusion.stats.get('received_measurements') == 1)
    n = 40
    for k in range(1, n + 1):            # no spinning: nothing is taken meanwhile
        pub.publish(ma.gnss_epoch_to_pointcloud2(_with(epoch, stamp_ns=epoch.stamp_ns + k * S)))
    # Acknowledged by the subscription: all in its queue, which kept the newest 10.
    assert pub.wait_for_all_acked(Duration(seconds=20))
    key = 'lost_gnss/measurements'
    g.spin_until(lambda: fusion.stats.get('received_measurements') + fusion.stats.get(key)
                 == n + 1, what='every message received or counted lost')
    assert fusion.stats.get(key) == n - 10
    fusion.publish_diagnostics()
    assert fusion.stats.values()[key] == fusion.stats.get(key)


@pytest.mark.slow
@pytest.mark.ros
def test_a_publisher_with_an_incompatible_qos_is_counted(graph):
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from gnsscam_ros.nodes.fusion_node import FusionNode
    g = graph
    fusion = g.add(FusionNode(context=g.ctx, parameter_overrides=_overrides(n_particles=50)))
    best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
    g.probe.create_publisher(PointCloud2, 'gnss/measurements', best_effort)
    key = 'qos_incompatible_gnss/measurements'
    g.spin_until(lambda: fusion.stats.get(key) >= 1, 20.0, key)
    assert key in fusion.stats.values()


# ================================================================== exit codes
_FAULTY = '''
import sys
from gnsscam_ros.nodes import {module}
from gnsscam_ros.nodes.camera_node import CameraNode
from gnsscam_ros.nodes.gnss_node import GnssNode


def boom(self, *args):
    raise RuntimeError('injected fault')


{patches}
sys.exit({module}.main())
'''


@pytest.mark.slow
@pytest.mark.ros
@pytest.mark.parametrize('module, patches, topic', [
    # camera_node's matcher thread dies (no callback raises): the node fails itself.
    ('pipeline', 'CameraNode.process = CameraNode._answer_unmatched = boom',
     'camera/image_raw'),
    ('camera_node', 'CameraNode.process = CameraNode._answer_unmatched = boom',
     'camera/image_raw'),
    # A callback raises in one of pipeline_node's nodes.
    ('pipeline', 'GnssNode.on_epoch = boom', 'gnss/pseudoranges'),
])
def test_a_node_that_fails_while_running_exits_1(tmp_path, module, patches, topic):
    import subprocess
    import sys
    from pathlib import Path

    from ros_harness import RosGraph, ros_env, stop
    root = Path(__file__).resolve().parents[1]
    script = tmp_path / 'faulty.py'
    script.write_text(_FAULTY.format(module=module, patches=patches))
    probe = RosGraph()
    err = tmp_path / 'stderr.txt'
    with open(err, 'w') as stderr:
        proc = subprocess.Popen([sys.executable, str(script)], cwd=root, stderr=stderr,
                                stdout=subprocess.DEVNULL,
                                env=ros_env(tmp_path, probe.domain))
    try:
        if topic == 'camera/image_raw':
            pub = probe.publisher(Image, topic)
            msg = ma.array_to_image(np.zeros((64, 64), np.uint8), T0)
        else:
            pub = probe.publisher(PointCloud2, topic)
            msg = ma.gnss_epoch_to_pointcloud2(_epoch())
        probe.spin_until(lambda: pub.get_subscription_count() > 0 or proc.poll() is not None,
                         60.0, 'the node subscribing')
        # Best effort input: sent again until the node has it (and fails).
        probe.spin_until(lambda: proc.poll() is not None or pub.publish(msg), 60.0,
                         'the node failing')
    finally:
        probe.close()
        rc = stop(proc)
    text = err.read_text()
    assert rc == 1, text
    assert 'injected fault' in text
