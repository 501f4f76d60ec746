"""Dataset -> rosbag2 bag (MCAP by default), with the topics of :mod:`.schema`.

:func:`convert_drive` is the library layer: no printing, no exit codes (``convert_cli`` adds
them). Messages are built by the ``msg_adapters`` writers the nodes publish with, as rosbags
dataclasses (:func:`.schema.rosbags_kit`) serialised with the ROS 2 Jazzy typestore, so no
ROS graph (and no rclpy) is needed.

Guarantees:

* **Never overwrites**: an existing output path (file, folder or dangling link) is refused
  before any work, and again just before the final rename.
* **All or nothing**: the bag is written into a hidden temporary sibling folder
  (``.NAME.partial-HOST-PID-*`` next to the output) and renamed into place only after the
  writer closed cleanly; on any error or ``KeyboardInterrupt`` the temporary folder is
  removed (after a SIGKILL the next ``gnsscam_convert`` finds it: :mod:`..io.partials`).
* **Bounded memory**: camera frames are rendered while writing, a few ahead on worker
  threads (rendering costs ~60 ms per VGA frame, writing ~1 ms), never all at once.
* **Time order**: the streams are merged by stamp, so the bag can be played or read
  sequentially; the bag time of each message is its header stamp; messages with equal
  stamps follow ``msg_adapters.wire.TIE_ORDER``.
"""
from __future__ import annotations

import dataclasses
import heapq
import json
import math
import os
import shutil
import threading
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer

from msg_adapters import (GeodeticFix, ImuSample, MessageError, TwistSample, array_to_image,
                          fix_to_navsatfix, gnss_epoch_to_pointcloud2, pose_stamped,
                          sample_to_imu, sample_to_twist)
from msg_adapters.wire import (GNSS, IMAGE, IMU, INFO, MAX_STAMP_SEC, NS_PER_S, ORIGIN,
                               STATUS_FIX, TIE_ORDER, TOPICS, TRUTH, TWIST, service_bits)

from ..core.frames import LocalFrame
from ..core.types import Drive
from ..io.partials import make_partial_dir
from . import schema
from .errors import BagContentError, BagError, BagExistsError

STORAGES = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}

#: ``progress(done_messages, total_messages, payload_bytes)``; may raise to abort.
ProgressFn = Callable[[int, int, int], None]

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
    if stamps.min() < 0 or stamps.max() >= (MAX_STAMP_SEC + 1) * NS_PER_S:
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


class _Messages:
    """The messages of one drive, one method per topic, built by the ``msg_adapters``
    writers the nodes publish with, as rosbags dataclasses (:func:`.schema.rosbags_kit`).

    Data a message cannot hold raises :class:`.BagContentError` naming the topic and index.
    """

    def __init__(self, drive: Drive, camera):
        self.kit = schema.rosbags_kit()
        self.drive = drive
        self.camera = camera
        truth = drive.truth
        self.q_truth = None
        if truth is not None and truth.yaw_rad is not None and len(truth):
            frame = LocalFrame.at_origin_or(drive.origin_llh, truth.ecef_m[0])
            self.q_truth = schema.yaw_to_ecef_quaternion(
                truth.yaw_rad, schema.enu_quaternion(frame.rot_ecef_to_enu))

    def info(self, text: str):
        return self.kit[schema.STRING](data=text)

    def origin(self, stamp_ns: int):
        """``map/origin``: status FIX, the service bits of every system in the drive,
        covariance unknown."""
        lat, lon, alt = (float(v) for v in self.drive.origin_llh)
        systems = {int(s) for ep in self.drive.gnss for s in np.unique(ep.system)}
        return fix_to_navsatfix(GeodeticFix(
            stamp_ns=stamp_ns, lat_deg=lat, lon_deg=lon, alt_m=alt, status=STATUS_FIX,
            service=service_bits(systems), frame_id=TOPICS[ORIGIN].frame_id), self.kit)

    def gnss(self, i: int):
        try:
            return gnss_epoch_to_pointcloud2(self.drive.gnss[i], TOPICS[GNSS].frame_id,
                                             self.kit)
        except MessageError as err:
            raise BagContentError(f'{GNSS}: epoch {i}: {err}', topic=GNSS) from err

    def image(self, i: int, img: np.ndarray):
        try:
            return array_to_image(img, int(self.camera.stamp_ns[i]),
                                  frame_id=TOPICS[IMAGE].frame_id,
                                  kit=self.kit)
        except MessageError as err:
            img = np.asarray(img)
            raise BagContentError(f'{IMAGE}: frame {i}: expected a uint8 (H, W) or (H, W, 3) '
                                  f'BGR image, got {img.dtype} {img.shape} ({err})',
                                  topic=IMAGE) from err

    def imu(self, i: int):
        imu = self.drive.imu
        return sample_to_imu(ImuSample(int(imu.stamp_ns[i]), imu.accel_mps2[i],
                                       imu.gyro_rps[i]), TOPICS[IMU].frame_id, self.kit)

    def twist(self, i: int):
        od = self.drive.odometry
        return sample_to_twist(TwistSample(int(od.stamp_ns[i]), od.speed_mps[i],
                                           od.yaw_rate_rps[i], od.speed_var[i],
                                           od.yaw_rate_var[i]), TOPICS[TWIST].frame_id,
                               self.kit)

    def truth(self, i: int):
        tr = self.drive.truth
        q = (0.0, 0.0, 0.0, 0.0) if self.q_truth is None else self.q_truth[i]
        return pose_stamped(int(tr.stamp_ns[i]), tr.ecef_m[i], q, TOPICS[TRUTH].frame_id,
                            self.kit)


def _keyed(stamps: np.ndarray, rank: int) -> Iterator[tuple[int, int, int]]:
    """``(stamp_ns, rank, index)`` for the merge (a function, so ``rank`` binds early)."""
    for i, stamp in enumerate(stamps.tolist()):
        yield stamp, rank, i


def _sources(drive: Drive, camera) -> tuple[dict[str, np.ndarray], int]:
    """Per topic its stamps (checked), and the first stamp of all."""
    stamps: dict[str, np.ndarray] = {}
    if drive.gnss:
        stamps[GNSS] = np.array([ep.stamp_ns for ep in drive.gnss], dtype=np.int64)
    if camera is not None and len(camera.stamp_ns):
        stamps[IMAGE] = np.asarray(camera.stamp_ns, dtype=np.int64)
    if drive.imu is not None and len(drive.imu):
        stamps[IMU] = np.asarray(drive.imu.stamp_ns, dtype=np.int64)
    if drive.odometry is not None and len(drive.odometry):
        stamps[TWIST] = np.asarray(drive.odometry.stamp_ns, dtype=np.int64)
    if drive.truth is not None and len(drive.truth):
        stamps[TRUTH] = np.asarray(drive.truth.stamp_ns, dtype=np.int64)
    if not stamps:
        raise BagContentError(f'{drive.name}: nothing to convert (no GNSS, camera, IMU, '
                              'odometry or truth)')
    for topic, st in stamps.items():
        # GNSS epochs and camera frames are events (strictly increasing); sampled series
        # may repeat a stamp.
        _check_stamps(st, topic, strict=topic in (GNSS, IMAGE))
    return stamps, int(min(int(st[0]) for st in stamps.values()))


def _tie_rank(topic: str) -> int:
    """Rank among messages with equal stamps: :data:`~msg_adapters.wire.TIE_ORDER`, then
    the other topics in the order of the layout."""
    if topic in TIE_ORDER:
        return TIE_ORDER.index(topic)
    return len(TIE_ORDER) + list(schema.DATASET_TOPICS).index(topic)


class _Sink:
    """The connections of one bag writer: serialises, writes and counts messages, and
    reports progress."""

    def __init__(self, writer: Writer, summary: ConvertSummary, namespace: str,
                 progress: ProgressFn | None):
        self.writer = writer
        self.summary = summary
        self.namespace = namespace
        self.progress = progress
        self.store = schema.typestore()
        self.conns: dict = {}
        self.done = self.nbytes = self.total = 0

    def add(self, spec: schema.TopicSpec) -> None:
        name = schema.qualified(spec.name, self.namespace)
        self.conns[spec.name] = self.writer.add_connection(
            name, spec.msgtype, typestore=self.store,
            offered_qos_profiles=[schema.qos(spec.latched)])
        self.summary.topics[name] = TopicCount(spec.msgtype)

    def put(self, topic: str, stamp_ns: int, msg) -> None:
        data = self.store.serialize_cdr(msg, msg.__msgtype__)
        self.writer.write(self.conns[topic], stamp_ns, data)
        rec = self.summary.topics[schema.qualified(topic, self.namespace)]
        rec.count += 1
        rec.payload_bytes += len(data)
        self.done += 1
        self.nbytes += len(data)
        if self.progress is not None and (topic == IMAGE
                                          or self.done % _PROGRESS_EVERY == 0):
            self.progress(self.done, self.total, self.nbytes)


def _write_all(sink: _Sink, messages: _Messages, stamps: dict[str, np.ndarray],
               first_ns: int, workers: int, waited: list[float]) -> None:
    """Register the topics and write every message of the drive in time order."""
    drive, camera = messages.drive, messages.camera
    present = {INFO} | set(stamps) | ({ORIGIN} if drive.origin_llh is not None else set())
    for spec in schema.DATASET_TOPICS.values():
        if spec.name in present:
            sink.add(spec)
    sink.total = sum(len(s) for s in stamps.values()) + (len(present) - len(stamps))
    info_text = json.dumps(dataset_info(drive, sink.namespace), allow_nan=False)
    sink.put(INFO, first_ns, messages.info(info_text))
    if ORIGIN in present:
        sink.put(ORIGIN, first_ns, messages.origin(first_ns))
    # Merge the per-topic stamp sequences: each yields (stamp, rank, index); the rank puts
    # equal stamps in the one tie order.
    order = sorted(stamps, key=_tie_rank)
    merged = heapq.merge(*[_keyed(stamps[t], rank) for rank, t in enumerate(order)])
    makers = {GNSS: messages.gnss, IMU: messages.imu, TWIST: messages.twist,
              TRUTH: messages.truth}
    frames = _frames_ahead(camera, workers, waited) if camera is not None else None
    try:
        for stamp_ns, rank, i in merged:
            topic = order[rank]
            if topic == IMAGE:
                k, img = next(frames)
                assert k == i, 'frames are consumed in index order'
                sink.put(topic, stamp_ns, messages.image(i, img))
            else:
                sink.put(topic, stamp_ns, makers[topic](i))
    finally:
        # On Ctrl-C or an error: stop the render threads before the bag is removed.
        if frames is not None:
            frames.close()


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
    messages = _Messages(drive, camera)
    workers = min(4, os.cpu_count() or 1) if workers is None else int(workers)

    started = time.perf_counter()
    if out.parent.exists() and not out.parent.is_dir():
        raise BagError(f'{out}: cannot write here: {out.parent} is not a folder', path=out)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        # Named after this host and pid, so that a later run can tell the leftover of a
        # killed conversion from a running one (io.partials.sweep_partials).
        tmp_root = make_partial_dir(out)
    except OSError as err:
        raise BagError(f'{out}: cannot write here: {err.strerror or err}', path=out) from err
    summary = ConvertSummary(path=out, storage=storage)
    waited = [0.0]
    try:
        tmp_bag = tmp_root / out.name
        with Writer(tmp_bag, version=9, storage_plugin=STORAGES[storage]) as writer:
            sink = _Sink(writer, summary, namespace, progress)
            _write_all(sink, messages, stamps, first_ns, workers, waited)
        if progress is not None:
            progress(sink.done, sink.total, sink.nbytes)
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
        shutil.rmtree(tmp_root, ignore_errors=True)
    summary.start_ns = first_ns
    summary.end_ns = max(int(s[-1]) for s in stamps.values())
    summary.bag_bytes = _dir_size(out)
    summary.seconds = time.perf_counter() - started
    summary.camera_wait_seconds = waited[0]
    return summary
