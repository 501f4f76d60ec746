"""Pose, particle cloud and WGS84 fix messages <-> numpy.

* ``pose``: ``geometry_msgs/PoseWithCovarianceStamped``, frame ``map`` (local ENU); the 6x6
  covariance is (x, y, z, roll, pitch, yaw); roll and pitch are not estimated and carry
  :data:`UNESTIMATED_VAR`.
* ``particles``: ``geometry_msgs/PoseArray``, one pose per particle (east, north, up, yaw).
* ``fix``, ``gnss/fix``: ``sensor_msgs/NavSatFix``; covariance in the ENU order of the
  message definition [m^2].
* ``ground_truth/pose``: ``geometry_msgs/PoseStamped`` (:func:`pose_stamped`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .errors import MessageError
from .message_classes import RCLPY, MessageKit
from .stamps import make_header, ns_to_stamp, stamp_to_ns
from .wire import (ANTENNA_FRAME, COVARIANCE_TYPE_KNOWN, COVARIANCE_TYPE_UNKNOWN, FIX,
                   MAP_FRAME, POSE, SERVICE_GPS, STATUS_FIX, split_ns)

if TYPE_CHECKING:                  # ROS messages: looked up in RCLPY where built, so that
    # the bag tools and the evaluation import this package without ROS 2 installed.
    from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped, Quaternion

UNESTIMATED_VAR = 1e6     # variance of the pose axes the filter does not estimate [rad^2]


def yaw_to_quaternion(yaw_rad: float, kit: MessageKit = RCLPY):
    """Rotation about z by ``yaw_rad`` [rad] as a unit quaternion."""
    half = 0.5 * float(yaw_rad)
    return kit['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=float(np.sin(half)),
                                               w=float(np.cos(half)))


def quaternion_to_yaw(q: Quaternion) -> float:
    """Heading (rotation about z, ZYX convention) of a quaternion [rad], in [-pi, pi].

    Raises:
        MessageError: Non-finite or zero-norm quaternion.
    """
    x, y, z, w = float(q.x), float(q.y), float(q.z), float(q.w)
    if not np.all(np.isfinite([x, y, z, w])) or x * x + y * y + z * z + w * w < 1e-12:
        raise MessageError(f'invalid quaternion {(x, y, z, w)}', 'non_finite')
    # w^2 + x^2 - y^2 - z^2, not 1 - 2 (y^2 + z^2): the heading of a quaternion that is
    # only near unit length (tf2 accepts |q|^2 within 1e-2) is that of its normalised form.
    return float(np.arctan2(2.0 * (w * z + x * y), w * w + x * x - y * y - z * z))


# ------------------------------------------------------------------------------ pose
@dataclass(frozen=True)
class PoseEstimate:
    """A pose with covariance.

    Attributes:
        stamp_ns: Stamp [ns].
        position_m: (3,) east, north, up in ``frame_id`` [m].
        yaw_rad: Heading, counter-clockwise from east [rad].
        covariance: (6, 6) over (x, y, z, roll, pitch, yaw) [m^2, rad^2].
        frame_id: Frame.
    """

    stamp_ns: int
    position_m: np.ndarray
    yaw_rad: float
    covariance: np.ndarray
    frame_id: str = MAP_FRAME

    @property
    def position_covariance_m2(self) -> np.ndarray:
        """(3, 3) position block [m^2]."""
        return self.covariance[:3, :3]


def pose_to_msg(estimate: PoseEstimate) -> PoseWithCovarianceStamped:
    """:class:`PoseEstimate` -> PoseWithCovarianceStamped.

    Raises:
        MessageError: Non-finite position or heading, or a covariance that is not 6x6.
    """
    pos = np.asarray(estimate.position_m, dtype=float).reshape(3)
    cov = np.asarray(estimate.covariance, dtype=float)
    if not (np.all(np.isfinite(pos)) and np.isfinite(estimate.yaw_rad)):
        raise MessageError('pose must be finite', 'non_finite')
    if cov.shape != (6, 6):
        raise MessageError(f'covariance shape {cov.shape}, expected (6, 6)', 'value')
    msg = RCLPY['geometry_msgs/msg/PoseWithCovarianceStamped']()
    msg.header = RCLPY['std_msgs/msg/Header'](stamp=ns_to_stamp(estimate.stamp_ns),
                                              frame_id=estimate.frame_id)
    msg.pose.pose.position.x, msg.pose.pose.position.y, msg.pose.pose.position.z = (
        float(v) for v in pos)
    msg.pose.pose.orientation = yaw_to_quaternion(estimate.yaw_rad)
    msg.pose.covariance = cov.reshape(-1).tolist()
    return msg


def pose_covariance(position_cov_m2: np.ndarray, yaw_var_rad2: float) -> np.ndarray:
    """(6, 6) pose covariance from a (3, 3) position block and a heading variance."""
    cov = np.zeros((6, 6))
    cov[:3, :3] = position_cov_m2
    cov[3, 3] = cov[4, 4] = UNESTIMATED_VAR
    cov[5, 5] = yaw_var_rad2
    return cov


def msg_to_pose(msg: PoseWithCovarianceStamped, what: str = POSE) -> PoseEstimate:
    """PoseWithCovarianceStamped -> :class:`PoseEstimate`.

    Raises:
        MessageError: Non-finite position or orientation.
    """
    p = msg.pose.pose.position
    pos = np.array([p.x, p.y, p.z], dtype=float)
    if not np.all(np.isfinite(pos)):
        raise MessageError(f'{what}: non-finite position', 'non_finite')
    return PoseEstimate(stamp_ns=stamp_to_ns(msg.header.stamp), position_m=pos,
                        yaw_rad=quaternion_to_yaw(msg.pose.pose.orientation),
                        covariance=np.array(msg.pose.covariance, dtype=float).reshape(6, 6),
                        frame_id=msg.header.frame_id)


# ------------------------------------------------------------------------- particles
#: CDR encapsulation header of a little-endian plain-CDR message (what rmw publishes).
_CDR_LE = b'\x00\x01\x00\x00'


def particles_to_posearray_cdr(particles: np.ndarray, stamp_ns: int,
                               frame_id: str = MAP_FRAME) -> bytes:
    """(N, 4) particles (east, north, up, yaw) -> the serialised ``PoseArray`` (CDR bytes).

    Written with numpy in one go: a publisher takes the bytes as they are
    (``Publisher.publish`` of bytes), where building N Python ``Pose`` objects would cost
    ~6-17 us per particle, more than the filter epoch at N = 1,000. Byte-identical to
    rclpy's serialisation of :func:`particles_to_posearray`'s message (tested).

    Raises:
        MessageError: A stamp that does not fit ``builtin_interfaces/Time``.
    """
    sec, nanosec = split_ns(stamp_ns)
    p = np.asarray(particles, dtype=float).reshape(-1, 4)
    name = frame_id.encode('utf-8') + b'\x00'
    # Offsets count from the end of the encapsulation header (CDR alignment).
    head = np.array([sec, nanosec, len(name)], dtype='<u4').tobytes() + name
    head += b'\x00' * (-len(head) % 4)
    head += np.array([p.shape[0]], dtype='<u4').tobytes()
    head += b'\x00' * (-len(head) % 8)
    poses = np.zeros((p.shape[0], 7), dtype='<f8')
    poses[:, :3] = p[:, :3]
    half = 0.5 * p[:, 3]
    poses[:, 5] = np.sin(half)
    poses[:, 6] = np.cos(half)
    return _CDR_LE + head + poses.tobytes()


def particles_to_posearray(particles: np.ndarray, stamp_ns: int,
                           frame_id: str = MAP_FRAME) -> PoseArray:
    """(N, 4) particles (east, north, up, yaw) -> PoseArray (the message object, from
    :func:`particles_to_posearray_cdr`'s bytes)."""
    from rclpy.serialization import deserialize_message    # ROS 2 only where called
    return deserialize_message(particles_to_posearray_cdr(particles, stamp_ns, frame_id),
                               RCLPY['geometry_msgs/msg/PoseArray'])


def posearray_to_particles(msg: PoseArray) -> np.ndarray:
    """PoseArray -> (N, 4) particles (east, north, up, yaw)."""
    out = np.empty((len(msg.poses), 4))
    for i, pose in enumerate(msg.poses):
        q = pose.orientation
        out[i] = (pose.position.x, pose.position.y, pose.position.z,
                  np.arctan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z)))
    return out


# ---------------------------------------------------------------------------- NavSatFix
@dataclass(frozen=True)
class GeodeticFix:
    """A WGS84 position fix.

    Attributes:
        stamp_ns: Stamp [ns].
        lat_deg: Latitude [deg].
        lon_deg: Longitude [deg].
        alt_m: Ellipsoidal height [m].
        covariance_enu_m2: (3, 3) covariance in east, north, up [m^2], or None if unknown.
        status: ``NavSatStatus`` status (-1 no fix, 0 fix, ...).
        service: ``NavSatStatus`` service bits (1 GPS, 2 GLONASS, 4 COMPASS, 8 GALILEO).
        frame_id: Frame of the antenna.
        covariance_type: ``NavSatFix.COVARIANCE_TYPE_*``; None: KNOWN when a covariance
            is given, else UNKNOWN.
    """

    stamp_ns: int
    lat_deg: float
    lon_deg: float
    alt_m: float
    covariance_enu_m2: np.ndarray | None = None
    status: int = STATUS_FIX
    service: int = SERVICE_GPS
    frame_id: str = ANTENNA_FRAME
    covariance_type: int | None = None


def fix_to_navsatfix(fix: GeodeticFix, kit: MessageKit = RCLPY):
    """:class:`GeodeticFix` -> NavSatFix (of ``kit``, :mod:`.message_classes`).

    Raises:
        MessageError: Non-finite coordinates or covariance.
    """
    values = [fix.lat_deg, fix.lon_deg, fix.alt_m]
    if not np.all(np.isfinite(values)):
        raise MessageError(f'non-finite fix {values}', 'non_finite')
    if fix.covariance_enu_m2 is None:
        cov, cov_type = np.zeros(9), COVARIANCE_TYPE_UNKNOWN
    else:
        cov = np.asarray(fix.covariance_enu_m2, dtype=float).reshape(9)
        if not np.all(np.isfinite(cov)):
            raise MessageError('non-finite fix covariance', 'non_finite')
        cov_type = (COVARIANCE_TYPE_KNOWN if fix.covariance_type is None
                    else int(fix.covariance_type))
    return kit['sensor_msgs/msg/NavSatFix'](
        header=make_header(fix.stamp_ns, fix.frame_id, kit),
        status=kit['sensor_msgs/msg/NavSatStatus'](status=int(fix.status),
                                                   service=int(fix.service)),
        latitude=float(fix.lat_deg), longitude=float(fix.lon_deg), altitude=float(fix.alt_m),
        position_covariance=cov, position_covariance_type=cov_type)


def navsatfix_to_fix(msg, what: str = FIX) -> GeodeticFix:
    """NavSatFix -> :class:`GeodeticFix`.

    Raises:
        MessageError: Non-finite or out-of-range latitude/longitude, non-finite altitude.
    """
    lat, lon, alt = float(msg.latitude), float(msg.longitude), float(msg.altitude)
    if not np.all(np.isfinite([lat, lon, alt])):
        raise MessageError(f'{what}: non-finite position', 'non_finite')
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 360.0):
        raise MessageError(f'{what}: latitude/longitude out of range ({lat}, {lon})', 'value')
    cov = None
    if msg.position_covariance_type != COVARIANCE_TYPE_UNKNOWN:
        cov = np.array(msg.position_covariance, dtype=float).reshape(3, 3)
    return GeodeticFix(stamp_ns=stamp_to_ns(msg.header.stamp), lat_deg=lat, lon_deg=lon,
                       alt_m=alt, covariance_enu_m2=cov, status=int(msg.status.status),
                       service=int(msg.status.service), frame_id=msg.header.frame_id,
                       covariance_type=int(msg.position_covariance_type))


# ---------------------------------------------------------------------- PoseStamped
def pose_stamped(stamp_ns: int, position_m, quaternion_xyzw, frame_id: str,
                 kit: MessageKit = RCLPY):
    """A ``geometry_msgs/PoseStamped`` (of ``kit``, :mod:`.message_classes`).

    Args:
        stamp_ns: Header stamp [ns].
        position_m: (3,) position in ``frame_id`` [m].
        quaternion_xyzw: (4,) orientation ``(x, y, z, w)``, written as given (the all-zero
            quaternion of ``ground_truth/pose`` means "heading unknown").
        frame_id: Header frame.
        kit: Message classes to build with.
    """
    p, q = position_m, quaternion_xyzw
    point = kit['geometry_msgs/msg/Point'](x=float(p[0]), y=float(p[1]), z=float(p[2]))
    orientation = kit['geometry_msgs/msg/Quaternion'](x=float(q[0]), y=float(q[1]),
                                                      z=float(q[2]), w=float(q[3]))
    return kit['geometry_msgs/msg/PoseStamped'](
        header=make_header(stamp_ns, frame_id, kit),
        pose=kit['geometry_msgs/msg/Pose'](position=point, orientation=orientation))
