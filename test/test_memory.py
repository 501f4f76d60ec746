"""Memory after a large message (gnsscam_ros/nodes/memory.py).

* the node processes' Fast DDS profile is put in force unless the user configures Fast DDS
  (or another RMW runs); the replay's profile carries the same history memory settings;
* a camera_node process given back the memory of a refused 50 MB image (Fast DDS's
  default reader history kept it for good: the test fails without the profile).
"""
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from ros_harness import RosGraph, ros_domain_id, ros_env, stop
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import Image

from gnsscam_ros.live.launch import DDS_PROFILE
from gnsscam_ros.nodes import memory

ROOT = Path(__file__).resolve().parents[1]
NS = '{http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles}'


# ============================================================== the environment
@pytest.fixture
def clean_cwd(tmp_path, monkeypatch):
    """A working directory without a DEFAULT_FASTRTPS_PROFILES.xml."""
    monkeypatch.chdir(tmp_path)
    return tmp_path


def test_node_processes_get_the_profile_when_fast_dds_is_not_configured(clean_cwd):
    env = {'ROS_DOMAIN_ID': '7'}
    assert memory.configure_node_memory(env) == str(memory.PROFILE)
    assert env == {'ROS_DOMAIN_ID': '7', 'FASTRTPS_DEFAULT_PROFILES_FILE': str(memory.PROFILE),
                   'RMW_FASTRTPS_USE_QOS_FROM_XML': '1'}
    assert memory.PROFILE.is_file()
    env = {'RMW_IMPLEMENTATION': 'rmw_fastrtps_dynamic_cpp'}
    assert memory.configure_node_memory(env) == str(memory.PROFILE)


@pytest.mark.parametrize('user', [
    {'FASTRTPS_DEFAULT_PROFILES_FILE': '/etc/mine.xml'},
    {'FASTDDS_DEFAULT_PROFILES_FILE': '/etc/mine.xml'},
    {'FASTRTPS_DEFAULT_PROFILES_FILE': '/etc/mine.xml', 'RMW_FASTRTPS_USE_QOS_FROM_XML': '1'},
])
def test_the_users_profile_wins(clean_cwd, user):
    env = dict(user)
    assert memory.configure_node_memory(env) == '/etc/mine.xml'
    assert env == user


def test_a_profile_in_the_working_directory_wins(clean_cwd):
    (clean_cwd / 'DEFAULT_FASTRTPS_PROFILES.xml').write_text('<dds/>')
    env = {}
    assert memory.configure_node_memory(env) == str(clean_cwd / 'DEFAULT_FASTRTPS_PROFILES.xml')
    assert env == {}


@pytest.mark.parametrize('user', [{'RMW_FASTRTPS_USE_QOS_FROM_XML': '0'},
                                  {'RMW_FASTRTPS_PUBLICATION_MODE': 'ASYNCHRONOUS'}])
def test_the_users_rmw_fastrtps_settings_stay(clean_cwd, user):
    env = dict(user)
    memory.configure_node_memory(env)
    assert env == {**user, 'FASTRTPS_DEFAULT_PROFILES_FILE': str(memory.PROFILE)}


def test_another_rmw_is_left_alone(clean_cwd):
    env = {'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp'}
    assert memory.configure_node_memory(env) is None
    assert env == {'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp'}


# ================================================================== the profiles
def _memory_settings(root: ET.Element) -> dict:
    """What rmw_fastrtps takes from the XML with RMW_FASTRTPS_USE_QOS_FROM_XML=1, and the
    discovery histories, of the default profiles."""
    def default(tag):
        found = [e for e in root.iter(NS + tag) if e.get('is_default_profile') == 'true']
        assert len(found) == 1, tag
        return found[0]

    def text(elem, path):
        found = elem.find('/'.join(NS + p for p in path.split('/')))
        return None if found is None else found.text.strip()

    participant, writer, reader = default('participant'), default('data_writer'), \
        default('data_reader')
    return {
        'builtin_reader': text(participant, 'rtps/builtin/readerHistoryMemoryPolicy'),
        'builtin_writer': text(participant, 'rtps/builtin/writerHistoryMemoryPolicy'),
        'writer_history': text(writer, 'historyMemoryPolicy'),
        'writer_publish_mode': text(writer, 'qos/publishMode/kind'),
        'writer_data_sharing': text(writer, 'qos/data_sharing/kind'),
        'reader_history': text(reader, 'historyMemoryPolicy'),
        'reader_data_sharing': text(reader, 'qos/data_sharing/kind'),
    }


def test_profiles_keep_rmw_fastrtps_settings_but_readers_free_their_memory():
    # rmw_fastrtps (Jazzy) without an XML: PREALLOCATED_WITH_REALLOC everywhere, synchronous
    # publication, no data sharing. The readers' history is the one change.
    expected = {'builtin_reader': 'PREALLOCATED_WITH_REALLOC',
                'builtin_writer': 'PREALLOCATED_WITH_REALLOC',
                'writer_history': 'PREALLOCATED_WITH_REALLOC',
                'writer_publish_mode': 'SYNCHRONOUS', 'writer_data_sharing': 'OFF',
                'reader_history': 'DYNAMIC', 'reader_data_sharing': 'OFF'}
    assert _memory_settings(ET.parse(memory.PROFILE).getroot()) == expected
    # The replay's profile replaces the nodes' one in the processes it starts.
    assert _memory_settings(ET.fromstring(DDS_PROFILE)) == expected


def _announcement_s(root: ET.Element) -> float:
    participant = [e for e in root.iter(NS + 'participant')
                   if e.get('is_default_profile') == 'true'][0]
    found = participant.find('/'.join(NS + p for p in (
        'rtps', 'builtin', 'discovery_config', 'leaseAnnouncement')))
    assert found is not None, 'no leaseAnnouncement: Fast DDS announces every 3 s'
    return (int(found.find(NS + 'sec').text) + 1e-9 * int(found.find(NS + 'nanosec').text))


def test_profiles_announce_participants_often_enough_for_a_restart_within_a_second():
    # A restarted node meets the running ones at their next announcement (Fast DDS
    # default: every 3 s); the node processes' and the replay's profiles say 0.5 s.
    assert _announcement_s(ET.parse(memory.PROFILE).getroot()) == 0.5
    assert _announcement_s(ET.fromstring(DDS_PROFILE)) == 0.5


# ============================================================ a node process
def _rss_mb(pid: int, field: str = 'VmRSS') -> float:
    for line in Path(f'/proc/{pid}/status').read_text().splitlines():
        if line.startswith(field + ':'):
            return int(line.split()[1]) / 1024.0
    raise AssertionError(f'no {field} for {pid}')


def _settled_rss_mb(probe, pid: int, timeout_s: float = 30.0) -> float:
    """Resident memory once it holds still: two readings 0.5 s apart within 1 MB [MB]."""
    deadline = time.monotonic() + timeout_s
    last = _rss_mb(pid)
    while True:
        probe.spin_for(0.5)
        now = _rss_mb(pid)
        if abs(now - last) < 1.0:
            return now
        assert time.monotonic() < deadline, f'resident memory still moving ({last}, {now})'
        last = now


def _image(stamp_s: int, side: int) -> Image:
    msg = Image()
    msg.header.stamp.sec = stamp_s
    msg.header.frame_id = 'camera'
    msg.height = msg.width = side
    msg.encoding, msg.step = 'bgr8', 3 * side
    msg.data = bytes(3 * side * side)
    return msg


@pytest.mark.slow
@pytest.mark.ros
def test_camera_node_gives_back_the_memory_of_a_refused_large_image(tmp_path):
    """A 4100x4100 image (50 MB, over the 4096 px limit) taken whole (reliable
    subscription) and refused: resident memory back within 20 MB once it is counted."""
    domain = ros_domain_id()
    log = open(tmp_path / 'camera_node.log', 'w')
    proc = subprocess.Popen(
        [sys.executable, '-m', 'gnsscam_ros.nodes.camera_node', '--ros-args',
         '-p', 'input_reliable:=true', '-p', 'diagnostics_period_s:=0.2'],
        env=ros_env(tmp_path, domain), cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
    probe = None
    try:
        probe = RosGraph(domain)
        counts: dict = {}

        def on_diagnostics(msg):
            for status in msg.status:
                if status.name.startswith('camera_node'):
                    counts.update({kv.key: kv.value for kv in status.values})

        def counted(key: str, n: int):
            return lambda: float(counts.get(key, 0)) >= n

        probe.probe.create_subscription(DiagnosticArray, 'diagnostics', on_diagnostics,
                                        probe.qos)
        pub = probe.publisher(Image, 'camera/image_raw')
        probe.spin_until(lambda: pub.get_subscription_count() > 0 or proc.poll() is not None,
                         60.0, 'camera_node subscribing camera/image_raw')
        assert proc.poll() is None, (tmp_path / 'camera_node.log').read_text()
        # Small valid images first (answered empty: no map database), until counted: the
        # paths a message takes are warm before the baseline.
        for k in range(3):
            pub.publish(_image(100 + k, 64))
        probe.spin_until(counted('received_images', 3), 30.0, 'three small images counted')
        before = _settled_rss_mb(probe, proc.pid)
        pub.publish(_image(110, 4100))
        probe.spin_until(counted('rejected_size', 1), 60.0, 'the large image refused')
        pub.publish(_image(111, 64))
        probe.spin_until(counted('received_images', 5), 30.0, 'a small image after it')
        # Refused, so taken whole; and gone (Fast DDS's default reader history kept it):
        # waited for with a generous timeout, not a fixed pause (a loaded machine frees
        # late).
        deadline = time.monotonic() + 60.0
        while _rss_mb(proc.pid) - before >= 20.0 and time.monotonic() < deadline:
            probe.spin_for(0.2)
        after = _rss_mb(proc.pid)
        assert after - before < 20.0, (before, after, _rss_mb(proc.pid, 'VmHWM'))
    finally:
        if probe is not None:
            probe.close()
        rc = stop(proc)
        log.close()
    text = (tmp_path / 'camera_node.log').read_text()
    assert rc == 0, text
    assert 'XMLPARSER' not in text, text        # Fast DDS read the profile without error


_EPOCHS = '''
import resource, sys
import numpy as np
from gnsscam_ros.nodes.memory import keep_epoch_memory
kept = keep_epoch_memory() if sys.argv[1] == 'kept' else None
def epoch():
    # The propagated sets at N = 10,000, M = 10 and two temporaries of their size.
    sets = np.empty((10, 10_000, 4))
    sets.fill(1.0)
    moved = sets + 1.0
    scaled = moved * 2.0
    return float(scaled[0, 0, 0])
epoch()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):
    epoch()
print(kept, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
'''


def test_epoch_arrays_stay_in_the_process_instead_of_faulting_in_every_epoch():
    def faults(mode: str) -> tuple[str, int]:
        out = subprocess.run([sys.executable, '-c', _EPOCHS, mode], capture_output=True,
                             text=True, check=True).stdout.split()
        return out[0], int(out[1])

    kept, with_setting = faults('kept')
    _, without = faults('default')
    assert kept == 'True'
    # glibc's default gives the freed 9.6 MB back and faults them in again every epoch.
    assert without > 20 * 1000
    assert with_setting < 0.05 * without


_FREEZE = '''
import gc, weakref
import numba, scipy.stats  # a started node's share of tracked objects
from gnsscam_ros.nodes.memory import freeze_start_up_objects


class Node:
    pass


cycle = Node()
cycle.me = cycle                        # garbage of the start-up: only the collector frees it
gone = weakref.ref(cycle)
del cycle
kept = [Node() for _ in range(1000)]
tracked = len(gc.get_objects())
frozen = freeze_start_up_objects()
print(tracked, frozen, len(gc.get_objects()), gone() is None, kept[0] in gc.get_objects())
'''


def test_start_up_objects_leave_the_collectors_full_collections():
    out = subprocess.run([sys.executable, '-c', _FREEZE], capture_output=True, text=True,
                         check=True).stdout.split()
    tracked, frozen, after = (int(v) for v in out[:3])
    assert tracked > 20_000                 # what a full collection walked before
    assert frozen >= 0.9 * tracked          # nearly all of it frozen (garbage freed)
    assert after < 100                      # and no longer walked
    assert out[3:] == ['True', 'False']     # the start-up garbage was collected first
