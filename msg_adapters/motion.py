"""IMU, odometry twist and dead-reckoning messages <-> the core's samples and states.

* ``imu/data`` (``sensor_msgs/Imu``): body x forward, z up; the dead reckoning uses the
  forward acceleration and the yaw rate (gyro z). Any frame name (the sensor's mounting
  is the installation's; the axes are taken as the vehicle's).
* ``odom/twist`` (``geometry_msgs/TwistWithCovarianceStamped``): forward speed
  ``linear.x`` [m/s] and yaw rate ``angular.z`` [rad/s]; variances at covariance indices 0
  and 35 (0: not reported). Any frame name (the vehicle's, whatever it is called).
* ``odometry/dead_reckoning`` (``nav_msgs/Odometry``, frame ``odom``, child ``base_link``;
  other frames are refused, ``'frame'``):
  the planar dead-reckoned pose; pose covariance x and y carry the accumulated
  travelled-distance variance, yaw the accumulated heading variance; twist is the current
  speed and yaw rate with their variances. Consecutive messages give the motion between
  them (:func:`gnsscam_ros.core.motion.motion_between`).
* ``odometry/global`` (``nav_msgs/Odometry``, frame ``map``, child ``base_link``): the fused
  estimate for robot_localization / Nav2 consumers (:class:`GlobalOdometry`): pose and 6x6
  covariance as ``pose``; twist in the child frame: forward speed ``linear.x`` and yaw rate
  ``angular.z`` from the dead reckoning, variances at twist covariance 0 and 35; the axes
  the package does not estimate (roll, pitch; lateral and vertical speed, roll and pitch
  rates) carry :data:`UNESTIMATED_VAR`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from gnsscam_ros.core.motion import DeadReckoningState

from .checks import (check_abs, check_covariance, check_finite, check_frame,
                     check_unit_quaternion)
from .errors import MessageError
from .geometry import UNESTIMATED_VAR, quaternion_to_yaw, yaw_to_quaternion
from .message_classes import RCLPY, MessageKit
from .limits import (MAX_ACCEL_MPS2, MAX_GYRO_RPS, MAX_POSITION_M, MAX_SPEED_MPS,
                     MAX_MESSAGE_YAW_RATE_RPS)
from .stamps import make_header, ns_to_stamp, stamp_to_ns
from .wire import (BASE_FRAME, DEAD_RECKONING, IMU, IMU_FRAME, MAP_FRAME, ODOM_FRAME,
                   ODOMETRY_GLOBAL, TWIST)

if TYPE_CHECKING:                  # ROS messages: looked up in RCLPY where built, so that
    # the bag tools and the evaluation import this package without ROS 2 installed.
    from geometry_msgs.msg import TwistWithCovarianceStamped
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import Imu


@dataclass(frozen=True)
class ImuSample:
    """One IMU sample.

    Attributes:
        stamp_ns: Stamp [ns].
        accel_mps2: (3,) specific force, body frame [m/s^2].
        gyro_rps: (3,) angular rate, body frame [rad/s].
    """

    stamp_ns: int
    accel_mps2: np.ndarray
    gyro_rps: np.ndarray


@dataclass(frozen=True)
class TwistSample:
    """One odometry speed and yaw-rate sample.

    Attributes:
        stamp_ns: Stamp [ns].
        speed_mps: Forward speed [m/s].
        yaw_rate_rps: Yaw rate [rad/s].
        speed_var: Speed variance [(m/s)^2] (<= 0: not reported).
        yaw_rate_var: Yaw-rate variance [(rad/s)^2] (<= 0: not reported).
    """

    stamp_ns: int
    speed_mps: float
    yaw_rate_rps: float
    speed_var: float = 0.0
    yaw_rate_var: float = 0.0


def imu_to_sample(msg: Imu, what: str = IMU) -> ImuSample:
    """Imu -> :class:`ImuSample`.

    The orientation is not used; when the message reports one (orientation covariance
    element 0 is not REP 145's -1 "no estimate") it must be a unit quaternion with a
    covariance, as the other two covariances must be (:func:`.checks.check_covariance`).

    Raises:
        MessageError: A message declaring its angular velocity or linear acceleration
            unavailable (covariance[0] == -1, REP 145; ``'value'``), an invalid stamp,
            non-finite rates or accelerations, or ones beyond the sensor and vehicle
            limits of :mod:`.limits` (``'range'``: any axis beyond
            :data:`.limits.MAX_ACCEL_MPS2` or :data:`.limits.MAX_GYRO_RPS`, the yaw rate
            beyond :data:`.limits.MAX_MESSAGE_YAW_RATE_RPS`), a covariance that is none or a
            reported orientation that is no rotation (``'range'``, ``'non_finite'``).
    """
    if msg.angular_velocity_covariance[0] == -1.0:
        raise MessageError(f'{what}: angular velocity marked unavailable', 'value')
    if msg.linear_acceleration_covariance[0] == -1.0:
        raise MessageError(f'{what}: linear acceleration marked unavailable', 'value')
    stamp_ns = stamp_to_ns(msg.header.stamp, what)
    a, g = msg.linear_acceleration, msg.angular_velocity
    accel = np.array([a.x, a.y, a.z], dtype=float)
    gyro = np.array([g.x, g.y, g.z], dtype=float)
    if not (np.all(np.isfinite(accel)) and np.all(np.isfinite(gyro))):
        raise MessageError(f'{what}: non-finite acceleration or angular velocity',
                           'non_finite')
    check_abs(what, 'acceleration', accel, MAX_ACCEL_MPS2, ' m/s^2')
    check_abs(what, 'angular velocity', gyro, MAX_GYRO_RPS, ' rad/s')
    check_abs(what, 'yaw rate', gyro[2], MAX_MESSAGE_YAW_RATE_RPS, ' rad/s')
    check_covariance(what, 'angular velocity covariance', msg.angular_velocity_covariance)
    check_covariance(what, 'linear acceleration covariance',
                     msg.linear_acceleration_covariance)
    if msg.orientation_covariance[0] != -1.0:
        o = msg.orientation
        check_unit_quaternion(what, 'orientation', o.x, o.y, o.z, o.w)
        check_covariance(what, 'orientation covariance', msg.orientation_covariance)
    return ImuSample(stamp_ns, accel, gyro)


def sample_to_imu(sample: ImuSample, frame_id: str = IMU_FRAME, kit: MessageKit = RCLPY):
    """:class:`ImuSample` -> Imu (of ``kit``, :mod:`.message_classes`): orientation marked
    unavailable (``orientation_covariance[0] = -1``, REP 145), the other covariances zero
    (unknown)."""
    a = np.asarray(sample.accel_mps2, dtype=float)
    g = np.asarray(sample.gyro_rps, dtype=float)
    vector = kit['geometry_msgs/msg/Vector3']
    orientation_cov = np.zeros(9)
    orientation_cov[0] = -1.0
    return kit['sensor_msgs/msg/Imu'](
        header=make_header(sample.stamp_ns, frame_id, kit),
        orientation=kit['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=orientation_cov,
        angular_velocity=vector(x=float(g[0]), y=float(g[1]), z=float(g[2])),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=vector(x=float(a[0]), y=float(a[1]), z=float(a[2])),
        linear_acceleration_covariance=np.zeros(9))


def twist_to_sample(msg: TwistWithCovarianceStamped, what: str = TWIST
                    ) -> TwistSample:
    """TwistWithCovarianceStamped -> :class:`TwistSample`.

    A variance of 0 means "not reported" (the dead reckoning then uses its default).

    Raises:
        MessageError: An invalid stamp, a non-finite twist, a speed or rate beyond
            :mod:`.limits` (``'range'``; the components a planar vehicle does not use
            too), or a covariance that is none (a negative variance, a correlation
            above 1; :func:`.checks.check_covariance`).
    """
    stamp_ns = stamp_to_ns(msg.header.stamp, what)
    t = msg.twist.twist
    cov = msg.twist.covariance
    _check_twist(what, t)
    check_covariance(what, 'twist covariance', cov)
    return TwistSample(stamp_ns, float(t.linear.x), float(t.angular.z),
                       float(cov[0]), float(cov[35]))


def _check_twist(what: str, t) -> None:
    """Every component of a vehicle's twist against :mod:`.limits`."""
    lin, ang = t.linear, t.angular
    check_finite(what, **{'speed or angular rate': [lin.x, lin.y, lin.z, ang.x, ang.y,
                                                    ang.z]})
    check_abs(what, 'speed', lin.x, MAX_SPEED_MPS, ' m/s')
    check_abs(what, 'lateral or vertical speed', [lin.y, lin.z], MAX_SPEED_MPS, ' m/s')
    check_abs(what, 'yaw rate', ang.z, MAX_MESSAGE_YAW_RATE_RPS, ' rad/s')
    check_abs(what, 'roll or pitch rate', [ang.x, ang.y], MAX_GYRO_RPS, ' rad/s')


def sample_to_twist(sample: TwistSample, frame_id: str = BASE_FRAME,
                    kit: MessageKit = RCLPY):
    """:class:`TwistSample` -> TwistWithCovarianceStamped (of ``kit``, :mod:`.message_classes`)."""
    vector = kit['geometry_msgs/msg/Vector3']
    cov = np.zeros(36)
    cov[0], cov[35] = sample.speed_var, sample.yaw_rate_var
    twist = kit['geometry_msgs/msg/Twist'](
        linear=vector(x=float(sample.speed_mps), y=0.0, z=0.0),
        angular=vector(x=0.0, y=0.0, z=float(sample.yaw_rate_rps)))
    return kit['geometry_msgs/msg/TwistWithCovarianceStamped'](
        header=make_header(sample.stamp_ns, frame_id, kit),
        twist=kit['geometry_msgs/msg/TwistWithCovariance'](twist=twist, covariance=cov))


def dead_reckoning_to_odometry(state: DeadReckoningState, frame_id: str = ODOM_FRAME,
                               child_frame_id: str = BASE_FRAME) -> Odometry:
    """:class:`DeadReckoningState` -> the ``odometry/dead_reckoning`` message.

    Raises:
        MessageError: Non-finite pose.
    """
    if not np.all(np.isfinite([state.x_m, state.y_m, state.yaw_rad])):
        raise MessageError('dead-reckoning pose must be finite', 'non_finite')
    msg = RCLPY['nav_msgs/msg/Odometry'](
        header=RCLPY['std_msgs/msg/Header'](stamp=ns_to_stamp(state.stamp_ns),
                                            frame_id=frame_id),
        child_frame_id=child_frame_id)
    msg.pose.pose.position.x = float(state.x_m)
    msg.pose.pose.position.y = float(state.y_m)
    msg.pose.pose.orientation = yaw_to_quaternion(state.yaw_rad)
    pose_cov = np.zeros(36)
    pose_cov[0] = pose_cov[7] = state.distance_var_m2
    pose_cov[21] = pose_cov[28] = UNESTIMATED_VAR
    pose_cov[35] = state.yaw_var_rad2
    msg.pose.covariance = pose_cov.tolist()
    msg.twist.twist.linear.x = float(state.speed_mps)
    msg.twist.twist.angular.z = float(state.yaw_rate_rps)
    twist_cov = np.zeros(36)
    twist_cov[0], twist_cov[35] = state.speed_var, state.yaw_rate_var
    msg.twist.covariance = twist_cov.tolist()
    return msg


def odometry_to_dead_reckoning(msg: Odometry, what: str = DEAD_RECKONING,
                               frame_id: str | None = ODOM_FRAME,
                               child_frame_id: str | None = BASE_FRAME
                               ) -> DeadReckoningState:
    """The ``odometry/dead_reckoning`` message -> :class:`DeadReckoningState`.

    The heading comes back wrapped to [-pi, pi]; :func:`motion_between` wraps differences.

    Args:
        msg: The message.
        what: Name used in error messages.
        frame_id: Required header frame, the dead reckoning's own (None: any).
        child_frame_id: Required child frame, the vehicle's (None: any).

    Raises:
        MessageError: Another frame or child frame (``'frame'``), an invalid stamp,
            non-finite values, a position beyond :data:`.limits.MAX_POSITION_M`, a speed
            or rate beyond the vehicle limits, an orientation that is no unit quaternion
            or a covariance that is none (a variance outside [0,
            :data:`.limits.MAX_VARIANCE`], a correlation above 1; ``'range'``).
    """
    check_frame(what, msg.header.frame_id, frame_id)
    check_frame(what, msg.child_frame_id, child_frame_id, 'child frame')
    stamp_ns = stamp_to_ns(msg.header.stamp, what)
    p, o = msg.pose.pose.position, msg.pose.pose.orientation
    pc, tc = msg.pose.covariance, msg.twist.covariance
    t = msg.twist.twist
    check_finite(what, position=[p.x, p.y, p.z])
    check_abs(what, 'position', [p.x, p.y, p.z], MAX_POSITION_M, ' m')
    _check_twist(what, t)
    check_unit_quaternion(what, 'orientation', o.x, o.y, o.z, o.w)
    check_covariance(what, 'pose covariance', pc)
    check_covariance(what, 'twist covariance', tc)
    return DeadReckoningState(
        stamp_ns=stamp_ns, x_m=float(p.x), y_m=float(p.y),
        yaw_rad=quaternion_to_yaw(msg.pose.pose.orientation), speed_mps=float(t.linear.x),
        yaw_rate_rps=float(t.angular.z), speed_var=float(tc[0]), yaw_rate_var=float(tc[35]),
        distance_var_m2=float(pc[0]), yaw_var_rad2=float(pc[35]))


# ---------------------------------------------------------------------- odometry/global
@dataclass(frozen=True)
class GlobalOdometry:
    """The fused estimate with the vehicle's velocity (``odometry/global``).

    Attributes:
        stamp_ns: Stamp (the GNSS epoch) [ns].
        position_m: (3,) east, north, up in ``frame_id`` [m].
        yaw_rad: Heading, counter-clockwise from east [rad].
        pose_covariance: (6, 6) over (x, y, z, roll, pitch, yaw) [m^2, rad^2].
        speed_mps: Forward speed, x of ``child_frame_id`` [m/s].
        yaw_rate_rps: Yaw rate, about z of ``child_frame_id`` [rad/s].
        speed_var: Variance of ``speed_mps`` [(m/s)^2].
        yaw_rate_var: Variance of ``yaw_rate_rps`` [(rad/s)^2].
        frame_id: Frame of the pose (``map``).
        child_frame_id: Frame of the twist (the vehicle, ``base_link``).
    """

    stamp_ns: int
    position_m: np.ndarray
    yaw_rad: float
    pose_covariance: np.ndarray
    speed_mps: float
    yaw_rate_rps: float
    speed_var: float
    yaw_rate_var: float
    frame_id: str = MAP_FRAME
    child_frame_id: str = BASE_FRAME


def global_odometry_to_msg(odom: GlobalOdometry) -> Odometry:
    """:class:`GlobalOdometry` -> the ``odometry/global`` message.

    Raises:
        MessageError: Non-finite pose or twist, or a pose covariance that is not 6x6.
    """
    pos = np.asarray(odom.position_m, dtype=float).reshape(3)
    cov = np.asarray(odom.pose_covariance, dtype=float)
    twist = [odom.speed_mps, odom.yaw_rate_rps, odom.speed_var, odom.yaw_rate_var]
    if not (np.all(np.isfinite(pos)) and np.isfinite(odom.yaw_rad)
            and np.all(np.isfinite(twist))):
        raise MessageError('odometry/global: pose and twist must be finite', 'non_finite')
    if cov.shape != (6, 6):
        raise MessageError(f'pose covariance shape {cov.shape}, expected (6, 6)', 'value')
    msg = RCLPY['nav_msgs/msg/Odometry'](
        header=RCLPY['std_msgs/msg/Header'](stamp=ns_to_stamp(odom.stamp_ns),
                                            frame_id=odom.frame_id),
        child_frame_id=odom.child_frame_id)
    p = msg.pose.pose.position
    p.x, p.y, p.z = (float(v) for v in pos)
    msg.pose.pose.orientation = yaw_to_quaternion(odom.yaw_rad)
    msg.pose.covariance = cov.reshape(-1).tolist()
    msg.twist.twist.linear.x = float(odom.speed_mps)
    msg.twist.twist.angular.z = float(odom.yaw_rate_rps)
    twist_cov = np.diag([odom.speed_var, UNESTIMATED_VAR, UNESTIMATED_VAR, UNESTIMATED_VAR,
                         UNESTIMATED_VAR, odom.yaw_rate_var])
    msg.twist.covariance = twist_cov.reshape(-1).tolist()
    return msg


def odometry_to_global(msg: Odometry, what: str = ODOMETRY_GLOBAL) -> GlobalOdometry:
    """The ``odometry/global`` message -> :class:`GlobalOdometry`.

    Raises:
        MessageError: Non-finite position or twist, or an invalid orientation.
    """
    p = msg.pose.pose.position
    t = msg.twist.twist
    tc = msg.twist.covariance
    pos = np.array([p.x, p.y, p.z], dtype=float)
    if not np.all(np.isfinite([*pos, t.linear.x, t.angular.z, tc[0], tc[35]])):
        raise MessageError(f'{what}: non-finite pose or twist', 'non_finite')
    return GlobalOdometry(
        stamp_ns=stamp_to_ns(msg.header.stamp), position_m=pos,
        yaw_rad=quaternion_to_yaw(msg.pose.pose.orientation),
        pose_covariance=np.array(msg.pose.covariance, dtype=float).reshape(6, 6),
        speed_mps=float(t.linear.x), yaw_rate_rps=float(t.angular.z),
        speed_var=float(tc[0]), yaw_rate_var=float(tc[35]), frame_id=msg.header.frame_id,
        child_frame_id=msg.child_frame_id)
