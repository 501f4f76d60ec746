"""Starting the four nodes for a replay: in this process or as child processes, with their
parameters, a ROS domain and namespace of their own, and the Fast DDS profile for camera
images between processes; and what they cost in CPU time.

**Node parameters for replay.** Some node timeouts are in wall time, which a replay at
``R != 1`` does not follow, and fusion_node's ``camera/matches`` queue (10) is shorter than
the matches that arrive while it runs a slow epoch. :data:`REPLAY_NODE_PARAMETERS` lifts
them (imu_node's ``source_timeout_s``: otherwise a pause of the odometry stream longer than
0.5 s while the filter runs a slow epoch would switch the dead reckoning to the IMU-only
source for a moment; fusion_node's ``odometry_wait_s``, ``odometry_timeout_s``,
``gnss_timeout_s`` and ``input_queue_depth``). With them, a replay at ``R = 0`` gives the
nodes the same input in the same order whatever the speed. :func:`write_params_file`
writes them as a ``--params-file``.

**Large messages.** With Fast DDS's default transports a camera image (0.9 MB) does not fit
the shared-memory segment and travels as UDP fragments, and a best-effort subscriber
(camera_node) loses most images sent from another process. :func:`use_dds_profile` points
Fast DDS at :data:`DDS_PROFILE` (a 32 MB shared-memory segment; only the publishing
process needs it) unless ``FASTRTPS_DEFAULT_PROFILES_FILE`` is set. The node processes
inherit it instead of their own profile, so it carries the same history memory settings
(:mod:`gnsscam_ros.nodes.memory`: memory given back after a large message).
"""
from __future__ import annotations

import itertools
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml
from rclpy.parameter import Parameter

from ..nodes.camera_node import CameraNode
from ..nodes.memory import use_fastdds_profile
from ..nodes.runtime import stop_process
from ..nodes.fusion_node import FusionNode
from ..nodes.gnss_node import GnssNode
from ..nodes.imu_node import ImuNode

#: Where :func:`.replay_through_nodes.replay_through_nodes` runs the nodes: in this process, one
#: executor thread each; as four child processes; or as pipeline_node in one child process.
LAYOUTS = ('threads', 'processes', 'pipeline')
#: Wait after the graph is connected for node processes started together with the replay:
#: two participants that miss each other's first announcements meet at the next periodic
#: one (Fast DDS: every 3 s) [s].
FRESH_PROCESSES_SETTLE_S = 3.5

#: Node parameters for a replay whose time is not wall time (see module doc). The waits stay
#: finite so that an epoch after the last odometry sample is still processed at the end;
#: fusion_node's are at most its upper bounds (odometry_wait_s 10 s, gnss_timeout_s 60 s).
REPLAY_NODE_PARAMETERS: dict[str, dict] = {
    'imu_node': {'source_timeout_s': 3600.0},
    'fusion_node': {'odometry_wait_s': 10.0, 'odometry_timeout_s': 10.0,
                    'gnss_timeout_s': 60.0, 'input_queue_depth': 200},
}

_runs = itertools.count()


# --------------------------------------------------------------- domain, namespace
def default_domain_id() -> int:
    """``$ROS_DOMAIN_ID``, else a domain in 220-232 (apart from the tests' ids) that
    changes with the process and with every call, so that concurrent runs on one machine
    do not see each other's topics and a run does not match the endpoints of a previous
    run's nodes that the discovery has not forgotten yet."""
    env = os.environ.get('ROS_DOMAIN_ID')
    if env and env.isdigit():
        return int(env)
    return 220 + (os.getpid() + next(_runs)) % 13


def private_namespace() -> str:
    """A namespace of its own for one run, ``/gnsscam_<pid>_<n>``, so that other graphs on
    the machine, in the same domain or not, never mix with it."""
    return f'/gnsscam_{os.getpid()}_{next(_runs)}'


# -------------------------------------------------------------------- parameters
def write_params_file(path: str | Path, parameters: dict[str, dict]) -> Path:
    """Write ``{node: {name: value}}`` as a ROS 2 ``--params-file`` (YAML).

    Args:
        path: File to write (replaced if present: it is a generated input, not a result).
        parameters: Parameters by node name.

    Returns:
        The path.
    """
    path = Path(path)
    data = {node: {'ros__parameters': dict(values)} for node, values in parameters.items()}
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding='utf-8')
    return path


def merge_parameters(*layers: dict[str, dict]) -> dict[str, dict]:
    """Merge ``{node: {name: value}}`` dictionaries, later layers winning per key."""
    out: dict[str, dict] = {}
    for layer in layers:
        for node, values in (layer or {}).items():
            out.setdefault(node, {}).update(values)
    return out


# ------------------------------------------------------------------- DDS profile
#: Fast DDS profile for large messages between processes on one machine. With the default
#: transports a 640x480 bgr8 image (0.9 MB) does not fit the 512 kB shared-memory segment
#: and travels as UDP fragments; a best-effort reader (camera_node takes images with sensor
#: QoS) drops the whole image when one fragment is lost, which loopback socket buffers
#: make common: measured here, 17 of 50 images paced at 10 Hz arrived. A 32 MB segment
#: carries whole images (50 of 50), and the GNSS epochs no longer compete with them for it.
#: The node processes started by a replay read this file instead of their own
#: (``nodes/fastdds_profile.xml``), so the participant's ``builtin`` and the
#: ``data_writer``/``data_reader`` profiles repeat that file's (the same test checks both).
DDS_PROFILE = """<?xml version="1.0" encoding="UTF-8" ?>
<!-- gnsscam_ros: shared memory large enough for camera images (see live/launch.py), and
     the node processes' history memory (see nodes/memory.py). -->
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <transport_descriptors>
    <transport_descriptor>
      <transport_id>gnsscam_shm</transport_id>
      <type>SHM</type>
      <segment_size>33554432</segment_size>
      <port_queue_capacity>1024</port_queue_capacity>
      <maxMessageSize>4194304</maxMessageSize>
    </transport_descriptor>
    <transport_descriptor>
      <transport_id>gnsscam_udp</transport_id>
      <type>UDPv4</type>
    </transport_descriptor>
  </transport_descriptors>
  <participant profile_name="gnsscam_participant" is_default_profile="true">
    <rtps>
      <userTransports>
        <transport_id>gnsscam_shm</transport_id>
        <transport_id>gnsscam_udp</transport_id>
      </userTransports>
      <useBuiltinTransports>false</useBuiltinTransports>
      <builtin>
        <!-- A participant announces itself every 0.5 s (Fast DDS: 3 s): a node that
             restarts finds the running ones within a second instead of up to 3 s. -->
        <discovery_config>
          <leaseAnnouncement>
            <sec>0</sec>
            <nanosec>500000000</nanosec>
          </leaseAnnouncement>
        </discovery_config>
        <readerHistoryMemoryPolicy>PREALLOCATED_WITH_REALLOC</readerHistoryMemoryPolicy>
        <writerHistoryMemoryPolicy>PREALLOCATED_WITH_REALLOC</writerHistoryMemoryPolicy>
      </builtin>
    </rtps>
  </participant>
  <data_writer profile_name="gnsscam_writer" is_default_profile="true">
    <qos>
      <publishMode>
        <kind>SYNCHRONOUS</kind>
      </publishMode>
      <data_sharing>
        <kind>OFF</kind>
      </data_sharing>
    </qos>
    <historyMemoryPolicy>PREALLOCATED_WITH_REALLOC</historyMemoryPolicy>
  </data_writer>
  <data_reader profile_name="gnsscam_reader" is_default_profile="true">
    <qos>
      <data_sharing>
        <kind>OFF</kind>
      </data_sharing>
    </qos>
    <historyMemoryPolicy>DYNAMIC</historyMemoryPolicy>
  </data_reader>
</profiles>
"""


def write_dds_profile(path: str | Path) -> Path:
    """Write :data:`DDS_PROFILE` (use it with ``FASTRTPS_DEFAULT_PROFILES_FILE=path`` in
    every process of the graph, before it starts)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(DDS_PROFILE, encoding='utf-8')
    return path


def use_dds_profile(folder: str | Path) -> str | None:
    """Point Fast DDS at :data:`DDS_PROFILE` (written into ``folder``), with its history
    memory settings in force, unless the user configures Fast DDS or another RMW is used
    (:func:`gnsscam_ros.nodes.memory.use_fastdds_profile`).

    Fast DDS reads the file when a process creates its first participant, so call this
    before the first ``rclpy.init`` of the process; child processes inherit it.

    Returns:
        The profile file in force (None: not Fast DDS).
    """
    path = Path(folder) / 'fastdds_profile.xml'
    in_force = use_fastdds_profile(path)
    if in_force == str(path):
        write_dds_profile(path)
    return in_force


# ------------------------------------------------------------------------ nodes
def make_nodes(context, namespace: str, params: dict[str, dict], database=None) -> list:
    """The four nodes in this process (``'threads'``), each with its parameters.

    Args:
        context: The rclpy context.
        namespace: Their namespace.
        params: ``{node name: {name: value}}``.
        database: A loaded map database for camera_node (None: its parameters decide).
    """
    def kwargs(node: str) -> dict:
        return {'context': context, 'namespace': namespace,
                'parameter_overrides': [Parameter(name, value=value) for name, value
                                        in params.get(node, {}).items()]}

    return [GnssNode(**kwargs('gnss_node')),
            CameraNode(database=database, **kwargs('camera_node')),
            ImuNode(**kwargs('imu_node')), FusionNode(**kwargs('fusion_node'))]


def start_node_processes(params: dict[str, dict], domain: int,
                         log_dir: str | Path | None, pipeline: bool, namespace: str) -> list:
    """Start the nodes as child processes (``python -m gnsscam_ros.nodes.<node>``, as
    ``ros2 run`` starts them, with a generated ``--params-file``): ``[(Popen, name)]``.

    Args:
        params: ``{node name: {name: value}}``.
        domain: ROS domain id.
        log_dir: Folder for their ROS logs and stderr (default: a new temporary folder).
        pipeline: One ``pipeline_node`` process instead of the four nodes.
        namespace: Their namespace.
    """
    folder = Path(log_dir) if log_dir is not None else Path(
        tempfile.mkdtemp(prefix='gnsscam_replay_'))
    folder.mkdir(parents=True, exist_ok=True)
    # Keys with the namespace: a bare node name only matches nodes in the root namespace.
    params_file = write_params_file(folder / 'replay_params.yaml', {
        f'{namespace.rstrip("/")}/{node}': values for node, values in params.items()})
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=str(domain), ROS_LOG_DIR=str(folder / 'ros_log'),
               ROS_AUTOMATIC_DISCOVERY_RANGE=env.get('ROS_AUTOMATIC_DISCOVERY_RANGE',
                                                     'LOCALHOST'),
               OPENBLAS_NUM_THREADS=env.get('OPENBLAS_NUM_THREADS', '1'))
    modules = ({'pipeline_node': 'pipeline'} if pipeline else
               {name: name for name in ('gnss_node', 'camera_node', 'imu_node', 'fusion_node')})
    procs = []
    try:
        for name, module in modules.items():
            stderr = (folder / f'{name}.stderr.txt').open('w')
            procs.append((subprocess.Popen(
                [sys.executable, '-m', f'gnsscam_ros.nodes.{module}', '--ros-args',
                 '-r', f'__ns:={namespace}', '--params-file', str(params_file)], env=env,
                stdout=subprocess.DEVNULL, stderr=stderr), name))
            stderr.close()
    except BaseException:
        for proc, _ in procs:
            stop_process(proc)
        raise
    return procs


# -------------------------------------------------------------------------- CPU
def own_cpu_s() -> float:
    """CPU time of this process so far (all threads) [s]."""
    return time.process_time()


def process_cpu_s(pid: int) -> float:
    """CPU time (user + system) of a running child process [s] (NaN when unknown)."""
    try:
        fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')
    except (OSError, ValueError, IndexError):
        return math.nan
