"""Dataset -> rosbag2 bag (MCAP by default), with the topics of :mod:`.schema`.

:func:`convert_drive` is the library layer: no printing, no exit codes (``convert_cli`` adds
them). Messages are rosbags dataclasses serialised with the ROS 2 Jazzy typestore, so no
ROS graph (and no rclpy) is needed.

Guarantees:

* **Never overwrites**: an existing output path (file, folder or dangling link) is refused
  before any work, and again just before the final rename.
* **All or nothing**: the bag is written into a hidden temporary sibling folder
  (``.NAME.partial-*`` next to the output) and renamed into place only after the writer
  closed cleanly; on any error or ``KeyboardInterrupt`` the temporary folder is removed.
* **Bounded memory**: camera frames are rendered while writing, a few ahead on worker
  threads (rendering costs ~60 ms per VGA frame, writing ~1 ms), never all at once.
* **Time order**: the streams are merged by stamp, so the bag can be played or read
  sequentially; the bag time of each message is its header stamp.
"""
from __future__ import annotations

import dataclasses
import heapq
import json
import math
import os
import shutil
import tempfile
import threading
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer

from ..core.frames import LocalFrame
from ..core.types import Drive
from . import schema
from .errors import BagContentError, BagError, BagExistsError

STORAGES = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}

#: ``progress(done_messages, total_messages, payload_bytes)``; may raise to abort.
ProgressFn = Callable[[int, int, int], None]

# GNSS `system` codes -> NavSatStatus service bits (SBAS and QZSS have none).
_SERVICE_BITS = {1: 1, 4: 2, 32: 4, 8: 8}
_PROGRESS_EVERY = 500          # messages between progress calls (images: every frame)


@dataclass
class TopicCount:
    """Messages written on one topic.

    Attributes:
        msgtype: Message type.
        count: Number of messages.
        payload_bytes: Serialised size of all messages [bytes].
    """

    msgtype: str
    count: int = 0
    payload_bytes: int = 0


@dataclass
class ConvertSummary:
    """What :func:`convert_drive` wrote.

    Attributes:
        path: The bag folder.
        storage: ``'mcap'`` or ``'sqlite3'``.
        topics: Per qualified topic name, its type and counts (in registration order).
        start_ns: First bag time [ns].
        end_ns: Last bag time [ns].
        bag_bytes: Size of the bag folder on disk [bytes].
        seconds: Wall time of the conversion [s].
        camera_wait_seconds: Part of it spent waiting for camera frames to render [s].
    """

    path: Path
    storage: str
    topics: dict[str, TopicCount] = field(default_factory=dict)
    start_ns: int = 0
    end_ns: int = 0
    bag_bytes: int = 0
    seconds: float = 0.0
    camera_wait_seconds: float = 0.0

    @property
    def messages(self) -> int:
        """Total number of messages."""
        return sum(t.count for t in self.topics.values())

    @property
    def duration_s(self) -> float:
        """Time span of the bag [s]."""
        return (self.end_ns - self.start_ns) / 1e9

    @property
    def mb_per_s(self) -> float:
        """End-to-end conversion speed: bag size / wall time [MB/s] (1 MB = 1e6 bytes)."""
        return self.bag_bytes / 1e6 / self.seconds if self.seconds > 0 else math.nan

    @property
    def write_mb_per_s(self) -> float:
        """Speed without the time spent waiting for rendered frames [MB/s]."""
        busy = self.seconds - self.camera_wait_seconds
        return self.bag_bytes / 1e6 / busy if busy > 0 else math.nan

    def as_dict(self) -> dict:
        """JSON-able form (for ``--json`` and logs)."""
        return {'path': str(self.path), 'storage': self.storage,
                'topics': {k: dataclasses.asdict(v) for k, v in self.topics.items()},
                'messages': self.messages, 'start_ns': self.start_ns, 'end_ns': self.end_ns,
                'duration_s': self.duration_s, 'bag_bytes': self.bag_bytes,
                'seconds': self.seconds, 'camera_wait_seconds': self.camera_wait_seconds,
                'mb_per_s': self.mb_per_s, 'write_mb_per_s': self.write_mb_per_s}


# ------------------------------------------------------------------------- helpers
def _jsonable(value, path: str, omitted: list[str]):
    """``value`` as plain JSON (numpy scalars unwrapped, non-finite floats -> None).

    Arrays with more than 16 elements are left out (their key is recorded in ``omitted``):
    the per-epoch error decomposition of the emulated drive belongs to the evaluation, not
    to a message.
    """
    if isinstance(value, dict):
        out = {}
        for k, v in value.items():
            item = _jsonable(v, f'{path}.{k}' if path else str(k), omitted)
            if item is not _OMIT:
                out[str(k)] = item
        return out
    if isinstance(value, np.ndarray):
        if value.size > 16:
            omitted.append(path)
            return _OMIT
        return _jsonable(value.tolist(), path, omitted)
    if isinstance(value, (list, tuple)):
        items = [_jsonable(v, f'{path}[{i}]', omitted) for i, v in enumerate(value)]
        return [v for v in items if v is not _OMIT]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if value is None or isinstance(value, (str, int, float, bool)):
        return value
    return str(value)


_OMIT = object()


def dataset_info(drive: Drive, namespace: str = '/') -> dict:
    """The ``dataset/info`` JSON object of a drive (see :mod:`.schema`)."""
    omitted: list[str] = []
    info = _jsonable(drive.info or {}, '', omitted)
    origin = None if drive.origin_llh is None else [float(v) for v in drive.origin_llh]
    return {'format': schema.FORMAT, 'name': drive.name, 'origin_llh': origin,
            'info': info, 'omitted_info': omitted,
            'topics': {schema.qualified(t.name, namespace): t.msgtype
                       for t in schema.DATASET_TOPICS.values()},
            'converter': 'gnsscam_ros.bags.convert'}


def _check_stamps(stamps: np.ndarray, topic: str, strict: bool) -> None:
    """Refuse stamps that a bag cannot hold or that go backwards (before writing)."""
    if stamps.size == 0:
        return
    if stamps.min() < 0 or stamps.max() >= 2 ** 31 * schema.NS_PER_S:
        raise BagContentError(f'{topic}: stamps outside builtin_interfaces/Time '
                              f'(0 .. 2^31 s)', topic=topic)
    steps = np.diff(stamps)
    bad = np.flatnonzero(steps <= 0 if strict else steps < 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise BagContentError(f'{topic}: stamp {int(stamps[i])} ns at index {i} is not after '
                              f'{int(stamps[i - 1])} ns', topic=topic)


def _dir_size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob('*') if p.is_file())


def _frames_ahead(camera, workers: int, waited: list[float]
                  ) -> Iterator[tuple[int, np.ndarray]]:
    """Yield ``(index, image)`` for every frame in order, rendering ahead on threads.

    Each worker thread renders with its own copy of the stream (``dataclasses.replace``):
    a renderer keeps caches and is not shared between threads, and the stream's images are
    a deterministic function of the index, so copies give identical frames. At most
    ``2 * workers`` frames are in flight. Streams that are not dataclasses are rendered in
    the calling thread.

    Args:
        camera: Object with ``stamp_ns`` and ``image(i)``.
        workers: Render threads (<= 1: render in the calling thread).
        waited: One-element list accumulating the time spent waiting [s].
    """
    n = len(camera.stamp_ns)
    if workers <= 1 or not dataclasses.is_dataclass(camera):
        for i in range(n):
            t0 = time.perf_counter()
            img = camera.image(i)
            waited[0] += time.perf_counter() - t0
            yield i, img
        return
    local = threading.local()

    def render(i: int) -> np.ndarray:
        stream = getattr(local, 'stream', None)
        if stream is None:
            stream = local.stream = dataclasses.replace(camera)
        return stream.image(i)

    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix='gnsscam_render')
    pending: deque = deque()
    try:
        nxt = 0
        for i in range(n):
            while nxt < n and len(pending) < 2 * workers:
                pending.append(pool.submit(render, nxt))
                nxt += 1
            t0 = time.perf_counter()
            img = pending.popleft().result()
            waited[0] += time.perf_counter() - t0
            yield i, img
    finally:
        # On Ctrl-C or an error downstream: drop queued frames, finish the running ones.
        pool.shutdown(wait=True, cancel_futures=True)


class _Builder:
    """Builds the rosbags messages of one drive (one method per topic)."""

    def __init__(self, drive: Drive, camera):
        self.store = schema.typestore()
        T = self.store.types
        self.T = T
        self.drive = drive
        self.camera = camera
        self.Time = T['builtin_interfaces/msg/Time']
        self.Header = T['std_msgs/msg/Header']
        self.fields = [T['sensor_msgs/msg/PointField'](
            name=name, offset=schema.GNSS_DTYPE.fields[name][1],
            datatype=schema.POINTFIELD_CODE[np.dtype(schema.GNSS_DTYPE.fields[name][0].type)],
            count=1) for name in schema.GNSS_DTYPE.names]
        truth = drive.truth
        self.q_truth = None
        if truth is not None and truth.yaw_rad is not None and len(truth):
            frame = (LocalFrame(*drive.origin_llh) if drive.origin_llh is not None
                     else LocalFrame.from_ecef(truth.ecef_m[0]))
            self.q_truth = schema.yaw_to_ecef_quaternion(
                truth.yaw_rad, schema.enu_quaternion(frame.rot_ecef_to_enu))

    def header(self, stamp_ns: int, frame_id: str):
        sec, nanosec = schema.split_ns(stamp_ns)
        return self.Header(stamp=self.Time(sec=sec, nanosec=nanosec), frame_id=frame_id)

    def info(self, stamp_ns: int, text: str):
        return self.T[schema.STRING](data=text)

    def origin(self, stamp_ns: int):
        T = self.T
        lat, lon, alt = (float(v) for v in self.drive.origin_llh)
        systems = {int(s) for ep in self.drive.gnss for s in np.unique(ep.system)}
        service = 0
        for s in systems:
            service |= _SERVICE_BITS.get(s, 0)
        status = T['sensor_msgs/msg/NavSatStatus'](status=0, service=service)
        return T[schema.NAVSATFIX](
            header=self.header(stamp_ns, schema.MAP_FRAME), status=status, latitude=lat,
            longitude=lon, altitude=alt, position_covariance=np.zeros(9),
            position_covariance_type=0)

    def gnss(self, i: int):
        ep = self.drive.gnss[i]
        n = ep.n_sv
        sv = np.asarray(ep.sv_pos_ecef_m, dtype=float).reshape(n, 3)
        sv_id = np.asarray(ep.sv_id)
        system = np.asarray(ep.system)
        if n and (sv_id.min() < 0 or sv_id.max() > 65535):
            raise BagContentError(f'{schema.GNSS}: epoch {i}: sv_id outside UINT16',
                                  topic=schema.GNSS)
        if n and (system.min() < 0 or system.max() > 255):
            raise BagContentError(f'{schema.GNSS}: epoch {i}: system outside UINT8',
                                  topic=schema.GNSS)
        pts = np.zeros(n, dtype=schema.GNSS_DTYPE)
        pts['x'], pts['y'], pts['z'] = sv[:, 0], sv[:, 1], sv[:, 2]
        pts['pseudorange'] = ep.pr_m
        pts['variance'] = ep.var_m2
        pts['cn0'] = ep.cn0_dbhz
        pts['elevation'] = ep.elevation_deg
        pts['sv_id'] = sv_id
        pts['system'] = system
        step = schema.GNSS_DTYPE.itemsize
        return self.T[schema.POINTCLOUD2](
            header=self.header(ep.stamp_ns, schema.EARTH_FRAME), height=1, width=n,
            fields=self.fields, is_bigendian=False, point_step=step, row_step=step * n,
            data=np.frombuffer(pts.tobytes(), dtype=np.uint8),
            # is_dense: no invalid (non-finite) satellite positions.
            is_dense=bool(np.all(np.isfinite(sv))))

    def image(self, i: int, img: np.ndarray):
        img = np.asarray(img)
        if img.dtype != np.uint8 or img.ndim not in (2, 3) or (
                img.ndim == 3 and img.shape[2] != 3) or img.size == 0:
            raise BagContentError(f'{schema.IMAGE}: frame {i}: expected a uint8 (H, W) or '
                                  f'(H, W, 3) BGR image, got {img.dtype} {img.shape}',
                                  topic=schema.IMAGE)
        h, w = img.shape[:2]
        channels = 1 if img.ndim == 2 else 3
        return self.T[schema.IMAGE_TYPE](
            header=self.header(int(self.camera.stamp_ns[i]), schema.CAMERA_FRAME),
            height=h, width=w, encoding='mono8' if channels == 1 else 'bgr8',
            is_bigendian=0, step=w * channels,
            data=np.ascontiguousarray(img).reshape(-1))

    def imu(self, i: int):
        T, imu = self.T, self.drive.imu
        Vec = T['geometry_msgs/msg/Vector3']
        a, g = imu.accel_mps2[i], imu.gyro_rps[i]
        ocov = np.zeros(9)
        ocov[0] = -1.0            # REP 145: no orientation estimate
        return T[schema.IMU_TYPE](
            header=self.header(int(imu.stamp_ns[i]), schema.BASE_FRAME),
            orientation=T['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=ocov,
            angular_velocity=Vec(x=float(g[0]), y=float(g[1]), z=float(g[2])),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=Vec(x=float(a[0]), y=float(a[1]), z=float(a[2])),
            linear_acceleration_covariance=np.zeros(9))

    def twist(self, i: int):
        T, od = self.T, self.drive.odometry
        Vec = T['geometry_msgs/msg/Vector3']
        cov = np.zeros(36)
        cov[0], cov[35] = od.speed_var[i], od.yaw_rate_var[i]
        twist = T['geometry_msgs/msg/Twist'](
            linear=Vec(x=float(od.speed_mps[i]), y=0.0, z=0.0),
            angular=Vec(x=0.0, y=0.0, z=float(od.yaw_rate_rps[i])))
        return T[schema.TWIST_TYPE](
            header=self.header(int(od.stamp_ns[i]), schema.BASE_FRAME),
            twist=T['geometry_msgs/msg/TwistWithCovariance'](twist=twist, covariance=cov))

    def truth(self, i: int):
        T, tr = self.T, self.drive.truth
        p = tr.ecef_m[i]
        q = (0.0, 0.0, 0.0, 0.0) if self.q_truth is None else self.q_truth[i]
        pose = T['geometry_msgs/msg/Pose'](
            position=T['geometry_msgs/msg/Point'](x=float(p[0]), y=float(p[1]),
                                                  z=float(p[2])),
            orientation=T['geometry_msgs/msg/Quaternion'](x=float(q[0]), y=float(q[1]),
                                                          z=float(q[2]), w=float(q[3])))
        return T[schema.POSE_STAMPED](
            header=self.header(int(tr.stamp_ns[i]), schema.EARTH_FRAME), pose=pose)


def _keyed(stamps: np.ndarray, rank: int) -> Iterator[tuple[int, int, int]]:
    """``(stamp_ns, rank, index)`` for the merge (a function, so ``rank`` binds early)."""
    for i, stamp in enumerate(stamps.tolist()):
        yield stamp, rank, i


def _sources(drive: Drive, camera) -> tuple[dict[str, np.ndarray], int]:
    """Per topic its stamps (checked), and the first stamp of all."""
    stamps: dict[str, np.ndarray] = {}
    if drive.gnss:
        stamps[schema.GNSS] = np.array([ep.stamp_ns for ep in drive.gnss], dtype=np.int64)
    if camera is not None and len(camera.stamp_ns):
        stamps[schema.IMAGE] = np.asarray(camera.stamp_ns, dtype=np.int64)
    if drive.imu is not None and len(drive.imu):
        stamps[schema.IMU] = np.asarray(drive.imu.stamp_ns, dtype=np.int64)
    if drive.odometry is not None and len(drive.odometry):
        stamps[schema.TWIST] = np.asarray(drive.odometry.stamp_ns, dtype=np.int64)
    if drive.truth is not None and len(drive.truth):
        stamps[schema.TRUTH] = np.asarray(drive.truth.stamp_ns, dtype=np.int64)
    if not stamps:
        raise BagContentError(f'{drive.name}: nothing to convert (no GNSS, camera, IMU, '
                              'odometry or truth)')
    for topic, st in stamps.items():
        # GNSS epochs and camera frames are events (strictly increasing); sampled series
        # may repeat a stamp.
        _check_stamps(st, topic, strict=topic in (schema.GNSS, schema.IMAGE))
    return stamps, int(min(int(st[0]) for st in stamps.values()))


# --------------------------------------------------------------------------- convert
def convert_drive(drive: Drive, out_path: str | os.PathLike, storage: str = 'mcap',
                  progress: ProgressFn | None = None, camera=None, namespace: str = '/',
                  workers: int | None = None) -> ConvertSummary:
    """Write a drive into a new rosbag2 bag (layout: :mod:`.schema`).

    Args:
        drive: The dataset (GNSS, odometry, IMU, truth; ``drive.camera`` if set).
        out_path: Bag folder to create; must not exist.
        storage: ``'mcap'`` (default, as ROS 2 Jazzy's ``ros2 bag``) or ``'sqlite3'``.
        progress: Called as ``progress(done, total, payload_bytes)`` every few hundred
            messages and after each camera frame; an exception it raises (e.g.
            ``KeyboardInterrupt``) aborts the conversion cleanly.
        camera: Camera stream (``stamp_ns`` (n,) [ns] and ``image(i)`` -> uint8 BGR
            (H, W, 3) or grey (H, W)); default ``drive.camera``.
        namespace: Namespace the topics are written under (default ``/``).
        workers: Threads rendering camera frames ahead (default: ``min(4, cpu count)``).

    Returns:
        What was written, with sizes and timing.

    Raises:
        BagExistsError: ``out_path`` exists (nothing is touched).
        BagContentError: Data that a bag cannot hold (stamps going backwards or out of
            range, ids out of range, bad images); named by topic.
        BagError: The writer failed (chained from the rosbags error).
        ValueError: Unknown ``storage``.
        KeyboardInterrupt: Re-raised after cleaning up.
    """
    if storage not in STORAGES:
        raise ValueError(f'unknown storage {storage!r}; use one of {sorted(STORAGES)}')
    out = Path(out_path)
    if out.exists() or out.is_symlink():
        raise BagExistsError(f'{out} exists; not overwriting', path=out)
    camera = drive.camera if camera is None else camera
    if camera is not None and not hasattr(camera, 'image'):
        camera = None           # e.g. a smartLoc drive: no image stream
    stamps, first_ns = _sources(drive, camera)
    builder = _Builder(drive, camera)
    workers = min(4, os.cpu_count() or 1) if workers is None else int(workers)

    started = time.perf_counter()
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp_root = Path(tempfile.mkdtemp(prefix=f'.{out.name}.partial-', dir=out.parent))
    summary = ConvertSummary(path=out, storage=storage)
    waited = [0.0]
    frames = None
    try:
        tmp_bag = tmp_root / out.name
        with Writer(tmp_bag, version=9, storage_plugin=STORAGES[storage]) as writer:
            store = builder.store
            conns = {}
            present = {schema.INFO} | set(stamps)
            if drive.origin_llh is not None:
                present.add(schema.ORIGIN)
            for spec in schema.DATASET_TOPICS.values():
                if spec.name not in present:
                    continue
                name = schema.qualified(spec.name, namespace)
                conns[spec.name] = writer.add_connection(
                    name, spec.msgtype, typestore=store,
                    offered_qos_profiles=[schema.qos(spec.latched)])
                summary.topics[name] = TopicCount(spec.msgtype)
            total = sum(len(s) for s in stamps.values()) + (len(present) - len(stamps))
            done = nbytes = 0

            def put(topic: str, stamp_ns: int, msg) -> None:
                nonlocal done, nbytes
                data = store.serialize_cdr(msg, msg.__msgtype__)
                writer.write(conns[topic], stamp_ns, data)
                rec = summary.topics[schema.qualified(topic, namespace)]
                rec.count += 1
                rec.payload_bytes += len(data)
                done += 1
                nbytes += len(data)

            info_text = json.dumps(dataset_info(drive, namespace), allow_nan=False)
            put(schema.INFO, first_ns, builder.info(first_ns, info_text))
            if schema.ORIGIN in conns:
                put(schema.ORIGIN, first_ns, builder.origin(first_ns))

            # Merge the per-topic stamp sequences: each yields (stamp, rank, index); the
            # rank keeps a fixed topic order among equal stamps.
            order = [t for t in schema.DATASET_TOPICS if t in stamps]
            merged = heapq.merge(*[_keyed(stamps[t], rank) for rank, t in enumerate(order)])
            if camera is not None:
                frames = _frames_ahead(camera, workers, waited)
            makers = {schema.GNSS: builder.gnss, schema.IMU: builder.imu,
                      schema.TWIST: builder.twist, schema.TRUTH: builder.truth}
            for stamp_ns, rank, i in merged:
                topic = order[rank]
                if topic == schema.IMAGE:
                    k, img = next(frames)
                    assert k == i, 'frames are consumed in index order'
                    put(topic, stamp_ns, builder.image(i, img))
                else:
                    put(topic, stamp_ns, makers[topic](i))
                if progress is not None and (topic == schema.IMAGE
                                             or done % _PROGRESS_EVERY == 0):
                    progress(done, total, nbytes)
            if frames is not None:
                frames.close()
        if progress is not None:
            progress(done, total, nbytes)
        if out.exists() or out.is_symlink():
            raise BagExistsError(f'{out} appeared while converting; not overwriting',
                                 path=out)
        # A directory rename within one file system is atomic: readers see no bag or the
        # whole bag.
        os.rename(tmp_bag, out)
    except BagError:
        raise
    except (ValueError, TypeError) as err:
        raise BagContentError(f'{out}: cannot convert {drive.name}: {err}', path=out) from err
    except OSError as err:
        raise BagError(f'{out}: write failed: {err}', path=out) from err
    except Exception as err:  # rosbags WriterError and friends
        raise BagError(f'{out}: write failed: {type(err).__name__}: {err}', path=out) from err
    finally:
        if frames is not None:
            frames.close()
        shutil.rmtree(tmp_root, ignore_errors=True)
    summary.start_ns = first_ns
    summary.end_ns = max(int(s[-1]) for s in stamps.values())
    summary.bag_bytes = _dir_size(out)
    summary.seconds = time.perf_counter() - started
    summary.camera_wait_seconds = waited[0]
    return summary
