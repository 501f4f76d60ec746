"""ROS message <-> numpy/dataclass conversions for gnsscam_ros (no node logic).

Every converter raises :class:`MessageError` (with a short ``reason``) on malformed input;
time stamps are integer nanoseconds. The parsers of input messages check them against the
documented physical limits of :mod:`.limits` (sizes from the header fields, before any
array is decoded); :class:`StampGate` (:mod:`.stamp_gate`) keeps each input topic's stamps
within a window of its recent stream. Topic and frame names, point layouts, system codes and
the equal-stamp order are in :mod:`.wire`; the writers the bag converter shares build with
a :class:`MessageKit` (:mod:`.message_classes`). See each module for the message layouts
(:mod:`.wire`).
"""
from . import limits, wire
from .checks import check_serialized_size
from .errors import MessageError
from .stamp_gate import ADVANCE, BEHIND, NEW_BASE, StampGate
from .geometry import (GeodeticFix, PoseEstimate, fix_to_navsatfix, msg_to_pose,
                       navsatfix_to_fix, particles_to_posearray,
                       particles_to_posearray_cdr, pose_covariance, pose_stamped,
                       pose_to_msg, posearray_to_particles, quaternion_to_yaw,
                       yaw_to_quaternion)
from .image import (ENCODINGS, array_to_image, check_image, check_image_size,
                    check_serialized_image, image_to_array)
from .integrity import (ERROR, OK, STALE, WARN, IntegrityRisk, integrity_risk_to_msg,
                        level_to_int, make_diagnostic_array, make_status, parse_integrity_risk,
                        status_values)
from .message_classes import RCLPY, MessageKit, message_class, numpy_kit
from .motion import (GlobalOdometry, ImuSample, TwistSample, dead_reckoning_to_odometry,
                     global_odometry_to_msg, imu_to_sample, odometry_to_dead_reckoning,
                     odometry_to_global, sample_to_imu, sample_to_twist, twist_to_sample)
from .pointcloud import (CameraMatches, check_serialized_cloud, check_serialized_gnss,
                         check_serialized_matches, gnss_epoch_to_pointcloud2,
                         matches_to_pointcloud2, pointcloud2_to_gnss_epoch,
                         pointcloud2_to_matches, pointcloud2_to_structured,
                         structured_to_pointcloud2)
from .stamps import make_header, ns_to_stamp, stamp_to_ns
from .wire import GNSS_DTYPE, MATCH_DTYPE, header_stamp_ns, service_bits

__all__ = [
    'ADVANCE', 'BEHIND', 'NEW_BASE', 'StampGate', 'check_image', 'check_image_size',
    'check_serialized_cloud', 'check_serialized_gnss', 'check_serialized_image',
    'check_serialized_matches', 'check_serialized_size', 'limits',
    'CameraMatches', 'ENCODINGS', 'ERROR', 'GNSS_DTYPE', 'GeodeticFix', 'GlobalOdometry',
    'ImuSample', 'IntegrityRisk', 'MATCH_DTYPE', 'MessageError', 'MessageKit', 'OK',
    'PoseEstimate', 'RCLPY', 'STALE', 'TwistSample', 'WARN', 'array_to_image',
    'dead_reckoning_to_odometry', 'fix_to_navsatfix', 'global_odometry_to_msg',
    'gnss_epoch_to_pointcloud2', 'header_stamp_ns', 'image_to_array', 'imu_to_sample',
    'integrity_risk_to_msg', 'level_to_int', 'make_diagnostic_array', 'make_header',
    'make_status', 'matches_to_pointcloud2', 'message_class', 'msg_to_pose',
    'navsatfix_to_fix', 'ns_to_stamp', 'numpy_kit', 'odometry_to_dead_reckoning',
    'odometry_to_global', 'parse_integrity_risk', 'particles_to_posearray',
    'particles_to_posearray_cdr',
    'pointcloud2_to_gnss_epoch', 'pointcloud2_to_matches', 'pointcloud2_to_structured',
    'pose_covariance', 'pose_stamped', 'pose_to_msg', 'posearray_to_particles',
    'quaternion_to_yaw', 'sample_to_imu', 'sample_to_twist', 'service_bits', 'stamp_to_ns',
    'status_values', 'structured_to_pointcloud2', 'twist_to_sample', 'wire',
    'yaw_to_quaternion',
]
