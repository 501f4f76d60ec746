"""Never crash, never lie: gnsscam_replay and gnsscam_record against corrupt bags, wrong
types, unwritable outputs and killed runs.

Each table entry runs the tool's ``main(argv)`` in-process (on a ROS domain of its own,
without the Fast DDS profile, which would change this process's environment): the
documented exit code, one ``gnsscam_replay:``/``gnsscam_record:`` error line naming the
bag (rcutils may add log lines of its own), no traceback, nothing left behind.
"""
import shutil
import signal
import struct
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from ros_harness import RosGraph, ros_domain_id, ros_env, wait_until
from rosbags.rosbag2 import StoragePlugin, Writer
from sensor_msgs.msg import Imu

from gnsscam_ros.bags import schema
from gnsscam_ros.bags.convert import convert_drive
from gnsscam_ros.bags.read import bag_topics, open_bag
from gnsscam_ros.datasets.emulated.drive import make_emulated_drive
from gnsscam_ros.io import partials
from gnsscam_ros.live.player import BagReplayer
from gnsscam_ros.live.record import BagRecorder
from gnsscam_ros.live.record import main as record_main
from gnsscam_ros.live.replay import main as replay_main
from gnsscam_ros.live.summary import ReplaySummary
from tools.fuzz.corrupt_inputs import (assert_refused, dead_pid, hidden_leftovers,
                                       unwritable_folder)

pytestmark = pytest.mark.ros

T0 = 1_700_000_000 * 10 ** 9
REPLAY = ['--wait', '0', '--rate', '0', '--no-dds-profile']


@pytest.fixture(autouse=True)
def own_domain(monkeypatch):
    """The CLIs init rclpy's default context: keep it off the other tests' domains."""
    monkeypatch.setenv('ROS_DOMAIN_ID', str(ros_domain_id()))
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')


@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    """A 2 s emulated drive as MCAP, as SQLite and converted under the namespace /a."""
    root = tmp_path_factory.mktemp('robust_bags')
    drive = make_emulated_drive(5, duration_s=2.0)
    convert_drive(drive, root / 'mcap')
    convert_drive(drive, root / 'sqlite', storage='sqlite3')
    convert_drive(drive, root / 'ns_a', namespace='/a')
    return root


def replay(argv, capfd):
    code = replay_main([str(a) for a in argv])
    out, err = capfd.readouterr()
    return code, out, err


def write_bag(path: Path, entries, storage=StoragePlugin.MCAP) -> Path:
    """A bag of ``(topic, msgtype, [payload, ...], msgdef or None)``."""
    store = schema.typestore()
    with Writer(path, version=9, storage_plugin=storage) as writer:
        for topic, msgtype, payloads, msgdef in entries:
            if msgdef is None:
                conn = writer.add_connection(topic, msgtype, typestore=store)
            else:
                conn = writer.add_connection(topic, msgtype, msgdef=msgdef,
                                             rihs01='RIHS01_' + '0' * 64)
            for k, data in enumerate(payloads):
                writer.write(conn, T0 + k * 10 ** 8, bytes(data))
    return path


def serialised(msgtype: str, **fields) -> bytes:
    store = schema.typestore()
    return bytes(store.serialize_cdr(store.types[msgtype](**fields), msgtype))


def an_imu_message() -> bytes:
    """One valid sensor_msgs/msg/Imu, serialised."""
    t = schema.typestore().types
    vector = t['geometry_msgs/msg/Vector3']
    return serialised(schema.IMU_TYPE,
                      header=t['std_msgs/msg/Header'](
                          stamp=t['builtin_interfaces/msg/Time'](sec=1_700_000_000, nanosec=0),
                          frame_id='base_link'),
                      orientation=t['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0),
                      orientation_covariance=np.zeros(9), angular_velocity=vector(
                          x=0.0, y=0.0, z=0.0), angular_velocity_covariance=np.zeros(9),
                      linear_acceleration=vector(x=0.0, y=0.0, z=0.0),
                      linear_acceleration_covariance=np.zeros(9))


# ======================================================================= replay
def corrupt_bags(bags: Path, folder: Path) -> dict[str, str]:
    """Write corrupt bags into ``folder``: ``{name: expected message part}``."""
    rng = np.random.default_rng(9)
    out: dict[str, str] = {}
    out['absent'] = 'no such bag'
    (folder / 'empty_dir').mkdir()
    out['empty_dir'] = 'not a readable rosbag2 bag'
    (folder / 'bad_yaml').mkdir()
    (folder / 'bad_yaml' / 'metadata.yaml').write_text('rosbag2_bagfile_information: [')
    out['bad_yaml'] = 'not a readable rosbag2 bag'
    (folder / 'other_yaml').mkdir()
    (folder / 'other_yaml' / 'metadata.yaml').write_text('this: is not rosbag2 metadata\n')
    out['other_yaml'] = 'not a readable rosbag2 bag'
    shutil.copytree(bags / 'mcap', folder / 'no_storage')
    (folder / 'no_storage' / 'mcap.mcap').unlink()
    out['no_storage'] = 'not a readable rosbag2 bag'
    (folder / 'zero.mcap').write_bytes(b'')
    out['zero.mcap'] = 'not a readable rosbag2 bag'
    (folder / 'zero.db3').write_bytes(b'')
    out['zero.db3'] = ''
    for seed in range(10):
        junk = rng.integers(0, 256, 64 + 4000 * seed, dtype=np.uint8).tobytes()
        (folder / f'junk_{seed}.mcap').write_bytes(junk)
        out[f'junk_{seed}.mcap'] = ''
        (folder / f'junk_{seed}.db3').write_bytes(junk)
        out[f'junk_{seed}.db3'] = ''
    good = (bags / 'mcap' / 'mcap.mcap').read_bytes()
    for fraction in (0.01, 0.02, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.97,
                     0.999):
        cut = int(len(good) * fraction)
        name = f'cut_{int(fraction * 1000)}'
        shutil.copytree(bags / 'mcap', folder / name)
        (folder / name / 'mcap.mcap').write_bytes(good[:cut])
        out[name] = ''
        (folder / f'{name}.mcap').write_bytes(good[:cut])
        out[f'{name}.mcap'] = ''
    db3 = (bags / 'sqlite' / 'sqlite.db3').read_bytes()
    for fraction in (0.05, 0.1, 0.3, 0.5, 0.9):
        name = f'sqlite_cut_{int(fraction * 100)}'
        shutil.copytree(bags / 'sqlite', folder / name)
        (folder / name / 'sqlite.db3').write_bytes(db3[:int(len(db3) * fraction)])
        out[name] = ''
    flipped = bytearray(good)
    flipped[-300:-100] = b'\xff' * 200                 # the summary section
    (folder / 'flipped_summary.mcap').write_bytes(bytes(flipped))
    out['flipped_summary.mcap'] = ''
    # Types: every topic of the graph with a type the nodes do not use.
    string = serialised(schema.STRING, data='x')
    imu = an_imu_message()
    for topic, wanted in schema.TOPIC_TYPES.items():
        wrong, payload = ((schema.IMU_TYPE, imu) if wanted == schema.STRING
                          else (schema.STRING, string))
        name = 'type_' + topic.replace('/', '_')
        write_bag(folder / name, [('/' + topic, wrong, [payload] * 3, None)])
        out[name] = f'topic /{topic} has type {wrong}, expected {wanted}'
    write_bag(folder / 'type_in_namespace', [('/a/gnss/pseudoranges', schema.STRING,
                                             [string], None)])
    out['type_in_namespace'] = 'topic /a/gnss/pseudoranges has type std_msgs/msg/String'
    write_bag(folder / 'unknown_type', [('/imu/data', 'my_msgs/msg/Mystery',
                                        [b'\x00\x01\x00\x00' + bytes(8)], 'float64 x\n')])
    out['unknown_type'] = 'unknown to the typestore: my_msgs/msg/Mystery'
    write_bag(folder / 'two_types', [('/extra', schema.STRING, [string], None),
                                     ('/extra', schema.IMU_TYPE, [imu], None)])
    out['two_types'] = 'has two types'
    write_bag(folder / 'no_topics', [])
    out['no_topics'] = 'no messages to play (no topics)'
    write_bag(folder / 'no_messages', [('/imu/data', schema.IMU_TYPE, [], None)])
    out['no_messages'] = 'no messages to play on /imu/data'
    return out


@pytest.mark.slow
def test_replay_refuses_corrupt_bags_and_wrong_types(bags, tmp_path, capfd):
    cases = corrupt_bags(bags, tmp_path)
    for name, why in cases.items():
        path = tmp_path / name
        code, out, err = replay([path] + REPLAY, capfd)
        line = assert_refused(code, err, 3, 'gnsscam_replay', path, strict=False)
        assert why in line, (name, line)
        assert out == '', (name, out)                    # no summary of a replay
    assert len(cases) >= 80
    # --namespace finds the bag's topics under it: the wrong type is refused there too.
    code, _, err = replay([tmp_path / 'type_in_namespace', '--namespace', '/a'] + REPLAY,
                          capfd)
    assert_refused(code, err, 3, 'gnsscam_replay', 'expected sensor_msgs/msg/PointCloud2',
                   strict=False)


def _garbled(msgtype: str, how: str) -> bytes:
    """A message of ``msgtype`` whose CDR does not decode."""
    if how == 'length':       # a string length far beyond the message
        if msgtype == schema.STRING:
            return b'\x00\x01\x00\x00' + struct.pack('<I', 0x7FFFFFFF) + b'x' * 8
        return b'\x00\x01\x00\x00' + struct.pack('<iII', 1_700_000_000, 0, 0x7FFFFFFF) + b'x'
    if how == 'short':        # a valid header stamp, then nothing
        return b'\x00\x01\x00\x00' + struct.pack('<iI', 1_700_000_000, 0)
    return b'\x00\x01'        # not even a CDR header


GARBLED = [(topic, how) for topic in ('gnss/pseudoranges', 'camera/image_raw', 'imu/data',
                                      'odom/twist', 'map/origin', 'dataset/info',
                                      'ground_truth/pose')
           for how in ('length', 'short', 'stub')]


@pytest.mark.slow
@pytest.mark.parametrize('topic,how', [
    pytest.param(t, h, marks=() if (t, h) in {('imu/data', 'length'),
                                              ('dataset/info', 'stub')}
                 else pytest.mark.slow) for t, h in GARBLED])
def test_replay_stops_at_a_message_that_does_not_decode(tmp_path, capfd, topic, how):
    """Publishing bytes the nodes cannot decode (rmw drops them before any callback) and
    exiting 0 would report a clean replay of data that never arrived."""
    msgtype = schema.TOPIC_TYPES[topic]
    bag = write_bag(tmp_path / 'bag', [('/' + topic, msgtype, [_garbled(msgtype, how)], None)])
    code, out, err = replay([bag] + REPLAY, capfd)
    line = assert_refused(code, err, 3, 'gnsscam_replay', bag, f'topic /{topic}',
                          strict=False)
    assert 'does not decode' in line or 'header' in line or 'stamp' in line, line


def test_replay_output_refusals(bags, tmp_path, capfd):
    js = tmp_path / 'summary.json'
    js.write_text('keep\n')
    code, _, err = replay([bags / 'mcap', '--json', js] + REPLAY, capfd)
    assert_refused(code, err, 4, 'gnsscam_replay', js)
    assert js.read_text() == 'keep\n'
    for target in (unwritable_folder(tmp_path) / 's.json', js / 's.json'):
        code, _, err = replay([bags / 'mcap', '--json', target] + REPLAY, capfd)
        assert_refused(code, err, 4, 'gnsscam_replay', target)
    for bad in (['--namespace', '/a b'], ['--rate', '-1'], ['--rate', 'nan'],
                ['--start', 'inf'], ['--ros-args', '-r'], ['--topics', 'no/such']):
        code, _, err = replay([bags / 'mcap'] + REPLAY + bad, capfd)
        assert_refused(code, err, 2, 'gnsscam_replay', strict=False)


def test_namespace_publishes_under_it(bags, tmp_path):
    graph = RosGraph()
    try:
        def topics(bag, **kwargs):
            node = BagReplayer(bag, context=graph.ctx, wait_s=0.0, **kwargs)
            try:
                return sorted(p.topic_name for p in node._bag_pubs.values())
            finally:
                node.destroy_node()
        root = topics(bags / 'mcap', namespace='/a', bag_namespace=None)
        assert root and all(t.startswith('/a/') for t in root), root
        assert '/a/imu/data' in root and '/a/gnss/pseudoranges' in root
        assert topics(bags / 'ns_a', namespace='/a', bag_namespace=None) == root
        # As before without a namespace: the root.
        assert '/imu/data' in topics(bags / 'mcap')
    finally:
        graph.close()


@pytest.mark.slow
def test_replay_cli_namespace_alone_reaches_nodes_in_it(bags, tmp_path):
    graph = RosGraph()
    inside = graph.collect(Imu, '/a/imu/data')
    at_root = graph.collect(Imu, '/imu/data')
    spin = threading.Thread(target=graph.executor.spin, daemon=True)
    spin.start()
    try:
        done = subprocess.run([sys.executable, '-m', 'gnsscam_ros.live.replay',
                               str(bags / 'mcap'), '--namespace', '/a', '--rate', '0',
                               '--wait', '5', '--no-dds-profile'],
                              env=ros_env(tmp_path, graph.domain), capture_output=True,
                              text=True, timeout=120)
        assert done.returncode == 0, done.stderr
        imu_count = bag_topics(bags / 'mcap')['/imu/data'][1]
        wait_until(lambda: len(inside) >= imu_count, 10.0, 'the IMU samples under /a')
        assert len(at_root) == 0
        assert 'Traceback' not in done.stderr
    finally:
        graph.executor.shutdown()
        spin.join(timeout=5)
        graph.close()


class _NeverAcknowledged:
    """A publisher whose reliable subscriber never acknowledges (a stopped or hung
    process: stopping a real one with SIGSTOP left Fast DDS's teardown hanging)."""

    def __init__(self):
        self.waited_s = []

    def wait_for_all_acked(self, timeout):
        self.waited_s.append(timeout.nanoseconds / 1e9)
        return False


def test_replay_names_the_topics_a_reader_never_acknowledged(bags):
    """A replay that ends before a reliable subscriber holds everything says so (its
    last messages may die with it), after waiting at most the acknowledgement timeout."""
    graph = RosGraph()
    node = None
    try:
        node = BagReplayer(bags / 'mcap', rate=0.0, wait_s=0.0, ack_timeout_s=0.5,
                           context=graph.ctx)
        assert node._deliver_all() == []        # nobody subscribes: nothing in flight
        stuck = node._bag_pubs['/imu/data'] = _NeverAcknowledged()
        assert node._deliver_all() == ['/imu/data']
        assert len(stuck.waited_s) == 1 and 0.0 < stuck.waited_s[0] <= 0.5
    finally:
        if node is not None:
            node.destroy_node()
        graph.close()
    summary = ReplaySummary(bag=bags / 'mcap', rate=0.0, undelivered=['/imu/data'])
    assert 'not acknowledged by every subscriber at the end: /imu/data' in summary.text()
    assert summary.as_dict()['undelivered'] == ['/imu/data']
    assert 'not acknowledged' not in ReplaySummary(bag=bags / 'mcap', rate=0.0).text()


# ======================================================================= record
def record(argv, capfd):
    code = record_main([str(a) for a in argv])
    out, err = capfd.readouterr()
    return code, out, err


def test_record_output_refusals(tmp_path, capfd):
    existing = tmp_path / 'existing'
    existing.mkdir()
    a_file = tmp_path / 'a_file'
    a_file.write_text('x')
    code, _, err = record(['--out', existing, '--duration', '0'], capfd)
    assert_refused(code, err, 4, 'gnsscam_record', existing)
    nowhere = unwritable_folder(tmp_path)
    for out in (nowhere / 'rec', a_file / 'rec'):
        code, _, err = record(['--out', out, '--duration', '0'], capfd)
        line = assert_refused(code, err, 4, 'gnsscam_record', out, strict=False)
        assert 'cannot write here' in line
        assert not out.exists()
    for bad in (['--duration', 'nan'], ['--duration', '-1'], ['--ros-args', '-r'],
                ['pose:foo_msgs/msg/Bar']):
        out = tmp_path / 'never'
        code, _, err = record(['--out', out, '--duration', '0'] + bad, capfd)
        assert_refused(code, err, 2, 'gnsscam_record', strict=False)
        assert not out.exists()
    assert not hidden_leftovers(tmp_path)


def test_record_removes_a_stale_partial_and_records(tmp_path, capfd):
    host = partials._host()
    stale = tmp_path / f'.rec.partial-{host}-{dead_pid()}-x1y2'
    (stale / 'bag').mkdir(parents=True)
    (stale / 'bag' / 'bag.mcap').write_bytes(b'\x00' * 4096)
    code, out, err = record(['--out', tmp_path / 'rec', '--duration', '0'], capfd)
    assert code == 0 and 'Traceback' not in err
    assert f'removed the leftover partial output {stale}' in err
    assert not stale.exists() and (tmp_path / 'rec').is_dir()
    with open_bag(tmp_path / 'rec'):
        pass
    assert not hidden_leftovers(tmp_path)


def test_record_write_error_stops_and_leaves_nothing(tmp_path):
    graph = RosGraph()
    try:
        recorder = graph.add(BagRecorder(tmp_path / 'rec',
                                         topics=['imu/data:sensor_msgs/msg/Imu'],
                                         context=graph.ctx))

        def disk_full(*args):
            raise OSError(28, 'No space left on device')
        recorder._writer.write = disk_full
        pub = graph.publisher(Imu, 'imu/data')
        graph.connect(pub)
        pub.publish(Imu())
        graph.spin_until(lambda: recorder.failure is not None, 10.0, 'the write error')
        assert 'No space left on device' in str(recorder.failure)
        assert str(tmp_path / 'rec') in str(recorder.failure)
        recorder.abort()
    finally:
        graph.close()
    assert not (tmp_path / 'rec').exists() and not hidden_leftovers(tmp_path)


@pytest.mark.slow
def test_sigkilled_record_leftover_is_removed_by_the_next_run(tmp_path, capfd):
    out = tmp_path / 'rec'
    proc = subprocess.Popen([sys.executable, '-m', 'gnsscam_ros.live.record', '--out',
                             str(out)], env=ros_env(tmp_path, ros_domain_id()),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        def partial():
            return [p for p in tmp_path.iterdir() if p.name.startswith('.rec.partial-')]
        wait_until(lambda: partial() or proc.poll() is not None, 60.0, 'the partial bag')
        assert proc.poll() is None, proc.communicate()[1]
        left = partial()
        assert f'-{proc.pid}-' in left[0].name            # the writer's pid in its name
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert left[0].exists() and not out.exists()
    code, _, err = record(['--out', out, '--duration', '0'], capfd)
    assert code == 0, err
    assert f'removed the leftover partial output {left[0]}' in err
    assert not left[0].exists() and out.is_dir()
