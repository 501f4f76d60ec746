"""What is specific to bags: which topics a bag holds, the QoS recorded for them, the bag
format tag and the typestore. Topic names, types, frames and latching are the topic
registry's, point layouts the wire contract's (:mod:`msg_adapters.wire`).

A converted dataset bag holds the topics of ``msg_adapters.wire.DATASET_BAG_TOPICS``, each
with the type and frame of its registry entry (``msg_adapters.wire.TOPICS``; the README's
topic table is rendered from it): ``dataset/info`` (JSON, below) and ``map/origin`` (when
known) once, ``gnss/pseudoranges`` at 1-5 Hz, ``camera/image_raw`` (bgr8, 640x480) at
10 Hz, ``imu/data`` at 100 Hz, ``odom/twist``, and ``ground_truth/pose`` at the truth rate.

Conventions:

* Names are written fully qualified under a namespace (default ``/``: ``/imu/data``), as
  ``ros2 bag record`` stores them; readers accept the relative and the qualified form.
* Bag time stamps (log times) equal the header stamps: the dataset's true times.
* ``dataset/info`` and ``map/origin`` come first, stamped with the first data stamp, and
  are offered ``transient_local`` so that ``ros2 bag play`` hands them to late subscribers.
  ``dataset/info`` is a JSON object: ``format`` (:data:`FORMAT`), ``name``,
  ``origin_llh`` (or null), ``info`` (the dataset's provenance, JSON-able parts), ``topics``
  (qualified name -> type of the topics above) and ``converter``. ``map/origin`` is
  written only when the dataset fixes the ``map`` frame origin (the emulated drive);
  without it (smartLoc) the nodes anchor ``map`` at the first robust fix. Its
  latitude/longitude/altitude are the origin of the local ENU ``map`` frame
  (``Drive.origin_llh``), status FIX, covariance unknown.
* ``ground_truth/pose`` is for evaluation only (no node subscribes to it): position = truth
  ECEF [m]; orientation = the vehicle attitude in ECEF, level with heading ``yaw`` about
  the up axis of the ENU frame at the map origin (the first truth point when the dataset
  has no origin); the all-zero quaternion means "heading unknown" (smartLoc truth).
* ``imu/data``: orientation unavailable (``orientation_covariance[0] = -1``, REP 145);
  rate and acceleration covariances all zero, i.e. unknown (sensor_msgs/Imu convention).
* ``odom/twist``: forward speed on ``linear.x`` [m/s], yaw rate on ``angular.z`` [rad/s],
  their variances at covariance indices 0 and 35, everything else 0 (as ``msg_adapters``).
* ``gnss/pseudoranges``: one point per satellite, ``msg_adapters.wire.GNSS_DTYPE``
  (naturally aligned, 48-byte points).
* Every message is built by the ``msg_adapters`` writer the nodes publish with (through
  :func:`rosbags_kit`), so a bag holds what a node would send.

A result bag (recorded from the nodes) holds ``pose``, ``integrity_risk`` and optionally
``fix``, ``particles``; :data:`RESULT_TOPICS` names them.
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                QosReliability, QosTime)
from rosbags.typesys import Stores, get_typestore

from msg_adapters.message_classes import MessageKit, numpy_kit
from msg_adapters.wire import (  # noqa: F401 - the topic names and types, for bag code
    BASE_FRAME, CAMERA_FRAME, DATASET_BAG_TOPICS, DEAD_RECKONING, DIAGNOSTIC_ARRAY,
    DIAGNOSTICS, EARTH_FRAME, FIX, GNSS, GNSS_FIX, GNSS_MEASUREMENTS, IMAGE, IMAGE_TYPE, IMU,
    IMU_TYPE, INFO, INTEGRITY, MAP_FRAME, MATCHES, NAVSATFIX, ODOMETRY, ODOMETRY_GLOBAL,
    ORIGIN, PARTICLES, POINTCLOUD2, POSE, POSE_ARRAY, POSE_COV_STAMPED, POSE_STAMPED,
    RESULT_BAG_TOPICS, STRING, TOPICS, TRUTH, TWIST, TWIST_TYPE, Topic)

#: The typestore every bag of this package is written and read with.
STORE = Stores.ROS2_JAZZY
#: ``dataset/info`` format tag; bump when the layout changes incompatibly.
FORMAT = 'gnsscam_ros.dataset_bag/1'

#: One topic of a bag: the registry's entry (``msg_adapters.wire.Topic``: name, type,
#: frame, latching, description).
TopicSpec = Topic

#: Topics of a dataset bag, in the order they are registered.
DATASET_TOPICS: dict[str, Topic] = {name: TOPICS[name] for name in DATASET_BAG_TOPICS}

#: Output topics of the nodes that the bag evaluation reads.
RESULT_TOPICS: dict[str, Topic] = {name: TOPICS[name] for name in RESULT_BAG_TOPICS}

#: Every topic of the gnsscam_ros graph (relative name) with its one message type: a bag
#: that holds one of them with another type is refused by the replay (the nodes would
#: receive messages they cannot read, and the replay would end as if all went well).
TOPIC_TYPES: dict[str, str] = {t.name: t.msgtype for t in TOPICS.values()}


@lru_cache(maxsize=1)
def typestore():
    """The shared ROS 2 Jazzy typestore (built once; building costs ~50 ms)."""
    return get_typestore(STORE)


@lru_cache(maxsize=1)
def rosbags_kit() -> MessageKit:
    """The ``msg_adapters`` writers' kit for the typestore's message dataclasses (what the
    converter serialises; no rclpy involved)."""
    return numpy_kit(typestore().types, f'rosbags {STORE.name}')


def qos(latched: bool) -> Qos:
    """Offered QoS recorded for a topic: reliable (a replay must not drop data), volatile,
    or transient_local for the once-only topics (the registry's ``Topic.latched``)."""
    zero = QosTime(sec=0, nsec=0)
    return Qos(history=QosHistory.KEEP_LAST, depth=1 if latched else 100,
               reliability=QosReliability.RELIABLE,
               durability=(QosDurability.TRANSIENT_LOCAL if latched
                           else QosDurability.VOLATILE),
               deadline=zero, lifespan=zero, liveliness=QosLiveliness.AUTOMATIC,
               liveliness_lease_duration=zero, avoid_ros_namespace_conventions=False)


def qualified(name: str, namespace: str = '/') -> str:
    """``name`` under ``namespace`` as a fully qualified topic (``/ns/name``)."""
    ns = '/' + namespace.strip('/') if namespace.strip('/') else ''
    return f'{ns}/{name.lstrip("/")}'


def relative(topic: str, namespace: str = '/') -> str | None:
    """The relative name of a bag topic under ``namespace``, or None when it is outside.

    Both ``/ns/name`` and a bare ``name`` (written by tools that do not qualify) match.
    """
    if not topic.startswith('/'):
        return topic
    prefix = qualified('', namespace)
    return topic[len(prefix):] if topic.startswith(prefix) else None


# ---------------------------------------------------------------- ground-truth attitude
def _matrix_to_quaternion(rot: np.ndarray) -> np.ndarray:
    """Rotation matrix -> unit quaternion ``(x, y, z, w)`` (Shepperd's method: pick the
    largest of the four squared components so the division is well conditioned)."""
    m = np.asarray(rot, dtype=float)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    cands = (trace, m[0, 0], m[1, 1], m[2, 2])
    k = int(np.argmax(cands))
    if k == 0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s,
             0.25 * s)
    elif k == 1:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = (0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s,
             (m[2, 1] - m[1, 2]) / s)
    elif k == 2:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = ((m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s,
             (m[0, 2] - m[2, 0]) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = ((m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s,
             (m[1, 0] - m[0, 1]) / s)
    q = np.array(q)
    return q / np.linalg.norm(q)


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of (..., 4) quaternions ``(x, y, z, w)``."""
    ax, ay, az, aw = np.moveaxis(np.asarray(a, dtype=float), -1, 0)
    bx, by, bz, bw = np.moveaxis(np.asarray(b, dtype=float), -1, 0)
    return np.stack([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz], axis=-1)


def enu_quaternion(rot_ecef_to_enu: np.ndarray) -> np.ndarray:
    """Orientation ``(x, y, z, w)`` of an ENU frame in ECEF, from its ``rot_ecef_to_enu``
    (rows = east, north, up unit vectors in ECEF, as :class:`..core.frames.LocalFrame`)."""
    # The ENU axes expressed in ECEF are the columns of the transpose.
    return _matrix_to_quaternion(np.asarray(rot_ecef_to_enu, dtype=float).T)


def yaw_to_ecef_quaternion(yaw_rad: np.ndarray, q_enu: np.ndarray) -> np.ndarray:
    """(n,) ENU headings [rad] -> (n, 4) ECEF orientations of a level vehicle.

    ``q = q_enu * q_z(yaw)``: first the heading about the local up axis, then the ENU frame
    into ECEF.
    """
    half = 0.5 * np.asarray(yaw_rad, dtype=float)
    qz = np.stack([np.zeros_like(half), np.zeros_like(half), np.sin(half), np.cos(half)],
                  axis=-1)
    return _quat_mul(np.broadcast_to(q_enu, qz.shape), qz)


def ecef_quaternion_to_yaw(q: np.ndarray, q_enu: np.ndarray) -> np.ndarray:
    """(n, 4) ECEF orientations -> (n,) ENU headings in [-pi, pi] [rad] (ZYX yaw of
    ``conj(q_enu) * q``)."""
    conj = np.asarray(q_enu, dtype=float) * np.array([-1.0, -1.0, -1.0, 1.0])
    local = _quat_mul(np.broadcast_to(conj, np.shape(q)), q)
    x, y, z, w = np.moveaxis(local, -1, 0)
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
