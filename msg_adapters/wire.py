"""The wire contract of gnsscam_ros, in one place.

The topic registry (:data:`TOPICS`: each topic's name, message type, frame, QoS, depth,
producer and consumers, :class:`Topic`), frame names, the point layouts of the GNSS and
camera-match clouds, the GNSS ``system`` codes and their ``NavSatStatus`` service bits,
time stamps (integer ns <-> ``builtin_interfaces/Time``), and the order of messages that
share a stamp. The message adapters, the bag converter and reader, the nodes and the
replay take them from here.

Plain Python and numpy, no ROS import: the storage layer (rosbags) and the rclpy layer
read the same definitions. The nodes build their publishers and subscriptions from
:data:`TOPICS` (``nodes.node_base``), the bag converter and reader take their topic layout
from it (``bags.schema``), the recorder its types, latching and queue depths
(``live.record``), and the README's topic table is rendered from it: run
``python -m msg_adapters.topic_table README.md`` after changing a topic here (a
test fails while the README differs; :mod:`.topic_table`).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from gnsscam_ros.core import motion

from .errors import MessageError

# ---------------------------------------------------------------------------- topics
# Names relative to the namespace of the nodes (``ros2 bag record`` stores them qualified,
# ``/imu/data``).
INFO = 'dataset/info'                         # dataset description (bags only)
ORIGIN = 'map/origin'                         # origin of the local ENU map frame
GNSS = 'gnss/pseudoranges'                    # receiver epochs (PointCloud2, GNSS_DTYPE)
GNSS_MEASUREMENTS = 'gnss/measurements'       # gnss_node's checked epochs (same layout)
GNSS_FIX = 'gnss/fix'                         # gnss_node's snapshot fix (NavSatFix)
IMAGE = 'camera/image_raw'
MATCHES = 'camera/matches'                    # camera_node's top-k matches (MATCH_DTYPE)
IMU = 'imu/data'
TWIST = 'odom/twist'
DEAD_RECKONING = 'odometry/dead_reckoning'    # imu_node's dead-reckoned pose (Odometry)
ODOMETRY_GLOBAL = 'odometry/global'           # fusion_node's estimate for ROS consumers
TRUTH = 'ground_truth/pose'                   # evaluation only (no node subscribes)
POSE = 'pose'
FIX = 'fix'
PARTICLES = 'particles'
INTEGRITY = 'integrity_risk'
DIAGNOSTICS = 'diagnostics'

# ---------------------------------------------------------------------------- frames
EARTH_FRAME = 'earth'          # ECEF: GNSS clouds, ground truth
MAP_FRAME = 'map'              # local ENU at the map origin: pose, particles, matches
ODOM_FRAME = 'odom'            # the dead reckoning's own frame
BASE_FRAME = 'base_link'       # the vehicle: IMU, wheel odometry, child of odometry/*
CAMERA_FRAME = 'camera'
ANTENNA_FRAME = 'gnss'         # the GNSS antenna: gnss/fix and fix
IMU_FRAME = 'imu'              # default frame of an IMU sample written alone

# --------------------------------------------------------------------- message types
STRING = 'std_msgs/msg/String'
NAVSATFIX = 'sensor_msgs/msg/NavSatFix'
POINTCLOUD2 = 'sensor_msgs/msg/PointCloud2'
IMAGE_TYPE = 'sensor_msgs/msg/Image'
IMU_TYPE = 'sensor_msgs/msg/Imu'
TWIST_TYPE = 'geometry_msgs/msg/TwistWithCovarianceStamped'
POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'
POSE_COV_STAMPED = 'geometry_msgs/msg/PoseWithCovarianceStamped'
POSE_ARRAY = 'geometry_msgs/msg/PoseArray'
DIAGNOSTIC_ARRAY = 'diagnostic_msgs/msg/DiagnosticArray'
ODOMETRY = 'nav_msgs/msg/Odometry'

# ------------------------------------------------------------------- topic registry
#: QoS policies of :class:`Topic` (the names of ``rclpy.qos`` policies, lower case).
RELIABLE, BEST_EFFORT = 'reliable', 'best_effort'
VOLATILE, TRANSIENT_LOCAL = 'volatile', 'transient_local'
KEEP_LAST = 'keep_last'
#: Producer of the input topics: the robot's drivers, or the replay of a dataset bag.
DATASET = 'dataset'
#: Producer of ``diagnostics``: every node of the package.
EVERY_NODE = 'every node'
#: Queue depth of a recorder's subscription [messages]: it must lose nothing while it
#: writes, and small messages cost little.
RECORD_DEPTH = 2000


@dataclass(frozen=True)
class Topic:
    """One topic of the gnsscam_ros graph: what travels on it and who sends and takes it.

    Attributes:
        name: Topic name relative to the nodes' namespace.
        msgtype: Message type, ``pkg/msg/Type`` (the rosbags and rclpy name).
        frame_id: Header frame (None: the message has no frame of its own).
        frame_parameter: The node parameter that sets another frame ('' for none).
        producers: Who publishes it: node names, :data:`DATASET` or :data:`EVERY_NODE`.
        consumers: The package's nodes that subscribe to it (none: an output for ROS
            consumers, the recorder and the evaluation).
        reliability: :data:`RELIABLE` or :data:`BEST_EFFORT`, of the nodes' endpoints (a
            sensor input: what the subscription asks; publishers may offer reliable).
        durability: :data:`VOLATILE`, or :data:`TRANSIENT_LOCAL` for the once-only
            (latched) topics, kept for late subscribers.
        depth: ``KEEP_LAST`` depth of the nodes' endpoints [messages] (a node's queue
            depth parameter may set another; its default is this one).
        record_depth: Depth of a recorder's subscription [messages].
        description: What it carries (the README's topic table).
        history: ``KEEP_LAST`` (the only history the graph uses).
    """

    name: str
    msgtype: str
    frame_id: str | None
    frame_parameter: str
    producers: tuple[str, ...]
    consumers: tuple[str, ...]
    reliability: str
    durability: str
    depth: int
    record_depth: int
    description: str
    history: str = KEEP_LAST

    @property
    def latched(self) -> bool:
        """Offered ``transient_local``: sent once, kept for late subscribers."""
        return self.durability == TRANSIENT_LOCAL

    @property
    def interface(self) -> str:
        """The type as ``ros2 interface`` shows it: ``sensor_msgs/PointCloud2``."""
        pkg, _, name = self.msgtype.split('/')
        return f'{pkg}/{name}'


def _input(name, msgtype, frame_id, frame_parameter, consumer, depth, description):
    """A sensor input: best effort, from the drivers or a replayed bag."""
    return Topic(name, msgtype, frame_id, frame_parameter, (DATASET,), (consumer,),
                 BEST_EFFORT, VOLATILE, depth, RECORD_DEPTH, description)


def _stream(name, msgtype, frame_id, frame_parameter, producer, consumers, description,
            depth=10, record_depth=RECORD_DEPTH):
    """A node output: reliable, volatile."""
    return Topic(name, msgtype, frame_id, frame_parameter, (producer,), tuple(consumers),
                 RELIABLE, VOLATILE, depth, record_depth, description)


#: Every topic of the gnsscam_ros graph, inputs first, then in the order of the graph.
TOPICS: dict[str, Topic] = {t.name: t for t in (
    _input(GNSS, POINTCLOUD2, EARTH_FRAME, 'input_frame_id', 'gnss_node', 10,
           'one point per satellite: `x y z` FLOAT64 ECEF [m], `pseudorange` FLOAT64 [m], '
           '`variance` FLOAT32 [m²], `cn0` FLOAT32 [dB-Hz], `elevation` FLOAT32 [deg], '
           '`sv_id` UINT16, `system` UINT8 (1 GPS, 2 SBAS, 4 GLONASS, 8 Galileo, 16 QZSS, '
           '32 BeiDou)'),
    _input(IMAGE, IMAGE_TYPE, CAMERA_FRAME, '', 'camera_node', 5,
           'mono8, bgr8 or rgb8 (camera_node `input_reliable`: reliable instead)'),
    _input(IMU, IMU_TYPE, BASE_FRAME, '', 'imu_node', 100,
           'body x forward, z up: forward acceleration and gyro z are used'),
    _input(TWIST, TWIST_TYPE, BASE_FRAME, '', 'imu_node', 100,
           'optional: `linear.x` speed [m/s], `angular.z` yaw rate [rad/s], variances at '
           'covariance 0 and 35'),
    Topic(INFO, STRING, None, '', (DATASET,), (), RELIABLE, TRANSIENT_LOCAL, 1, 1,
          'dataset description (JSON), bags only: format, name, origin, provenance, topics'),
    Topic(ORIGIN, NAVSATFIX, MAP_FRAME, 'map_frame_id', (DATASET, 'fusion_node'), (),
          RELIABLE, TRANSIENT_LOCAL, 1, 1,
          'geodetic origin of the `map` frame (`map_origin_llh`, else the first robust '
          'fix), published once it exists; a late subscriber still gets it. Status FIX, '
          'covariance unknown, as the bag converter writes it'),
    Topic(TRUTH, POSE_STAMPED, EARTH_FRAME, '', (DATASET,), (), RELIABLE, VOLATILE, 10,
          RECORD_DEPTH, 'ground truth in ECEF, bags only (evaluation; no node subscribes)'),
    _stream(GNSS_MEASUREMENTS, POINTCLOUD2, EARTH_FRAME, '', 'gnss_node', ['fusion_node'],
            'the satellites that passed the checks (every epoch, even when too few are '
            'left)'),
    _stream(GNSS_FIX, NAVSATFIX, ANTENNA_FRAME, 'fix_frame_id', 'gnss_node', [],
            'robust snapshot fix of usable epochs, approximated covariance (ENU)'),
    _stream(MATCHES, POINTCLOUD2, MAP_FRAME, 'map_frame_id', 'camera_node', ['fusion_node'],
            'top-k database images, best first: `x y z` FLOAT64, `score` FLOAT32, '
            '`image_id` UINT32; stamp = image stamp'),
    _stream(DEAD_RECKONING, ODOMETRY, ODOM_FRAME, 'odom_frame_id', 'imu_node',
            ['fusion_node'],
            'child `base_link` (`base_frame_id`): planar dead-reckoned pose, integrated at '
            'every input sample, published one per `output_period_s` (0.1 s); pose '
            'covariance x/y: accumulated distance variance, yaw: heading variance; twist: '
            'speed and yaw rate', depth=100),
    _stream(INTEGRITY, DIAGNOSTIC_ARRAY, None, '', 'fusion_node', [],
            'one status: the integrity verdict, see below'),
    _stream(POSE, POSE_COV_STAMPED, MAP_FRAME, 'map_frame_id', 'fusion_node', [],
            'estimate (the weighted mean of the chosen motion sample), 3×3 position '
            'covariance, heading variance'),
    _stream(ODOMETRY_GLOBAL, ODOMETRY, MAP_FRAME, 'map_frame_id', 'fusion_node', [],
            'child `base_link` (`base_frame_id`), for robot_localization / Nav2: the pose '
            'and covariance of `pose` (roll, pitch variance 1e6), twist in `base_link`: '
            'forward speed and yaw rate of the newest dead-reckoning state at or before the '
            'epoch, variances at covariance 0 and 35 (others 1e6; speed 0 with variance 1e6 '
            'when none within 1 s); every epoch `pose` is published'),
    _stream(FIX, NAVSATFIX, ANTENNA_FRAME, 'fix_frame_id', 'fusion_node', [],
            'the same estimate in WGS84 (epochs with a GNSS update)'),
    # Clouds are large (~56 kB): a shallow history, and a recorder keeps fewer waiting.
    _stream(PARTICLES, POSE_ARRAY, MAP_FRAME, 'map_frame_id', 'fusion_node', [],
            'the particle cloud after resampling (at most `max_published_particles`, '
            'weighted deterministic subsample)', depth=2, record_depth=100),
    _stream(DIAGNOSTICS, DIAGNOSTIC_ARRAY, None, '', EVERY_NODE, [],
            'node status, counters, rejections by reason, processing times'),
)}

#: Topics of a dataset bag (``gnsscam_convert``), in the order they are registered.
DATASET_BAG_TOPICS = (INFO, ORIGIN, GNSS, IMAGE, IMU, TWIST, TRUTH)
#: The nodes' outputs that a result bag holds and the bag evaluation reads.
RESULT_BAG_TOPICS = (POSE, FIX, PARTICLES, INTEGRITY)


def topics_of(node: str) -> tuple[list[Topic], list[Topic]]:
    """``(published, subscribed)`` topics of a node of the package, by its name."""
    published = [t for t in TOPICS.values() if node in t.producers
                 or t.producers == (EVERY_NODE,)]
    return published, [t for t in TOPICS.values() if node in t.consumers]


# ---------------------------------------------------------------------- point layouts
#: ``gnss/pseudoranges``, ``gnss/measurements`` (frame ``earth``), one point per
#: satellite: ``x y z`` FLOAT64 satellite ECEF position [m], ``pseudorange`` FLOAT64 [m],
#: ``variance`` FLOAT32 [m^2], ``cn0`` FLOAT32 [dB-Hz], ``elevation`` FLOAT32 [deg],
#: ``sv_id`` UINT16, ``system`` UINT8; little endian, naturally aligned (1 pad byte at 47).
#:
#: **Input contract of ``gnss/pseudoranges``** (what a driver must put in it):
#:
#: * ``pseudorange``: the code pseudorange [m] with the *satellite* clock offset removed
#:   (broadcast polynomial + relativistic term ``F e sqrt(A) sin E`` + the group delay of
#:   the signal: TGD for GPS L1, BGD(E1,E5b) for Galileo E1, TGD1 for BeiDou B1I), and the
#:   ionospheric and tropospheric delays removed (e.g. Klobuchar, Saastamoinen). The
#:   *receiver* clock stays in it (the filter estimates one per system).
#: * ``x y z``: the satellite's ECEF position at the signal's *transmission* time
#:   (reception time - pseudorange / c - satellite clock), in the ECEF frame *of that
#:   time*: not rotated for the Earth's rotation during the ~70 ms flight, which the
#:   consumer applies (``core.frames.sagnac_corrected``).
#: * ``header.stamp``: the receiver's measurement (reception) time as UTC, POSIX
#:   seconds/nanoseconds (ROS time), i.e. GPS time - (GPS - UTC leap seconds, 18 s since
#:   2017); stamps of one source must increase.
#: * ``variance``: the pseudorange error variance [m^2] as a relative weight; when the
#:   driver has none, put the elevation/C/N0 model of ``core.corrections`` or a constant
#:   (10 m^2): the filter learns its error scale online, but ``gnss_node`` warns when the
#:   post-fit residuals are implausibly large for it (``core.gnss_checks``). NaN is refused.
#: * ``cn0``/``elevation``: NaN when unknown (never below a mask then).
#:
#: A driver with raw measurements (e.g. u-blox RXM-RAWX: ``prMes``, ``cno``, ``gnssId``,
#: ``svId`` and the receiver time of week) fills ``core.preprocess.ObservationEpoch`` and
#: calls ``core.preprocess.Preprocessor(navigation).process(obs).epoch`` with navigation
#: from RXM-SFRBX or a RINEX file (``datasets.rinex.read_navigation``); the result goes out
#: with ``msg_adapters.gnss_epoch_to_pointcloud2``.
GNSS_DTYPE = np.dtype({
    'names': ['x', 'y', 'z', 'pseudorange', 'variance', 'cn0', 'elevation', 'sv_id', 'system'],
    'formats': ['<f8', '<f8', '<f8', '<f8', '<f4', '<f4', '<f4', '<u2', 'u1'],
    'offsets': [0, 8, 16, 24, 32, 36, 40, 44, 46], 'itemsize': 48})

#: ``camera/matches`` (frame ``map``), best match first: ``x y z`` FLOAT64 [m],
#: ``score`` FLOAT32, ``image_id`` UINT32.
MATCH_DTYPE = np.dtype({
    'names': ['x', 'y', 'z', 'score', 'image_id'],
    'formats': ['<f8', '<f8', '<f8', '<f4', '<u4'],
    'offsets': [0, 8, 16, 24, 28], 'itemsize': 32})

#: ``sensor_msgs/PointField`` datatype codes <-> numpy scalar types.
POINTFIELD_TYPES = {1: np.int8, 2: np.uint8, 3: np.int16, 4: np.uint16, 5: np.int32,
                    6: np.uint32, 7: np.float32, 8: np.float64}
POINTFIELD_CODE = {np.dtype(v): k for k, v in POINTFIELD_TYPES.items()}
POINTFIELD_NAMES = {1: 'INT8', 2: 'UINT8', 3: 'INT16', 4: 'UINT16', 5: 'INT32', 6: 'UINT32',
                    7: 'FLOAT32', 8: 'FLOAT64'}

# ------------------------------------------------------------ systems, service bits
#: Satellite systems of the ``system`` field (1 GPS, 2 SBAS, 4 GLONASS, 8 Galileo,
#: 16 QZSS, 32 BeiDou).
KNOWN_SYSTEMS = (1, 2, 4, 8, 16, 32)

# sensor_msgs/NavSatStatus and NavSatFix constants.
STATUS_NO_FIX, STATUS_FIX = -1, 0
SERVICE_GPS, SERVICE_GLONASS, SERVICE_COMPASS, SERVICE_GALILEO = 1, 2, 4, 8
COVARIANCE_TYPE_UNKNOWN, COVARIANCE_TYPE_KNOWN = 0, 3

#: ``system`` code -> NavSatStatus service bit (SBAS and QZSS have none).
SERVICE_OF_SYSTEM = {1: SERVICE_GPS, 4: SERVICE_GLONASS, 8: SERVICE_GALILEO,
                     32: SERVICE_COMPASS}


def service_bits(systems) -> int:
    """NavSatStatus service bits of a set of ``system`` codes (SBAS/QZSS: no bit)."""
    bits = 0
    for s in set(int(v) for v in systems):
        bits |= SERVICE_OF_SYSTEM.get(s, 0)
    return bits


# ---------------------------------------------------------------------------- stamps
NS_PER_S = 1_000_000_000
MAX_STAMP_SEC = 2 ** 31 - 1    # builtin_interfaces/Time.sec is an int32


def split_ns(stamp_ns: int) -> tuple[int, int]:
    """Integer ns -> ``(sec, nanosec)`` of ``builtin_interfaces/Time``.

    Raises:
        MessageError: Negative or beyond the int32 seconds of the message (reason
            ``'stamp'``; a ValueError).
    """
    stamp_ns = int(stamp_ns)
    sec, nanosec = divmod(stamp_ns, NS_PER_S)
    if not 0 <= sec <= MAX_STAMP_SEC:
        raise MessageError(f'stamp {stamp_ns} ns does not fit builtin_interfaces/Time',
                           'stamp')
    return sec, nanosec


def join_ns(sec: int, nanosec: int) -> int:
    """``builtin_interfaces/Time`` fields -> integer ns."""
    return int(sec) * NS_PER_S + int(nanosec)


def header_stamp_ns(raw: bytes | memoryview) -> int:
    """Header stamp [ns] of a CDR-serialised message that starts with ``std_msgs/Header``,
    read without decoding the rest (an image is ~1 MB; its stamp is 8 bytes).

    Raises:
        MessageError: Too short, or an encapsulation other than plain CDR.
    """
    if len(raw) < 12 or raw[0] != 0 or raw[1] not in (0, 1):
        raise MessageError('not a plain CDR message with a header', 'size')
    # Encapsulation kind 0x0001 is little endian, 0x0000 big endian; the Time follows.
    sec, nanosec = struct.unpack_from('<iI' if raw[1] == 1 else '>iI', raw, 4)
    return sec * NS_PER_S + nanosec


def header_dims(raw: bytes | memoryview) -> tuple[int, int] | None:
    """``(height, width)`` of a CDR-serialised ``sensor_msgs/Image`` or ``PointCloud2``
    (both put them right after their ``std_msgs/Header``), read without decoding the
    rest, so that a message too large to use is refused before its arrays are copied.

    Returns:
        The sizes, or None when ``raw`` is not plain CDR or too short to hold them (the
        deserialiser judges such a message).
    """
    if len(raw) < 16 or raw[0] != 0 or raw[1] not in (0, 1):
        return None
    order = '<' if raw[1] == 1 else '>'
    # After the 4-byte encapsulation: Time (8 bytes), frame_id (uint32 length with the
    # terminating NUL, then the characters), then uint32 fields aligned to 4 bytes
    # relative to the end of the encapsulation.
    (length,) = struct.unpack_from(f'{order}I', raw, 12)
    offset = 16 + length
    offset += -(offset - 4) % 4
    if len(raw) < offset + 8:
        return None
    height, width = struct.unpack_from(f'{order}II', raw, offset)
    return int(height), int(width)


# ------------------------------------------------------------------ equal-stamp order
# The input topic of each dead-reckoning source of core.motion.
_DR_SOURCE_TOPIC = {motion.ODOMETRY: TWIST, motion.IMU: IMU}

#: Order of input messages that share a stamp (other topics after them). Such messages
#: have no order of their own (a live system receives them in any order); the bag
#: converter writes and the replay publishes them in this one: the dead reckoning's
#: sources in its own rule (``core.motion.DR_SOURCES``: odometry before IMU), then camera
#: and GNSS after the motion of their instant, as a receiver delivers an epoch after its
#: time of validity.
TIE_ORDER = tuple(_DR_SOURCE_TOPIC[s] for s in motion.DR_SOURCES) + (IMAGE, GNSS)
