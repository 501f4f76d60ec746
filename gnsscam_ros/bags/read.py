"""rosbag2 bag -> dataset (the inverse of :mod:`.convert`) and -> result arrays.

* :func:`read_drive`: a dataset bag (topics of :mod:`.schema`) back into a
  :class:`~gnsscam_ros.core.types.Drive`; camera frames stay in the bag and are read on
  demand (:class:`BagCamera`).
* :func:`read_results`: the nodes' outputs ``pose``, ``fix``, ``particles``,
  ``integrity_risk`` (and ground truth / map origin when recorded too) for the evaluation.
* :func:`bag_topics`: what a bag holds.

Messages are decoded with rosbags and the ROS 2 Jazzy typestore, then converted by the same
``msg_adapters`` functions the nodes use (they read fields by name, so rosbags dataclasses
work as well as rclpy messages): one parser per message layout.

Errors name the bag and, where one is at fault, the topic: :class:`.BagReadError`
(missing, not a bag, truncated or corrupt storage, a message that does not decode),
:class:`.BagTypeError` (a topic with another type than :mod:`.schema` says, or a type the
typestore does not know), :class:`.BagContentError` (a required topic missing, wrong frame
or point layout). Topics that are not asked for are ignored whatever their type, so bags
recorded with ``ros2 bag record -a`` can be read.
"""
from __future__ import annotations

import json
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
from rosbags.rosbag2 import Reader

from msg_adapters import (IntegrityRisk, MessageError, image_to_array, imu_to_sample,
                          msg_to_pose, navsatfix_to_fix, parse_integrity_risk,
                          pointcloud2_to_gnss_epoch, posearray_to_particles, stamp_to_ns,
                          twist_to_sample)
from msg_adapters.wire import EARTH_FRAME, header_stamp_ns

from ..core.frames import LocalFrame
from ..core.types import Drive, GnssEpoch, ImuSeries, OdometrySeries, Trajectory
from . import schema
from .errors import BagContentError, BagError, BagReadError, BagTypeError


# ------------------------------------------------------------------------- opening
@contextmanager
def open_bag(path: str | Path) -> Iterator[Reader]:
    """Open a bag (rosbag2 folder, or a bare ``.mcap``/``.db3`` file) for reading.

    Raises:
        BagReadError: Missing path, no metadata, unknown storage, unreadable or
            truncated file (the rosbags error is chained).
    """
    path = Path(path)
    if not path.exists():
        raise BagReadError(f'{path}: no such bag', path=path)
    try:
        reader = Reader(path)
        reader.open()
    except BagError:
        raise
    except Exception as err:  # rosbags ReaderError, OSError, struct/zstd/yaml errors
        raise BagReadError(f'{path}: not a readable rosbag2 bag (corrupt or truncated?): '
                           f'{type(err).__name__}: {err}', path=path) from err
    try:
        yield reader
    finally:
        try:
            reader.close()
        except Exception:       # closing a broken bag must not hide the first error
            pass


def bag_topics(path: str | Path) -> dict[str, tuple[str, int]]:
    """``{qualified topic: (message type, message count)}`` of a bag.

    Raises:
        BagReadError: See :func:`open_bag`.
    """
    with open_bag(path) as reader:
        out: dict[str, tuple[str, int]] = {}
        for conn in reader.connections:
            msgtype, count = out.get(conn.topic, (conn.msgtype, 0))
            out[conn.topic] = (msgtype, count + conn.msgcount)
        return out


def _select(reader: Reader, path: Path, wanted: dict[str, str], namespace: str
            ) -> dict[str, list]:
    """Connections of the wanted relative topics, checked against their expected types.

    Raises:
        BagTypeError: A wanted topic has another or an unknown type.
    """
    store = schema.typestore()
    found: dict[str, list] = {topic: [] for topic in wanted}
    for conn in reader.connections:
        rel = schema.relative(conn.topic, namespace)
        if rel not in wanted:
            continue
        if conn.msgtype not in store.types:
            raise BagTypeError(f'{path}: topic {conn.topic} has unknown message type '
                               f'{conn.msgtype} (expected {wanted[rel]})', path=path,
                               topic=conn.topic)
        if conn.msgtype != wanted[rel]:
            raise BagTypeError(f'{path}: topic {conn.topic} has type {conn.msgtype}, '
                               f'expected {wanted[rel]}', path=path, topic=conn.topic)
        found[rel].append(conn)
    return found


def _scan(path: Path, wanted: dict[str, str], handlers: dict[str, Callable],
          namespace: str = '/', raw: frozenset = frozenset()) -> dict[str, int]:
    """One pass over a bag: ``handlers[topic](log_ns, msg)`` for each wanted message.

    Args:
        path: The bag.
        wanted: ``{relative topic: expected type}``.
        handlers: ``{relative topic: callback}`` (a topic without a handler is only
            type-checked).
        namespace: Namespace the topics were recorded under.
        raw: Topics whose handler takes the serialised bytes instead of the message.

    Returns:
        ``{relative topic: number of connections found}`` (0: topic absent).

    Raises:
        BagReadError: The storage fails while reading, or a message does not decode.
        BagTypeError: See :func:`_select`.
        BagContentError: A handler refused a message (``MessageError``); topic named.
    """
    store = schema.typestore()
    with open_bag(path) as reader:
        found = _select(reader, path, wanted, namespace)
        conns = [c for topic, cs in found.items() if topic in handlers for c in cs]
        by_id = {c.id: schema.relative(c.topic, namespace) for c in conns}
        if conns:
            messages = reader.messages(connections=conns)
            while True:
                try:
                    item = next(messages, None)
                except Exception as err:
                    raise BagReadError(f'{path}: corrupt or truncated bag while reading: '
                                       f'{type(err).__name__}: {err}', path=path) from err
                if item is None:
                    break
                conn, log_ns, data = item
                topic = by_id[conn.id]
                try:
                    msg = data if topic in raw else store.deserialize_cdr(data, conn.msgtype)
                except Exception as err:
                    raise BagReadError(f'{path}: topic {conn.topic}: message at {log_ns} ns '
                                       f'does not decode as {conn.msgtype}: {err}', path=path,
                                       topic=conn.topic) from err
                try:
                    handlers[topic](log_ns, msg)
                except MessageError as err:
                    raise BagContentError(f'{path}: topic {conn.topic}: message at {log_ns} '
                                          f'ns: {err}', path=path, topic=conn.topic) from err
        return {topic: len(cs) for topic, cs in found.items()}


def _frame_check(path: Path, topic: str, msg, frame_id: str) -> None:
    if msg.header.frame_id != frame_id:
        raise BagContentError(f'{path}: topic {topic}: frame {msg.header.frame_id!r}, '
                              f'expected {frame_id!r}', path=path, topic=topic)


def _truth_from_rows(stamps: list[int], rows: list[tuple], origin_llh) -> Trajectory | None:
    """Truth rows ``(x, y, z, qx, qy, qz, qw)`` -> Trajectory (yaw None if all zero)."""
    if not stamps:
        return None
    arr = np.array(rows, dtype=float).reshape(-1, 7)
    ecef, quat = arr[:, :3], arr[:, 3:]
    yaw = None
    if np.any(quat != 0.0):
        # The frame the truth headings refer to (the converter's).
        frame = LocalFrame.at_origin_or(origin_llh, ecef[0])
        yaw = schema.ecef_quaternion_to_yaw(quat, schema.enu_quaternion(frame.rot_ecef_to_enu))
        yaw[np.all(quat == 0.0, axis=1)] = np.nan    # per-sample unknown heading
    return Trajectory(stamp_ns=np.array(stamps, dtype=np.int64), ecef_m=ecef, yaw_rad=yaw)


# ------------------------------------------------------------------------- camera
class BagCamera:
    """Camera frames kept in a bag, read on demand (the interface of ``CameraStream``).

    Attributes:
        path: The bag.
        stamp_ns: (n,) header stamps [ns].
        log_ns: (n,) bag times [ns] (used to seek; equal to the stamps in converted bags).
        topic: Qualified topic name.
    """

    def __init__(self, path: Path, topic: str, stamp_ns: np.ndarray, log_ns: np.ndarray):
        self.path = Path(path)
        self.topic = topic
        self.stamp_ns = np.asarray(stamp_ns, dtype=np.int64)
        self.log_ns = np.asarray(log_ns, dtype=np.int64)

    def __len__(self) -> int:
        return int(self.stamp_ns.shape[0])

    def _decode(self, msg, log_ns: int) -> np.ndarray:
        try:
            img, _ = image_to_array(msg, self.topic)
        except MessageError as err:
            raise BagContentError(f'{self.path}: topic {self.topic}: frame at {log_ns} ns: '
                                  f'{err}', path=self.path, topic=self.topic) from err
        return img.copy()       # own the pixels: the message buffer is transient

    def frames(self, start: int = 0, stop: int | None = None
               ) -> Iterator[tuple[int, int, np.ndarray]]:
        """Iterate ``(index, stamp_ns, image)`` in one pass over the bag.

        Raises:
            BagReadError: Storage or decoding failure.
        """
        idx = range(*slice(start, stop).indices(len(self)))
        if not len(idx):
            return
        store = schema.typestore()
        with open_bag(self.path) as reader:
            conns = [c for c in reader.connections if c.topic == self.topic]
            k = idx.start
            it = reader.messages(connections=conns, start=int(self.log_ns[idx.start]),
                                 stop=int(self.log_ns[idx.stop - 1]) + 1)
            for conn, log_ns, raw in it:
                if k >= idx.stop:
                    break
                msg = store.deserialize_cdr(raw, conn.msgtype)
                yield k, int(self.stamp_ns[k]), self._decode(msg, log_ns)
                k += 1

    def image(self, i: int) -> np.ndarray:
        """Frame ``i`` as stored, (H, W, 3) uint8 BGR or (H, W) grey (opens the bag: use
        :meth:`frames` to iterate)."""
        n = len(self)
        if not -n <= int(i) < n:
            raise IndexError(f'frame {i} out of range for {n} frames')
        i = int(i) % n
        # Frames sharing a bag time: skip to the i-th of them.
        first = int(np.searchsorted(self.log_ns, self.log_ns[i]))
        for k, _, img in self.frames(first, i + 1):
            if k == i:
                return img
        raise BagReadError(f'{self.path}: topic {self.topic}: frame {i} not found',
                           path=self.path, topic=self.topic)


# ------------------------------------------------------------------------- drive
def read_drive(path: str | Path, namespace: str = '/', require_gnss: bool = True) -> Drive:
    """Read a dataset bag back into a Drive (the inverse of :func:`.convert.convert_drive`).

    Float32 point fields (``variance``, ``cn0``, ``elevation``) come back as their float32
    values; truth headings as angles in [-pi, pi]; camera frames as a :class:`BagCamera`.

    Args:
        path: Bag folder (or a bare ``.mcap``/``.db3`` file).
        namespace: Namespace the topics were written under.
        require_gnss: Raise when the bag has no ``gnss/pseudoranges``.

    Returns:
        The drive; name, origin and provenance from ``dataset/info`` and ``map/origin``
        when present (else the bag's name, no origin, ``info = {'bag': path}``).

    Raises:
        BagReadError, BagTypeError: See the module docstring.
        BagContentError: No ``gnss/pseudoranges`` (with ``require_gnss``), a wrong frame or
            point layout.
    """
    path = Path(path)
    wanted = {t.name: t.msgtype for t in schema.DATASET_TOPICS.values()}
    meta: dict = {}
    origin: list = []
    epochs: list[GnssEpoch] = []
    imu: list[tuple] = []
    imu_ns: list[int] = []
    odo: list[tuple] = []
    truth_ns: list[int] = []
    truth_rows: list[tuple] = []
    cam_ns: list[int] = []
    cam_log: list[int] = []
    cam_topic: list[str] = []

    def on_info(log_ns, msg):
        try:
            meta.update(json.loads(msg.data))
        except ValueError as err:
            raise MessageError(f'dataset/info is not JSON: {err}') from err

    def on_origin(log_ns, msg):
        fix = navsatfix_to_fix(msg, schema.ORIGIN)
        origin[:] = [fix.lat_deg, fix.lon_deg, fix.alt_m]

    def on_gnss(log_ns, msg):
        epochs.append(pointcloud2_to_gnss_epoch(msg, EARTH_FRAME, schema.GNSS))

    def on_imu(log_ns, msg):
        s = imu_to_sample(msg, schema.IMU)
        imu_ns.append(s.stamp_ns)
        imu.append((*s.accel_mps2, *s.gyro_rps))

    def on_twist(log_ns, msg):
        s = twist_to_sample(msg, schema.TWIST)
        odo.append((s.stamp_ns, s.speed_mps, s.yaw_rate_rps, s.speed_var, s.yaw_rate_var))

    def on_truth(log_ns, msg):
        _frame_check(path, schema.TRUTH, msg, EARTH_FRAME)
        p, q = msg.pose.position, msg.pose.orientation
        truth_ns.append(stamp_to_ns(msg.header.stamp))
        truth_rows.append((p.x, p.y, p.z, q.x, q.y, q.z, q.w))

    def on_image(log_ns, data):
        cam_ns.append(header_stamp_ns(data))
        cam_log.append(log_ns)

    handlers = {schema.INFO: on_info, schema.ORIGIN: on_origin, schema.GNSS: on_gnss,
                schema.IMU: on_imu, schema.TWIST: on_twist, schema.TRUTH: on_truth,
                schema.IMAGE: on_image}
    found = _scan(path, wanted, handlers, namespace, raw=frozenset({schema.IMAGE}))
    if require_gnss and not found[schema.GNSS]:
        raise BagContentError(f'{path}: no topic {schema.qualified(schema.GNSS, namespace)} '
                              f'({schema.POINTCLOUD2}); is this a dataset bag?', path=path,
                              topic=schema.GNSS)
    if found[schema.IMAGE]:
        with open_bag(path) as reader:
            cam_topic = [c.topic for c in reader.connections
                         if schema.relative(c.topic, namespace) == schema.IMAGE]
    origin_llh = tuple(origin) if origin else (
        tuple(meta['origin_llh']) if meta.get('origin_llh') else None)
    imu_arr = np.array(imu, dtype=float).reshape(-1, 6)
    odo_arr = np.array(odo, dtype=float).reshape(-1, 5)
    info = dict(meta.get('info') or {})
    info['bag'] = str(path)
    return Drive(
        name=meta.get('name') or path.name, origin_llh=origin_llh, gnss=epochs,
        odometry=OdometrySeries(
            stamp_ns=np.array([r[0] for r in odo], dtype=np.int64),
            speed_mps=odo_arr[:, 1], yaw_rate_rps=odo_arr[:, 2], speed_var=odo_arr[:, 3],
            yaw_rate_var=odo_arr[:, 4]) if odo else None,
        imu=ImuSeries(stamp_ns=np.array(imu_ns, dtype=np.int64), accel_mps2=imu_arr[:, :3],
                      gyro_rps=imu_arr[:, 3:]) if imu else None,
        truth=_truth_from_rows(truth_ns, truth_rows, origin_llh),
        camera=BagCamera(path, cam_topic[0], np.array(cam_ns), np.array(cam_log))
        if cam_ns else None,
        info=info)


# ------------------------------------------------------------------------- results
@dataclass
class ResultBag:
    """The nodes' outputs recorded in a bag, as arrays.

    Attributes:
        path: The bag.
        pose_stamp_ns: (P,) ``pose`` stamps [ns].
        pose_enu_m: (P, 3) estimates in the nodes' ``map`` frame [m].
        pose_yaw_rad: (P,) headings [rad].
        pose_cov: (P, 6, 6) pose covariances [m^2, rad^2].
        pose_frame_id: Frame of ``pose`` ('' when there is none).
        fix_stamp_ns: (F,) ``fix`` stamps [ns].
        fix_llh: (F, 3) latitude [deg], longitude [deg], ellipsoidal height [m].
        fix_cov_enu_m2: (F, 3, 3) fix covariances [m^2] (NaN when unknown).
        particles: ``{stamp_ns: (N, 4) east, north, up, yaw}`` of ``particles``.
        integrity: ``integrity_risk`` messages in bag order.
        truth: ``ground_truth/pose`` when recorded too, else None.
        origin_llh: ``map/origin`` when recorded too, else None.
        topics: ``{relative topic: connections found}``.
    """

    path: Path
    pose_stamp_ns: np.ndarray
    pose_enu_m: np.ndarray
    pose_yaw_rad: np.ndarray
    pose_cov: np.ndarray
    pose_frame_id: str
    fix_stamp_ns: np.ndarray
    fix_llh: np.ndarray
    fix_cov_enu_m2: np.ndarray
    particles: dict = field(default_factory=dict)
    integrity: list[IntegrityRisk] = field(default_factory=list)
    truth: Trajectory | None = None
    origin_llh: tuple | None = None
    topics: dict = field(default_factory=dict)


def read_results(path: str | Path, namespace: str = '/', particles: bool = True
                 ) -> ResultBag:
    """Read ``pose``, ``fix``, ``particles``, ``integrity_risk`` (and ``ground_truth/pose``,
    ``map/origin`` if present) from a bag recorded from the nodes.

    ``integrity_risk`` is parsed by ``msg_adapters.parse_integrity_risk`` into
    :class:`~msg_adapters.IntegrityRisk`: level OK/ERROR/STALE, ``risk_bound``,
    ``empirical_risk``, ``divergence_risk``, ``alert_limit_m``, ``target_risk``,
    ``epoch_stamp_ns``, ``protection_level_m``, ``epoch_status``, ``risk_bounds_by_limit``
    (further alert limits) and the other values in ``extra`` (``inverse_bernoulli``, ...).

    Args:
        path: The result bag.
        namespace: Namespace the nodes ran in.
        particles: Read the particle clouds (large; False skips them).

    Raises:
        BagReadError, BagTypeError: See the module docstring.
        BagContentError: Neither ``integrity_risk`` nor ``pose``/``fix`` in the bag, or a
            message that does not parse (topic named).
    """
    path = Path(path)
    wanted = {t.name: t.msgtype for t in schema.RESULT_TOPICS.values()}
    wanted[schema.TRUTH] = schema.POSE_STAMPED
    wanted[schema.ORIGIN] = schema.NAVSATFIX
    poses: list = []
    fixes: list = []
    integrity: list[IntegrityRisk] = []
    clouds: dict = {}
    truth_ns: list[int] = []
    truth_rows: list[tuple] = []
    origin: list = []
    frames: set = set()

    def on_pose(log_ns, msg):
        poses.append(msg_to_pose(msg, schema.POSE))
        frames.add(msg.header.frame_id)

    def on_fix(log_ns, msg):
        fixes.append(navsatfix_to_fix(msg, schema.FIX))

    def on_particles(log_ns, msg):
        clouds[stamp_to_ns(msg.header.stamp)] = posearray_to_particles(msg)

    def on_integrity(log_ns, msg):
        integrity.append(parse_integrity_risk(msg, schema.INTEGRITY))

    def on_truth(log_ns, msg):
        _frame_check(path, schema.TRUTH, msg, EARTH_FRAME)
        p, q = msg.pose.position, msg.pose.orientation
        truth_ns.append(stamp_to_ns(msg.header.stamp))
        truth_rows.append((p.x, p.y, p.z, q.x, q.y, q.z, q.w))

    def on_origin(log_ns, msg):
        fix = navsatfix_to_fix(msg, schema.ORIGIN)
        origin[:] = [fix.lat_deg, fix.lon_deg, fix.alt_m]

    handlers = {schema.POSE: on_pose, schema.FIX: on_fix, schema.INTEGRITY: on_integrity,
                schema.TRUTH: on_truth, schema.ORIGIN: on_origin}
    if particles:
        handlers[schema.PARTICLES] = on_particles
    found = _scan(path, wanted, handlers, namespace)
    if not found[schema.INTEGRITY] and not found[schema.POSE] and not found[schema.FIX]:
        raise BagContentError(
            f'{path}: no {schema.qualified(schema.INTEGRITY, namespace)}, '
            f'{schema.qualified(schema.POSE, namespace)} or '
            f'{schema.qualified(schema.FIX, namespace)} topic; record the nodes\' outputs '
            '(e.g. ros2 bag record /pose /fix /particles /integrity_risk '
            '/ground_truth/pose /map/origin)', path=path)
    if len(frames) > 1:
        raise BagContentError(f'{path}: topic {schema.POSE} changes frame: {sorted(frames)}',
                              path=path, topic=schema.POSE)
    origin_llh = tuple(origin) if origin else None
    cov = [np.full((3, 3), np.nan) if f.covariance_enu_m2 is None else f.covariance_enu_m2
           for f in fixes]
    return ResultBag(
        path=path,
        pose_stamp_ns=np.array([p.stamp_ns for p in poses], dtype=np.int64),
        pose_enu_m=np.array([p.position_m for p in poses], dtype=float).reshape(-1, 3),
        pose_yaw_rad=np.array([p.yaw_rad for p in poses], dtype=float),
        pose_cov=np.array([p.covariance for p in poses], dtype=float).reshape(-1, 6, 6),
        pose_frame_id=next(iter(frames), ''),
        fix_stamp_ns=np.array([f.stamp_ns for f in fixes], dtype=np.int64),
        fix_llh=np.array([(f.lat_deg, f.lon_deg, f.alt_m) for f in fixes],
                         dtype=float).reshape(-1, 3),
        fix_cov_enu_m2=np.array(cov, dtype=float).reshape(-1, 3, 3),
        particles=clouds, integrity=integrity,
        truth=_truth_from_rows(truth_ns, truth_rows, origin_llh), origin_llh=origin_llh,
        topics=found)
