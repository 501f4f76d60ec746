"""The valid input the campaigns play between (and around) the faults.

A seeded emulated drive (:func:`~gnsscam_ros.datasets.emulated.drive.make_emulated_drive`):
GNSS epochs at 1 Hz, the IMU decimated to ``imu_rate_hz`` (the dead reckoning takes its speed
and yaw rate from the odometry; the IMU stream is there to be a live input that can be
fuzzed), odometry twist at 10 Hz, and optionally camera frames: synthetic street views
(:mod:`gnsscam_ros.vision.synthetic`) placed on the drive's true positions, with a small map
database of the same scenes, so that camera_node decodes and matches every valid frame and
fusion_node gets matches where the vehicle really is.

Every message is built by the ``msg_adapters`` writers the nodes and the bag converter use,
in the wire contract's equal-stamp order (``msg_adapters.wire.TIE_ORDER``).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

import msg_adapters as ma
from gnsscam_ros.core.frames import LocalFrame
from gnsscam_ros.core.motion import DeadReckoningState
from gnsscam_ros.datasets.emulated.drive import make_emulated_drive
from msg_adapters import wire
from gnsscam_ros.vision.synthetic import synthetic_scene
from gnsscam_ros.vision.synthetic import perturb_view
from gnsscam_ros.vision.features import OrbExtractor, OrbParams
from gnsscam_ros.vision.database import MapDatabase, PositionTable

#: The input topics of the graph: the four the sensors feed and the three links between
#: the nodes (a second publisher on them is a fault the nodes must survive too).
SENSOR_TOPICS = (wire.GNSS, wire.IMU, wire.TWIST, wire.IMAGE)
LINK_TOPICS = (wire.GNSS_MEASUREMENTS, wire.DEAD_RECKONING, wire.MATCHES)
INPUT_TOPICS = SENSOR_TOPICS + LINK_TOPICS

_TIE = {topic: rank for rank, topic in enumerate(wire.TIE_ORDER)}


@dataclass(frozen=True)
class StreamConfig:
    """What the valid stream holds.

    Attributes:
        seed: Drive seed (and of the camera frames).
        duration_s: Drive length [s].
        faults: Faulty satellites per faulty epoch of the emulated drive (0: none).
        gnss_rate_hz: GNSS epochs per second.
        imu_rate_hz: IMU samples per second published (the drive has 100 Hz).
        camera: Publish camera frames (and build the map database that matches them).
        camera_period_s: One frame per this much stamp time, half a period before each
            GNSS epoch.
        image_shape: (height, width) of the frames [px].
    """

    seed: int = 1
    duration_s: float = 40.0
    faults: int = 0
    gnss_rate_hz: float = 1.0
    imu_rate_hz: float = 10.0
    camera: bool = True
    camera_period_s: float = 1.0
    image_shape: tuple[int, int] = (240, 320)


@dataclass(frozen=True)
class Event:
    """One valid message of the stream: ``topic`` at ``stamp_ns``, ``index`` into its series."""

    stamp_ns: int
    rank: int
    topic: str
    index: int


@lru_cache(maxsize=4)
def emulated_drive(seed: int, duration_s: float, faults: int, gnss_rate_hz: float = 1.0):
    """The emulated drive (cached: generating it takes a few seconds)."""
    return make_emulated_drive(seed, faults=faults, duration_s=duration_s,
                               gnss_rate_hz=gnss_rate_hz)


class ValidStream:
    """The stamp-ordered valid messages of one drive, and its ground truth.

    Args:
        config: What to play.
        work_dir: Folder for the map database (camera only).
    """

    def __init__(self, config: StreamConfig, work_dir: str | Path):
        self.config = config
        self.drive = drive = emulated_drive(config.seed, float(config.duration_s),
                                            config.faults, float(config.gnss_rate_hz))
        self.frame = LocalFrame(*drive.origin_llh)
        self.truth_stamp_ns = np.asarray(drive.truth.stamp_ns, dtype=np.int64)
        self.truth_enu = self.frame.ecef_to_enu(drive.truth.ecef_m)
        self.gnss_stamps = [int(e.stamp_ns) for e in drive.gnss]
        step = max(1, int(round(100.0 / max(config.imu_rate_hz, 1e-3))))
        self.imu_index = np.arange(0, len(drive.imu), step)
        self.camera_stamps = self._camera_stamps() if config.camera else []
        self.database_path = None
        if config.camera:
            self.database_path = self._build_database(Path(work_dir) / 'fuzz_map.npz')
        events = [Event(s, _TIE[wire.GNSS], wire.GNSS, k)
                  for k, s in enumerate(self.gnss_stamps)]
        events += [Event(int(drive.imu.stamp_ns[i]), _TIE[wire.IMU], wire.IMU, j)
                   for j, i in enumerate(self.imu_index)]
        events += [Event(int(s), _TIE[wire.TWIST], wire.TWIST, k)
                   for k, s in enumerate(drive.odometry.stamp_ns)]
        events += [Event(s, _TIE[wire.IMAGE], wire.IMAGE, k)
                   for k, s in enumerate(self.camera_stamps)]
        self.events = sorted(events, key=lambda e: (e.stamp_ns, e.rank))

    # ------------------------------------------------------------------ camera
    def _camera_stamps(self) -> list[int]:
        period_ns = int(self.config.camera_period_s * 1e9)
        first, last = self.gnss_stamps[0], self.gnss_stamps[-1]
        return list(range(first + period_ns // 2, last, period_ns))

    def scene(self, k: int) -> np.ndarray:
        """The database view of camera frame ``k`` (BGR)."""
        return synthetic_scene(k, seed=1000 + self.config.seed,
                               shape=tuple(self.config.image_shape))

    def camera_frame(self, k: int) -> np.ndarray:
        """Camera frame ``k``: another view of its database scene (BGR)."""
        rng = np.random.default_rng([self.config.seed, 77, k])
        return perturb_view(self.scene(k), rng)

    def _build_database(self, path: Path) -> Path:
        n = len(self.camera_stamps)
        extractor = OrbExtractor(OrbParams())
        descriptors = [extractor.descriptors(self.scene(k)) for k in range(n)]
        enu = np.array([self.truth_at(s) for s in self.camera_stamps]).reshape(-1, 3)
        table = PositionTable.from_columns(('east_m', 'north_m', 'up_m'), enu)
        db = MapDatabase.build(descriptors, [f'scene_{k:05d}' for k in range(n)], table,
                               branching=10, depth=3, seed=0)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.unlink(missing_ok=True)
        db.save(path)
        return path

    # ------------------------------------------------------------------ messages
    def message(self, event: Event):
        """The rclpy message of a valid event."""
        drive, k = self.drive, event.index
        if event.topic == wire.GNSS:
            return ma.gnss_epoch_to_pointcloud2(drive.gnss[k])
        if event.topic == wire.IMU:
            i = int(self.imu_index[k])
            return ma.sample_to_imu(ma.ImuSample(int(drive.imu.stamp_ns[i]),
                                                 drive.imu.accel_mps2[i], drive.imu.gyro_rps[i]))
        if event.topic == wire.TWIST:
            odo = drive.odometry
            return ma.sample_to_twist(ma.TwistSample(
                int(odo.stamp_ns[k]), float(odo.speed_mps[k]), float(odo.yaw_rate_rps[k]),
                float(odo.speed_var[k]), float(odo.yaw_rate_var[k])))
        if event.topic == wire.IMAGE:
            return ma.array_to_image(self.camera_frame(k), self.camera_stamps[k])
        raise ValueError(f'no valid stream on {event.topic}')

    def templates(self, stamp_ns: int) -> dict:
        """A valid message of every input topic at ``stamp_ns`` (the seeds of the faults):
        sensor messages from the drive sample at or before it, and plausible link
        messages (the epoch's satellites, a dead-reckoning state, the true position as a
        camera match)."""
        drive = self.drive
        k = max(0, int(np.searchsorted(self.gnss_stamps, stamp_ns, 'right')) - 1)
        epoch = drive.gnss[k]
        i = max(0, int(np.searchsorted(drive.imu.stamp_ns, stamp_ns, 'right')) - 1)
        j = max(0, int(np.searchsorted(drive.odometry.stamp_ns, stamp_ns, 'right')) - 1)
        truth = self.truth_at(stamp_ns)
        odo = drive.odometry
        cloud = ma.gnss_epoch_to_pointcloud2(epoch)
        state = DeadReckoningState(
            stamp_ns=stamp_ns, x_m=float(truth[0]), y_m=float(truth[1]), yaw_rad=0.0,
            speed_mps=float(odo.speed_mps[j]), yaw_rate_rps=float(odo.yaw_rate_rps[j]),
            speed_var=0.01, yaw_rate_var=1e-4, distance_var_m2=1.0, yaw_var_rad2=1e-3)
        matches = ma.CameraMatches(stamp_ns=stamp_ns, position_m=truth.reshape(1, 3),
                                   score=np.array([0.5]), image_id=np.array([0]))
        small = self.camera_frame(0) if self.config.camera else np.full(
            tuple(self.config.image_shape) + (3,), 128, np.uint8)
        out = {
            wire.GNSS: cloud,
            wire.GNSS_MEASUREMENTS: ma.gnss_epoch_to_pointcloud2(epoch),
            wire.IMU: ma.sample_to_imu(ma.ImuSample(int(drive.imu.stamp_ns[i]),
                                                    drive.imu.accel_mps2[i],
                                                    drive.imu.gyro_rps[i])),
            wire.TWIST: ma.sample_to_twist(ma.TwistSample(
                int(odo.stamp_ns[j]), float(odo.speed_mps[j]), float(odo.yaw_rate_rps[j]),
                float(odo.speed_var[j]), float(odo.yaw_rate_var[j]))),
            wire.IMAGE: ma.array_to_image(small, stamp_ns),
            wire.DEAD_RECKONING: ma.dead_reckoning_to_odometry(state),
            wire.MATCHES: ma.matches_to_pointcloud2(matches),
        }
        for msg in out.values():
            msg.header.stamp = ma.ns_to_stamp(stamp_ns)
        return out

    # ------------------------------------------------------------------ truth
    def truth_at(self, stamp_ns: int) -> np.ndarray:
        """True position (east, north, up in the drive's frame) at ``stamp_ns`` [m]."""
        t = self.truth_stamp_ns
        return np.array([np.interp(stamp_ns, t, self.truth_enu[:, a]) for a in range(3)])

    def horizontal_error_m(self, stamp_ns: int, lat_deg: float, lon_deg: float,
                           alt_m: float) -> float:
        """Horizontal distance of a WGS84 estimate from the truth at ``stamp_ns`` [m]
        (inf when the estimate is not finite)."""
        if not np.all(np.isfinite([lat_deg, lon_deg, alt_m])):
            return float('inf')
        enu = self.frame.geodetic_to_enu(lat_deg, lon_deg, alt_m)
        truth = self.truth_at(stamp_ns)
        return float(np.hypot(*(np.asarray(enu).reshape(3)[:2] - truth[:2])))

    def seconds(self, stamp_ns: int) -> float:
        """Stamp time since the first GNSS epoch [s]."""
        return (int(stamp_ns) - self.gnss_stamps[0]) / 1e9
