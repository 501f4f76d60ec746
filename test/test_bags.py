"""Dataset <-> rosbag2 bags: round trips, an independent decoder, bad input, Ctrl-C, and the
evaluation of a recorded result bag."""
import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import weakref
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from conftest import SMARTLOC_EXCERPT
from rosbags.rosbag2 import StoragePlugin, Writer

from msg_adapters.wire import GNSS_DTYPE
from gnsscam_ros.bags import schema
from gnsscam_ros.bags.convert import convert_drive
from gnsscam_ros.bags.convert_cli import main as convert_main
from gnsscam_ros.bags.errors import (BagContentError, BagError, BagExistsError, BagReadError,
                                     BagTypeError)
from gnsscam_ros.bags.read import bag_topics, read_drive, read_results
from gnsscam_ros.core.frames import LocalFrame
from gnsscam_ros.core.types import Drive, GnssEpoch, ImuSeries, OdometrySeries, Trajectory

T0 = 1_700_000_000 * 10 ** 9
ORIGIN = (50.1109, 8.6821, 110.0)


# ----------------------------------------------------------------------- fixtures
class FakeCamera:
    """Deterministic frames; remembers which frames are still alive (memory bound)."""

    def __init__(self, stamps_ns, shape=(48, 64, 3), fail_at=None):
        self.stamp_ns = np.asarray(stamps_ns, dtype=np.int64)
        self.shape = shape
        self.fail_at = fail_at
        self.refs = []
        self.max_alive = 0

    def __len__(self):
        return len(self.stamp_ns)

    def frame(self, i):
        shape = self.shape[:2] if i == 3 else self.shape     # one grey (mono8) frame
        return np.random.default_rng(1000 + i).integers(0, 256, shape, dtype=np.uint8)

    def image(self, i):
        if self.fail_at is not None and i == self.fail_at:
            raise RuntimeError(f'render failed at frame {i}')
        img = self.frame(i)
        self.refs = [r for r in self.refs if r() is not None] + [weakref.ref(img)]
        self.max_alive = max(self.max_alive, len(self.refs))
        return img


@dataclass(eq=False)
class FakeStream:
    """A dataclass stream: the converter renders it on worker threads (per-thread copies)."""

    stamp_ns: np.ndarray
    fail_at: int | None = None
    log: list = field(default_factory=list)        # shared by the copies (shallow)
    refs: list = field(default_factory=list)
    max_alive: list = field(default_factory=lambda: [0])
    lock: threading.Lock = field(default_factory=threading.Lock)

    def image(self, i):
        if self.fail_at is not None and i == self.fail_at:
            raise RuntimeError(f'render failed at frame {i}')
        img = np.random.default_rng(2000 + i).integers(0, 256, (24, 32, 3), dtype=np.uint8)
        with self.lock:
            self.log.append((id(self), i))
            self.refs[:] = [r for r in self.refs if r() is not None] + [weakref.ref(img)]
            self.max_alive[0] = max(self.max_alive[0], len(self.refs))
        return img


def synthetic_drive(camera=True, origin=True, yaw=True, name='synthetic') -> Drive:
    """A small drive touching every field: NaN C/N0, several systems, wrapping headings,
    stamps shared between topics."""
    rng = np.random.default_rng(7)
    frame = LocalFrame(*ORIGIN)
    gnss = []
    for k in range(6):
        n = 4 + k % 4
        cn0 = rng.uniform(20, 50, n)
        if k == 2:
            cn0[1] = np.nan
        sv = rng.normal(0, 1.5e7, (n, 3))
        sv *= 2.6e7 / np.linalg.norm(sv, axis=1, keepdims=True)   # at GPS orbit radius
        gnss.append(GnssEpoch(
            stamp_ns=T0 + k * 200_000_000, sv_pos_ecef_m=sv,
            pr_m=rng.uniform(2.0e7, 2.5e7, n), var_m2=rng.uniform(1, 50, n),
            sv_id=rng.integers(1, 400, n), system=rng.choice([1, 4, 8, 32], n),
            elevation_deg=rng.uniform(5, 90, n), cn0_dbhz=cn0))
    t_imu = T0 + np.arange(120) * 10_000_000
    imu = ImuSeries(stamp_ns=t_imu, accel_mps2=rng.normal(0, 1, (120, 3)),
                    gyro_rps=rng.normal(0, 0.1, (120, 3)))
    t_odo = T0 + np.arange(12) * 100_000_000
    odo = OdometrySeries(stamp_ns=t_odo, speed_mps=rng.uniform(0, 14, 12),
                         yaw_rate_rps=rng.normal(0, 0.2, 12), speed_var=rng.uniform(0, 1, 12),
                         yaw_rate_var=rng.uniform(0, 0.01, 12))
    t_truth = T0 + np.arange(60) * 20_000_000
    enu = np.column_stack([np.linspace(0, 30, 60), np.linspace(0, -20, 60), np.full(60, 1.8)])
    truth = Trajectory(stamp_ns=t_truth, ecef_m=frame.enu_to_ecef(enu),
                       yaw_rad=np.linspace(-3.14, 3.14, 60) if yaw else None)
    cam = FakeCamera(T0 + np.arange(12) * 100_000_000) if camera else None
    return Drive(name=name, origin_llh=ORIGIN if origin else None, gnss=gnss, odometry=odo,
                 imu=imu, truth=truth, camera=cam,
                 info={'seed': 7, 'array': np.arange(100), 'nested': {'x': np.float64(1.5)}})


def assert_same_drive(src: Drive, back: Drive):
    """Every value of ``back`` equals ``src`` (float32 point fields at float32)."""
    assert back.name == src.name
    assert back.origin_llh == (None if src.origin_llh is None else tuple(src.origin_llh))
    assert len(back.gnss) == len(src.gnss)
    for a, b in zip(src.gnss, back.gnss):
        assert b.stamp_ns == a.stamp_ns
        np.testing.assert_array_equal(b.sv_pos_ecef_m, a.sv_pos_ecef_m)
        np.testing.assert_array_equal(b.pr_m, a.pr_m)
        for f in ('var_m2', 'cn0_dbhz', 'elevation_deg'):
            np.testing.assert_array_equal(getattr(b, f), getattr(a, f).astype(np.float32))
        np.testing.assert_array_equal(b.sv_id, a.sv_id)
        np.testing.assert_array_equal(b.system, a.system)
    for part, names in (('imu', ('stamp_ns', 'accel_mps2', 'gyro_rps')),
                        ('odometry', ('stamp_ns', 'speed_mps', 'yaw_rate_rps', 'speed_var',
                                      'yaw_rate_var'))):
        a, b = getattr(src, part), getattr(back, part)
        assert (a is None) == (b is None), part
        for f in names if a is not None else ():
            np.testing.assert_array_equal(getattr(b, f), getattr(a, f))
    np.testing.assert_array_equal(back.truth.stamp_ns, src.truth.stamp_ns)
    np.testing.assert_array_equal(back.truth.ecef_m, src.truth.ecef_m)
    if src.truth.yaw_rad is None:
        assert back.truth.yaw_rad is None
    else:
        dyaw = np.angle(np.exp(1j * (back.truth.yaw_rad - src.truth.yaw_rad)))
        assert np.abs(dyaw).max() < 1e-12


# ---------------------------------------------------------------------- round trips
@pytest.mark.slow
@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_round_trip_every_message(tmp_path, storage):
    src = synthetic_drive()
    out = tmp_path / 'bag'
    seen = []
    summary = convert_drive(src, out, storage=storage, progress=lambda *a: seen.append(a))
    assert seen[-1][0] == seen[-1][1] == summary.messages
    suffix = '.mcap' if storage == 'mcap' else '.db3'
    assert sorted(p.name for p in out.iterdir()) == ['bag' + suffix, 'metadata.yaml']
    assert [p.name for p in tmp_path.iterdir()] == ['bag']      # no temporary leftovers
    counts = {t: c.count for t, c in summary.topics.items()}
    assert counts == {'/dataset/info': 1, '/map/origin': 1, '/gnss/pseudoranges': 6,
                      '/camera/image_raw': 12, '/imu/data': 120, '/odom/twist': 12,
                      '/ground_truth/pose': 60}
    assert bag_topics(out) == {t: (c.msgtype, c.count) for t, c in summary.topics.items()}
    assert summary.start_ns == T0 and summary.duration_s == pytest.approx(1.19)

    back = read_drive(out)
    assert_same_drive(src, back)
    assert back.info['seed'] == 7 and back.info['nested'] == {'x': 1.5}
    assert 'array' not in back.info            # large arrays stay out of dataset/info
    frames = list(back.camera.frames())
    assert [k for k, _, _ in frames] == list(range(12))
    for k, stamp, img in frames:
        assert stamp == src.camera.stamp_ns[k]
        np.testing.assert_array_equal(img, src.camera.frame(k))
    np.testing.assert_array_equal(back.camera.image(7), src.camera.frame(7))
    # Frames are rendered while writing, a few at a time (here: in the calling thread).
    assert src.camera.max_alive <= 3


@pytest.mark.ros
def test_bag_messages_are_the_bytes_the_nodes_publish():
    """The converter builds with the nodes' writers: each rosbags message serialises to what
    the same writer's rclpy message serialises to."""
    from rclpy.serialization import serialize_message

    import msg_adapters as ma
    kit, store = schema.rosbags_kit(), schema.typestore()
    src = synthetic_drive()
    ep, imu, odo = src.gnss[2], src.imu, src.odometry
    ep.sv_pos_ecef_m[0, 1] = np.nan                    # is_dense false, NaN carried
    cases = [
        lambda k: ma.gnss_epoch_to_pointcloud2(ep, kit=k),
        lambda k: ma.array_to_image(src.camera.frame(1), T0, kit=k),
        lambda k: ma.array_to_image(src.camera.frame(3), T0, kit=k),     # mono8
        lambda k: ma.sample_to_imu(ma.ImuSample(T0, imu.accel_mps2[4], imu.gyro_rps[4]),
                                   'base_link', k),
        lambda k: ma.sample_to_twist(ma.TwistSample(T0, *(float(getattr(odo, f)[3]) for f in (
            'speed_mps', 'yaw_rate_rps', 'speed_var', 'yaw_rate_var'))), kit=k),
        lambda k: ma.fix_to_navsatfix(ma.GeodeticFix(T0, *ORIGIN, service=5,
                                                     frame_id='map'), k),
        lambda k: ma.fix_to_navsatfix(ma.GeodeticFix(T0, *ORIGIN, np.diag([1., 2., 3.])), k),
        lambda k: ma.pose_stamped(T0, src.truth.ecef_m[0], (0.1, 0.2, 0.3, 0.9), 'earth', k),
    ]
    for make in cases:
        ours = make(kit)
        # Through rosbags once more: Fast CDR leaves alignment padding uninitialised.
        theirs = store.deserialize_cdr(serialize_message(make(ma.RCLPY)), ours.__msgtype__)
        assert (store.serialize_cdr(ours, ours.__msgtype__).tobytes()
                == store.serialize_cdr(theirs, ours.__msgtype__).tobytes()), ours.__msgtype__


def test_round_trip_without_origin_or_heading(tmp_path):
    src = synthetic_drive(camera=False, origin=False, yaw=False)
    convert_drive(src, tmp_path / 'bag')
    assert schema.qualified(schema.ORIGIN) not in bag_topics(tmp_path / 'bag')
    back = read_drive(tmp_path / 'bag')
    assert_same_drive(src, back)
    assert back.camera is None


def test_threaded_rendering_keeps_order_and_bounds_memory(tmp_path):
    stream = FakeStream(T0 + np.arange(40) * 100_000_000)
    drive = dataclasses.replace(synthetic_drive(camera=False), camera=stream)
    summary = convert_drive(drive, tmp_path / 'bag', workers=3)
    assert summary.topics['/camera/image_raw'].count == 40
    back = read_drive(tmp_path / 'bag')
    for k, _, img in back.camera.frames():
        np.testing.assert_array_equal(img, FakeStream(stream.stamp_ns).image(k))
    # Rendered once each, by per-thread copies (a renderer is not shared between threads).
    assert sorted(i for _, i in stream.log) == list(range(40))
    copies = {who for who, _ in stream.log}
    assert id(stream) not in copies and 1 <= len(copies) <= 3
    # At most 2 x workers frames in flight, plus the one being written.
    assert stream.max_alive[0] <= 2 * 3 + 2


def test_namespace_and_bag_order(tmp_path):
    convert_drive(synthetic_drive(camera=False), tmp_path / 'bag', namespace='/car1')
    topics = bag_topics(tmp_path / 'bag')
    assert '/car1/imu/data' in topics and '/imu/data' not in topics
    with pytest.raises(BagContentError, match='gnss/pseudoranges'):
        read_drive(tmp_path / 'bag')                   # looked for under /
    assert len(read_drive(tmp_path / 'bag', namespace='car1').gnss) == 6


def test_independent_decoder_mcap_ros2(tmp_path):
    """The bag decodes with the mcap + mcap-ros2-support packages (not rosbags)."""
    # pip-only test dependencies (no rosdep key): skipped where they are not installed.
    make_reader = pytest.importorskip('mcap.reader').make_reader
    DecoderFactory = pytest.importorskip('mcap_ros2.decoder').DecoderFactory

    src = synthetic_drive()
    convert_drive(src, tmp_path / 'bag')
    by_topic: dict = {}
    last_log = 0
    with open(tmp_path / 'bag' / 'bag.mcap', 'rb') as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for sch, channel, message, msg in reader.iter_decoded_messages():
            assert sch.encoding == 'ros2msg' and channel.message_encoding == 'cdr'
            assert message.log_time >= last_log                   # time ordered
            last_log = message.log_time
            if hasattr(msg, 'header'):
                stamp = msg.header.stamp.sec * 10 ** 9 + msg.header.stamp.nanosec
                assert stamp == message.log_time                  # true stamps as bag time
            by_topic.setdefault(channel.topic, []).append(msg)
    info = json.loads(by_topic['/dataset/info'][0].data)
    assert info['name'] == 'synthetic' and info['origin_llh'] == list(ORIGIN)
    origin = by_topic['/map/origin'][0]
    assert (origin.latitude, origin.longitude, origin.altitude) == ORIGIN
    assert origin.header.frame_id == 'map'
    for ep, msg in zip(src.gnss, by_topic['/gnss/pseudoranges'], strict=True):
        assert msg.header.frame_id == 'earth' and msg.point_step == 48 and msg.is_dense
        assert [(f.name, f.offset, f.datatype) for f in msg.fields] == [
            ('x', 0, 8), ('y', 8, 8), ('z', 16, 8), ('pseudorange', 24, 8),
            ('variance', 32, 7), ('cn0', 36, 7), ('elevation', 40, 7), ('sv_id', 44, 4),
            ('system', 46, 2)]
        pts = np.frombuffer(bytes(msg.data), dtype=GNSS_DTYPE)
        np.testing.assert_array_equal(np.column_stack([pts['x'], pts['y'], pts['z']]),
                                      ep.sv_pos_ecef_m)
        np.testing.assert_array_equal(pts['pseudorange'], ep.pr_m)
        np.testing.assert_array_equal(pts['cn0'], ep.cn0_dbhz.astype(np.float32))
        np.testing.assert_array_equal(pts['sv_id'], ep.sv_id)
        np.testing.assert_array_equal(pts['system'], ep.system)
    for k, msg in enumerate(by_topic['/camera/image_raw']):
        img = src.camera.frame(k)
        assert msg.encoding == ('mono8' if img.ndim == 2 else 'bgr8')
        channels = 1 if img.ndim == 2 else 3
        assert (msg.height, msg.width, msg.step) == (*img.shape[:2], img.shape[1] * channels)
        assert bytes(msg.data) == img.tobytes()
    for k, msg in enumerate(by_topic['/imu/data']):
        a, g = msg.linear_acceleration, msg.angular_velocity
        assert [a.x, a.y, a.z, g.x, g.y, g.z] == [*src.imu.accel_mps2[k], *src.imu.gyro_rps[k]]
        assert msg.orientation_covariance[0] == -1.0 and msg.header.frame_id == 'base_link'
    for k, msg in enumerate(by_topic['/odom/twist']):
        t, cov = msg.twist.twist, msg.twist.covariance
        assert (t.linear.x, t.angular.z, cov[0], cov[35]) == (
            src.odometry.speed_mps[k], src.odometry.yaw_rate_rps[k],
            src.odometry.speed_var[k], src.odometry.yaw_rate_var[k])
    for k, msg in enumerate(by_topic['/ground_truth/pose']):
        p = msg.pose.position
        assert [p.x, p.y, p.z] == list(src.truth.ecef_m[k])
        assert msg.header.frame_id == 'earth'
    assert len(by_topic['/ground_truth/pose']) == 60


@pytest.mark.slow
def test_emulated_drive_with_rendered_camera(tmp_path):
    from gnsscam_ros.datasets.emulated.camera import with_camera
    from gnsscam_ros.datasets.emulated.drive import make_emulated_drive
    src = with_camera(make_emulated_drive(3, faults=2, duration_s=1.0))
    summary = convert_drive(src, tmp_path / 'emu', workers=2)
    assert summary.topics['/camera/image_raw'].count == len(src.camera) == 11
    back = read_drive(tmp_path / 'emu')
    assert_same_drive(src, back)
    assert back.info['seed'] == 3 and back.info['camera']['n_frames'] == 11
    for k, stamp, img in back.camera.frames():
        assert img.shape == (480, 640, 3)
        np.testing.assert_array_equal(img, src.camera.image(k))


@pytest.mark.slow
def test_cli_smartloc_excerpt_round_trip(tmp_path, capsys, smartloc_excerpt):
    out = tmp_path / 'smartloc'
    assert convert_main(['smartloc', str(SMARTLOC_EXCERPT), '--out', str(out), '--quiet',
                         '--storage', 'sqlite3']) == 0
    text = capsys.readouterr().out
    assert '/gnss/pseudoranges' in text and 'MB/s' in text
    back = read_drive(out)
    assert_same_drive(smartloc_excerpt, back)
    assert back.origin_llh is None and back.imu is None
    # An existing bag is refused before any work, and stays as it was.
    before = sorted((p.name, p.stat().st_size) for p in out.iterdir())
    assert convert_main(['smartloc', str(SMARTLOC_EXCERPT), '--out', str(out)]) == 4
    assert 'exists' in capsys.readouterr().err
    assert sorted((p.name, p.stat().st_size) for p in out.iterdir()) == before
    assert convert_main(['smartloc', str(tmp_path / 'nowhere'), '--out',
                         str(tmp_path / 'x'), '--quiet']) == 3
    assert not (tmp_path / 'x').exists()


# ---------------------------------------------------------------------- output safety
@pytest.mark.parametrize('kind', ['dir', 'file', 'empty_dir', 'dangling_link'])
def test_existing_output_is_never_overwritten(tmp_path, kind):
    out = tmp_path / 'bag'
    if kind == 'dir':
        out.mkdir()
        (out / 'keep.txt').write_text('precious')
    elif kind == 'file':
        out.write_text('precious')
    elif kind == 'empty_dir':
        out.mkdir()
    else:
        out.symlink_to(tmp_path / 'missing')
    with pytest.raises(BagExistsError, match=str(out)):
        convert_drive(synthetic_drive(camera=False), out)
    if kind == 'dir':
        assert [p.name for p in out.iterdir()] == ['keep.txt']
        assert (out / 'keep.txt').read_text() == 'precious'
    elif kind == 'file':
        assert out.read_text() == 'precious'
    assert len(list(tmp_path.iterdir())) == 1


@pytest.mark.parametrize('threaded', [False, True])
def test_ctrl_c_leaves_no_partial_bag(tmp_path, threaded):
    drive = synthetic_drive()
    if threaded:
        drive = dataclasses.replace(drive, camera=FakeStream(T0 + np.arange(30) * 10 ** 8))

    def progress(done, total, nbytes):
        if done >= 40:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        convert_drive(drive, tmp_path / 'bag', progress=progress, workers=2)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_cli_interrupted_process_leaves_no_partial_bag(tmp_path, sig):
    """A real Ctrl-C (or kill) of gnsscam_convert mid-way: exit 130, nothing left."""
    out = tmp_path / 'bags' / 'emu'
    proc = subprocess.Popen(
        # Invoked the way the gnsscam_convert console script does.
        [sys.executable, '-c', 'import sys; from gnsscam_ros.bags.convert_cli import main; '
         # 240 s of drive (~20 s to convert): long enough that the signal always lands
         # mid-way, even when this process is slow to see the first file (60 s once
         # finished first on a loaded machine).
         'sys.exit(main())', 'emulated', '--seed', '1', '--duration-s', '240', '--out',
         str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        # A suite started in the background of a non-interactive shell inherits SIGINT
        # ignored, and Python then installs no KeyboardInterrupt handler: give the child
        # the default disposition, as a terminal would.
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 60
    # Wait until frames are being written into the temporary sibling folder.
    while not any((out.parent).glob('.emu.partial-*/emu/*.mcap')):
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.05)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert 'interrupted; no bag written' in err
    assert list(out.parent.iterdir()) == []


@pytest.mark.parametrize('threaded', [False, True])
def test_failure_mid_way_leaves_no_partial_bag(tmp_path, threaded):
    stamps = T0 + np.arange(12) * 100_000_000
    cam = FakeStream(stamps, fail_at=5) if threaded else FakeCamera(stamps, fail_at=5)
    drive = dataclasses.replace(synthetic_drive(camera=False), camera=cam)
    with pytest.raises(BagError, match='render failed at frame 5'):
        convert_drive(drive, tmp_path / 'bag', workers=2)
    assert list(tmp_path.iterdir()) == []


def test_data_a_bag_cannot_hold_is_refused_before_writing(tmp_path):
    drive = synthetic_drive(camera=False)
    stamps = drive.imu.stamp_ns.copy()
    stamps[50] = stamps[10]
    drive = dataclasses.replace(drive, imu=dataclasses.replace(drive.imu, stamp_ns=stamps))
    with pytest.raises(BagContentError, match='imu/data: stamp'):
        convert_drive(drive, tmp_path / 'bag')
    drive = synthetic_drive(camera=False)
    drive.gnss[0] = dataclasses.replace(drive.gnss[0], sv_id=np.full(4, 70000))
    with pytest.raises(BagContentError, match='epoch 0: sv_id does not fit UINT16'):
        convert_drive(drive, tmp_path / 'bag')
    with pytest.raises(ValueError, match='unknown storage'):
        convert_drive(drive, tmp_path / 'bag', storage='rosbag1')
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------- bad bags
@pytest.fixture(scope='module')
def good_bag(tmp_path_factory):
    path = tmp_path_factory.mktemp('good') / 'bag'
    convert_drive(synthetic_drive(camera=False), path)
    return path


def _copy(good_bag, tmp_path):
    dst = tmp_path / 'bag'
    shutil.copytree(good_bag, dst)
    return dst, dst / 'bag.mcap'


def test_missing_and_not_a_bag(tmp_path):
    with pytest.raises(BagReadError, match=f'{tmp_path / "nope"}: no such bag'):
        read_drive(tmp_path / 'nope')
    (tmp_path / 'empty').mkdir()
    with pytest.raises(BagReadError, match=str(tmp_path / 'empty')):
        read_drive(tmp_path / 'empty')
    (tmp_path / 'x.txt').write_text('hello')
    with pytest.raises(BagReadError, match='x.txt'):
        read_results(tmp_path / 'x.txt')


@pytest.mark.parametrize('fraction', [0.1, 0.5, 0.999])
def test_truncated_bag(good_bag, tmp_path, fraction):
    bag, mcap = _copy(good_bag, tmp_path)
    os.truncate(mcap, int(mcap.stat().st_size * fraction))
    with pytest.raises(BagReadError, match=f'{bag}: .*(corrupt or truncated)'):
        read_drive(bag)
    with pytest.raises(BagReadError, match='truncated'):
        read_drive(mcap)                                   # the bare storage file too


def test_storage_is_chosen_by_the_metadata_not_the_suffix(good_bag, tmp_path):
    """An MCAP file named ``.db3`` in a folder whose metadata says ``mcap`` is a valid bag
    (rosbag2 picks the plugin from ``storage_identifier``): the same messages as before;
    the bare file, without metadata, is opened by its suffix and refused by name."""
    bag, mcap = _copy(good_bag, tmp_path)
    renamed = mcap.rename(mcap.with_suffix('.db3'))
    meta = bag / 'metadata.yaml'
    meta.write_text(meta.read_text().replace(mcap.name, renamed.name))
    assert 'storage_identifier: mcap' in meta.read_text()
    assert bag_topics(bag) == bag_topics(good_bag)
    assert_same_drive(read_drive(good_bag), read_drive(bag))
    with pytest.raises(BagReadError, match=str(renamed)):
        bag_topics(renamed)


def test_corrupt_bag(good_bag, tmp_path):
    bag, mcap = _copy(good_bag, tmp_path)
    data = bytearray(mcap.read_bytes())
    data[-200:-100] = b'\xff' * 100                         # summary section
    mcap.write_bytes(bytes(data))
    with pytest.raises(BagReadError, match=str(bag)):
        read_drive(bag)
    bag2 = tmp_path / 'bag2'
    shutil.copytree(good_bag, bag2)
    data = bytearray((bag2 / 'bag.mcap').read_bytes())
    at = data.index(b'earth\x00')       # frame_id of the first GNSS cloud
    data[at - 4:at] = b'\xff\xff\xff\x7f'                   # absurd string length
    (bag2 / 'bag.mcap').write_bytes(bytes(data))
    with pytest.raises(BagReadError, match='/gnss/pseudoranges: message at .* does not '
                                           'decode'):
        read_drive(bag2)
    (bag2 / 'metadata.yaml').write_text('rosbag2_bagfile_information: [')
    with pytest.raises(BagReadError, match='metadata'):
        read_drive(bag2)


def _bag_with(path: Path, topic: str, msgtype: str, msgdef=None, payload=b''):
    """A bag with a valid GNSS epoch on /gnss/pseudoranges plus one extra connection."""
    store = schema.typestore()
    good = tmp_good = path.parent / (path.name + '_src')
    convert_drive(synthetic_drive(camera=False), tmp_good)
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        from rosbags.rosbag2 import Reader
        with Reader(good) as reader:
            conns = {}
            for c in reader.connections:
                if c.topic != topic:
                    conns[c.id] = writer.add_connection(c.topic, c.msgtype, typestore=store)
            for c, t, raw in reader.messages():
                if c.id in conns:
                    writer.write(conns[c.id], t, raw)
        if msgdef is None:
            extra = writer.add_connection(topic, msgtype, typestore=store)
        else:
            extra = writer.add_connection(topic, msgtype, msgdef=msgdef,
                                          rihs01='RIHS01_' + '0' * 64)
        writer.write(extra, T0, payload)
    shutil.rmtree(good)


@pytest.mark.slow
def test_unknown_message_type(tmp_path):
    payload = b'\x00\x01\x00\x00' + np.float64(1.0).tobytes()
    _bag_with(tmp_path / 'bag', '/gnss/pseudoranges', 'my_msgs/msg/Mystery',
              msgdef='float64 x\n', payload=payload)
    with pytest.raises(BagTypeError, match='/gnss/pseudoranges has unknown message type '
                                           'my_msgs/msg/Mystery'):
        read_drive(tmp_path / 'bag')
    # A topic that is not read may carry any type: recorded bags often hold extras.
    _bag_with(tmp_path / 'bag2', '/extra/stuff', 'my_msgs/msg/Mystery',
              msgdef='float64 x\n', payload=payload)
    assert len(read_drive(tmp_path / 'bag2').gnss) == 6


def test_topic_with_the_wrong_type(tmp_path):
    store = schema.typestore()
    text = store.serialize_cdr(store.types['std_msgs/msg/String'](data='x'),
                               'std_msgs/msg/String')
    _bag_with(tmp_path / 'bag', '/imu/data', 'std_msgs/msg/String', payload=bytes(text))
    with pytest.raises(BagTypeError, match='/imu/data has type std_msgs/msg/String, '
                                           'expected sensor_msgs/msg/Imu') as info:
        read_drive(tmp_path / 'bag')
    assert info.value.topic == '/imu/data' and info.value.path == tmp_path / 'bag'
    _bag_with(tmp_path / 'res', '/integrity_risk', 'std_msgs/msg/String', payload=bytes(text))
    with pytest.raises(BagTypeError, match='/integrity_risk has type std_msgs/msg/String'):
        read_results(tmp_path / 'res')


def test_wrong_frame_is_named(tmp_path):
    store = schema.typestore()
    T = store.types
    stamp = T['builtin_interfaces/msg/Time'](sec=1, nanosec=0)
    msg = T['geometry_msgs/msg/PoseStamped'](
        header=T['std_msgs/msg/Header'](stamp=stamp, frame_id='map'),
        pose=T['geometry_msgs/msg/Pose'](
            position=T['geometry_msgs/msg/Point'](x=1.0, y=2.0, z=3.0),
            orientation=T['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0)))
    raw = bytes(store.serialize_cdr(msg, 'geometry_msgs/msg/PoseStamped'))
    _bag_with(tmp_path / 'bag', '/ground_truth/pose', 'geometry_msgs/msg/PoseStamped',
              payload=raw)
    with pytest.raises(BagContentError, match="ground_truth/pose: frame 'map', expected "
                                              "'earth'"):
        read_drive(tmp_path / 'bag')


# ---------------------------------------------------------------------- result bags
def _result_bag(path: Path, epochs, with_particles=True, with_fix=True, with_truth=None,
                origin=ORIGIN):
    """Write the fusion node's outputs, built and serialised by rclpy/msg_adapters."""
    from rclpy.serialization import serialize_message

    from gnsscam_ros.core.verdict import ERROR, OK, STALE, IntegrityVerdict
    from msg_adapters import (GeodeticFix, PoseEstimate, fix_to_navsatfix,
                              integrity_risk_to_msg, particles_to_posearray, pose_covariance,
                              pose_to_msg)
    frame = LocalFrame(*origin)
    store = schema.typestore()
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = {t: w.add_connection('/' + t, ty, typestore=store) for t, ty in (
            ('integrity_risk', schema.DIAGNOSTIC_ARRAY), ('pose', schema.POSE_COV_STAMPED),
            ('fix', schema.NAVSATFIX), ('particles', schema.POSE_ARRAY))}
        if with_truth is not None:
            c['truth'] = w.add_connection('/ground_truth/pose', schema.POSE_STAMPED,
                                          typestore=store)
            c['origin'] = w.add_connection('/map/origin', schema.NAVSATFIX, typestore=store)
            convert_store = store
            T = convert_store.types
            lat, lon, alt = origin
            o = T[schema.NAVSATFIX](
                header=T['std_msgs/msg/Header'](stamp=T['builtin_interfaces/msg/Time'](
                    sec=T0 // 10 ** 9, nanosec=0), frame_id='map'),
                status=T['sensor_msgs/msg/NavSatStatus'](status=0, service=1),
                latitude=lat, longitude=lon, altitude=alt, position_covariance=np.zeros(9),
                position_covariance_type=0)
            w.write(c['origin'], T0, store.serialize_cdr(o, schema.NAVSATFIX))
            for s, ecef in zip(with_truth.stamp_ns, with_truth.ecef_m):
                msg = T[schema.POSE_STAMPED](
                    header=T['std_msgs/msg/Header'](stamp=T['builtin_interfaces/msg/Time'](
                        sec=int(s) // 10 ** 9, nanosec=int(s) % 10 ** 9), frame_id='earth'),
                    pose=T['geometry_msgs/msg/Pose'](
                        position=T['geometry_msgs/msg/Point'](x=ecef[0], y=ecef[1],
                                                              z=ecef[2]),
                        orientation=T['geometry_msgs/msg/Quaternion'](x=0., y=0., z=0.,
                                                                      w=0.)))
                w.write(c['truth'], int(s), store.serialize_cdr(msg, schema.POSE_STAMPED))

        def put(topic, stamp, msg):
            w.write(c[topic], stamp, serialize_message(msg))

        for ep in epochs:
            s = ep['stamp_ns']
            if ep.get('stale'):
                put('integrity_risk', s, integrity_risk_to_msg(IntegrityVerdict(
                    stamp_ns=s, level=STALE, message='stale', alert_limit_m=8.0,
                    target_risk=0.1, epoch_stamp_ns=s)))
                continue
            ok = ep.get('ok', ep['bound8'] <= 0.1)
            details = {'inverse_bernoulli': 'exact'}
            if 'valid' in ep:
                details['integrity_valid'] = ep['valid']
            # An OK verdict is backed by a protection level within the alert limit.
            put('integrity_risk', s, integrity_risk_to_msg(IntegrityVerdict(
                stamp_ns=s, level=OK if ok else ERROR, message='', risk_bound=ep['bound8'],
                empirical_risk=ep['bound8'] / 2, divergence_risk=ep['bound8'] / 2,
                alert_limit_m=8.0, target_risk=0.1, epoch_stamp_ns=s, details=details,
                protection_level_m=ep.get('pl', 6.0 if ok else 12.0),
                epoch_status='updated', risk_bounds_by_limit={16.0: ep['bound16']})))
            put('pose', s, pose_to_msg(PoseEstimate(
                stamp_ns=s, position_m=ep['enu'], yaw_rad=0.3,
                covariance=pose_covariance(np.diag([4.0, 4.0, 9.0]), 0.01))))
            if with_fix:
                lat, lon, alt = frame.enu_to_geodetic(ep['enu'])
                put('fix', s, fix_to_navsatfix(GeodeticFix(
                    stamp_ns=s, lat_deg=float(lat), lon_deg=float(lon), alt_m=float(alt),
                    covariance_enu_m2=np.diag([4.0, 4.0, 9.0]))))
            if with_particles:
                cloud = np.column_stack([ep['enu'] + ep['spread'], np.zeros(len(ep['spread']))])
                put('particles', s, particles_to_posearray(cloud, s))


def _epochs(frame_truth_enu):
    rng = np.random.default_rng(3)
    out = []
    for k, true in enumerate(frame_truth_enu):
        err = np.array([12.0, 0.0, 1.0]) if k % 3 == 0 else np.array([1.0, -1.0, 0.5])
        out.append({'stamp_ns': T0 + k * 10 ** 9, 'enu': true + err,
                    'bound8': 0.05 if k % 2 else 0.4, 'bound16': 0.01,
                    'spread': rng.normal(0, 1.0, (200, 3))})
    out.append({'stamp_ns': T0 + len(out) * 10 ** 9, 'stale': True})
    return out


@pytest.mark.ros
def test_read_results_written_by_rclpy(tmp_path):
    frame = LocalFrame(*ORIGIN)
    truth_enu = np.column_stack([np.arange(9.0) * 10, np.zeros(9), np.full(9, 1.8)])
    epochs = _epochs(truth_enu)
    _result_bag(tmp_path / 'res', epochs)
    res = read_results(tmp_path / 'res')
    assert len(res.integrity) == 10 and res.integrity[-1].stale
    first = res.integrity[0]
    assert (first.level, first.risk_bound, first.alert_limit_m, first.target_risk) == (
        2, 0.4, 8.0, 0.1)
    assert first.epoch_stamp_ns == T0 and first.risk_bounds_by_limit == {16.0: 0.01}
    assert first.epoch_status == 'updated' and first.extra == {'inverse_bernoulli': 'exact'}
    assert res.integrity[-1].epoch_status is None
    np.testing.assert_array_equal(res.pose_enu_m, [e['enu'] for e in epochs[:-1]])
    assert res.pose_frame_id == 'map' and res.pose_cov[0, 2, 2] == 9.0
    back = frame.geodetic_to_enu(res.fix_llh[:, 0], res.fix_llh[:, 1], res.fix_llh[:, 2])
    np.testing.assert_allclose(back, res.pose_enu_m, atol=1e-6)
    assert len(res.particles) == 9 and res.particles[T0].shape == (200, 4)
    assert res.truth is None and res.origin_llh is None


@pytest.mark.ros
def test_evaluate_result_bag_matches_the_metric_functions(tmp_path):
    from gnsscam_ros.core.integrity import hazard_mass
    from gnsscam_ros.evaluation.bag_eval import evaluate_result_bag
    from gnsscam_ros.evaluation.metrics import integrity_metrics
    from gnsscam_ros.evaluation.runner import accuracy

    frame = LocalFrame(*ORIGIN)
    truth_enu = np.column_stack([np.arange(9.0) * 10, np.zeros(9), np.full(9, 1.8)])
    truth = Trajectory(stamp_ns=T0 + np.arange(9) * 10 ** 9,
                       ecef_m=frame.enu_to_ecef(truth_enu))
    epochs = _epochs(truth_enu)
    _result_bag(tmp_path / 'res', epochs, with_truth=truth)
    out = evaluate_result_bag(tmp_path / 'res')

    est = np.array([e['enu'] for e in epochs[:-1]])
    expect = accuracy(est, truth_enu)
    for key in ('rmse_2d_m', 'rmse_3d_m', 'epochs', 'p95_2d_m'):
        assert out[key] == pytest.approx(expect[key], abs=1e-6)
    err = np.hypot(*(est - truth_enu)[:, :2].T)
    ref = np.array([hazard_mass((e['enu'] + e['spread'])[None], np.full((1, 200),
                                                                        -np.log(200)),
                                t, [8.0, 16.0]) for e, t in zip(epochs, truth_enu)])
    for a, (limit, key) in enumerate(((8.0, 'bound8'), (16.0, 'bound16'))):
        bound = np.array([e[key] for e in epochs[:-1]])
        want = integrity_metrics(err, bound, ref[:, a], limit, 0.1)
        got = out['integrity'][f'{limit:g}']
        for k, v in want.items():
            assert got[k] == pytest.approx(v, abs=1e-9), (limit, k)
    assert out['integrity']['8']['faults'] == 3
    assert out['integrity_by_inverse_bernoulli'].keys() == {'exact'}
    assert out['statuses'] == {'ERROR': 5, 'OK': 4, 'STALE': 1}
    assert out['bag']['estimate_source'] == 'fix'
    assert out['bag']['reference_risk_source']['particles'] == 9
    assert out['baseline_wls']['rmse_2d_m'] is None

    # Without particles the reference risk comes from the pose covariance; without fix and
    # without a map origin the pose frame is unknown: a clear error.
    _result_bag(tmp_path / 'res2', epochs, with_particles=False, with_truth=truth)
    out2 = evaluate_result_bag(tmp_path / 'res2')
    assert out2['bag']['reference_risk_source']['pose_covariance'] == 9
    assert out2['rmse_2d_m'] == pytest.approx(out['rmse_2d_m'])
    _result_bag(tmp_path / 'res3', epochs, with_fix=False)
    truth_bag = tmp_path / 'truth'
    convert_drive(Drive(name='t', origin_llh=None, gnss=[], odometry=None, imu=None,
                        truth=truth), truth_bag)
    with pytest.raises(BagContentError, match='map origin is unknown'):
        evaluate_result_bag(tmp_path / 'res3', truth_bag=truth_bag)
    out3 = evaluate_result_bag(tmp_path / 'res3', truth_bag=truth_bag, origin_llh=ORIGIN)
    assert out3['bag']['estimate_source'] == 'pose'
    assert out3['rmse_2d_m'] == pytest.approx(out['rmse_2d_m'], abs=1e-6)
    with pytest.raises(BagContentError, match='no ground_truth/pose'):
        evaluate_result_bag(tmp_path / 'res3')


@pytest.mark.ros
@pytest.mark.slow
def test_evaluate_result_bag_agrees_with_offline_run(tmp_path):
    """A run written as the fusion node would publish it scores like the offline runner."""
    from msg_adapters import ERROR, OK

    from gnsscam_ros.core.filter import FilterConfig
    from gnsscam_ros.datasets.emulated.drive import make_emulated_drive
    from gnsscam_ros.evaluation.bag_eval import evaluate_result_bag
    from gnsscam_ros.evaluation.runner import (accuracy, run_filter, run_snapshot_baseline,
                                               summarize, truth_at)

    drive = make_emulated_drive(2, faults=3, duration_s=40)
    config = FilterConfig(n_particles=200, alert_limit_m=8.0, extra_alert_limits_m=(16.0,))
    record = run_filter(drive, config, seed=1)
    offline = summarize(record, config)
    convert_drive(drive, tmp_path / 'dataset')
    epochs = []
    bounds = record.risk_bound[config.inverse_bernoulli]
    for k, s in enumerate(record.stamp_ns):
        # The verdict fusion_node publishes: OK = the filter's flag, and whether the filter
        # was settled with its motion known (for the 16 m limit).
        epochs.append({'stamp_ns': int(s), 'enu': record.estimate_enu_m[k],
                       'bound8': float(bounds[k, 0]), 'bound16': float(bounds[k, 1]),
                       'spread': np.zeros((1, 3)), 'ok': bool(record.integrity_ok[k]),
                       'valid': bool(record.integrity_valid[k]),
                       'pl': float(record.protection_level_m[k])})
    assert OK == 0 and ERROR == 2
    _result_bag(tmp_path / 'res', epochs, with_particles=False, origin=drive.origin_llh)
    out = evaluate_result_bag(tmp_path / 'res', truth_bag=tmp_path / 'dataset')
    for key in ('rmse_2d_m', 'rmse_3d_m', 'epochs'):
        assert out[key] == pytest.approx(offline[key], rel=1e-9, abs=1e-6)
    for limit in ('8', '16'):
        for key in ('p_fa', 'p_mi', 'epochs', 'faults', 'false_alarms',
                    'missed_identifications', 'mean_risk_bound'):
            assert out['integrity'][limit][key] == pytest.approx(
                offline['integrity'][limit][key]), (limit, key)
    frame = LocalFrame(*drive.origin_llh)
    stamps, fixes = run_snapshot_baseline(drive, frame, config.measurement_var_m2)
    baseline = accuracy(fixes, truth_at(drive, frame, stamps))
    assert out['baseline_wls']['epochs'] == baseline['epochs'] > 0
    assert out['baseline_wls']['rmse_2d_m'] == pytest.approx(baseline['rmse_2d_m'], rel=1e-6)
    assert out['rmse_2d_ratio_to_wls'] == pytest.approx(
        out['rmse_2d_m'] / out['baseline_wls']['rmse_2d_m'])
