"""Every node parameter, declared once with its metadata (``core.parameters``): default,
meaning, unit, range, read-only; no rclpy here.

A node's parameters are the fields of dataclasses: the core's own configurations
(``FilterConfig``'s parts, ``InputTiming``, ``DeadReckoningConfig``: the offline runs use
the same names and defaults) and the node's own settings below (frames, queues, timeouts;
frame and depth defaults are the topic registry's, ``msg_adapters.wire.TOPICS``). The
nodes declare them from these groups (``GnssCamNode.declare_node_parameters``),
``config/*.yaml`` documents them, and :mod:`.parameter_reference` (with fusion_node's
groups, which need the filter) renders the markdown parameter reference.

This module imports no numba, scipy or OpenCV: the light nodes start without them.
"""
from __future__ import annotations

from dataclasses import dataclass

from gnsscam_ros.core.motion import DeadReckoningConfig
from gnsscam_ros.core.parameters import ParameterSpec, field_specs, parameter
from msg_adapters.wire import (BASE_FRAME, DEAD_RECKONING, FIX, GNSS, GNSS_FIX,
                               GNSS_MEASUREMENTS, IMAGE, IMU, MATCHES, POSE, TOPICS)

# Float ranges need finite ends; this stands for "no upper limit".
BIG = 1e12
#: Largest queue depth a parameter may set [messages].
MAX_QUEUE_DEPTH = 100_000
#: Longest silence of GNSS (or of processed epochs) before integrity_risk is STALE [s]: a
#: larger value would let a consumer take the last verdict as current for longer than a
#: minute (1e12 disabled STALE altogether).
MAX_GNSS_TIMEOUT_S = 60.0
#: Longest period of the STALE reports while stale [s].
MAX_STALE_REPORT_PERIOD_S = 10.0


def _llh_default():
    return (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class EveryNode:
    """Parameters every node of the package has (``GnssCamNode``)."""

    diagnostics_period_s: float = parameter(
        1.0, 'Period of the diagnostics report.', 's', low=0.05, high=3600.0,
        read_only=True)


@dataclass(frozen=True)
class GnssNodeSettings:
    """gnss_node: its checks of the receiver's epochs and its snapshot fix."""

    elevation_mask_deg: float = parameter(
        0.0, 'Satellites below this elevation are dropped; NaN elevations are kept.', 'deg',
        low=-90.0, high=90.0)
    cn0_mask_dbhz: float = parameter(
        0.0, 'Satellites below this C/N0 are dropped; NaN C/N0 is kept.', 'dB-Hz', low=0.0,
        high=100.0)
    min_satellites: int = parameter(
        4, 'Fewest satellites for a usable epoch (position + clock: >= 4).', low=4,
        high=1000)
    measurement_var_m2: float = parameter(
        10.0, 'Floor of the pseudorange variance in the snapshot fix.', 'm^2', low=1e-6)
    input_frame_id: str = parameter(
        TOPICS[GNSS].frame_id, 'Required frame of gnss/pseudoranges (ECEF); others are '
        'refused.', read_only=True)
    fix_frame_id: str = parameter(TOPICS[GNSS_FIX].frame_id, 'Frame of gnss/fix (antenna).')
    input_queue_depth: int = parameter(
        TOPICS[GNSS].depth, 'Subscription queue depth of gnss/pseudoranges.', 'messages',
        low=1, high=MAX_QUEUE_DEPTH, read_only=True)
    stale_timeout_s: float = parameter(
        2.0, 'No pseudoranges for this long is reported as a stale input.', 's', low=0.01)


@dataclass(frozen=True)
class ImuNodeSettings:
    """imu_node: sources, frames and queues of the dead reckoning."""

    source_timeout_s: float = parameter(
        0.5, 'A source without messages for this long is inactive (wall time).', 's',
        low=0.001)
    odom_frame_id: str = parameter(TOPICS[DEAD_RECKONING].frame_id,
                                   'Frame of odometry/dead_reckoning.')
    base_frame_id: str = parameter(BASE_FRAME, 'Child frame of odometry/dead_reckoning.')
    input_queue_depth: int = parameter(
        TOPICS[IMU].depth, 'Subscription queue depth of imu/data and odom/twist.',
        'messages', low=1, high=MAX_QUEUE_DEPTH, read_only=True)
    output_queue_depth: int = parameter(
        TOPICS[DEAD_RECKONING].depth, 'Publisher queue depth of odometry/dead_reckoning.',
        'messages', low=1, high=MAX_QUEUE_DEPTH, read_only=True)


@dataclass(frozen=True)
class CameraNodeSettings:
    """camera_node: the map database, the matcher and its queues."""

    database_path: str = parameter(
        '', "Map database file (.npz from gnsscam_mapdb build); '' = none (every frame is "
        'answered empty).', read_only=True)
    top_k: int = parameter(5, 'Matches published per image.', low=1, high=1000)
    queue_size: int = parameter(
        2, 'Frames waiting for the matcher; when full the oldest is dropped.', low=1,
        high=1000, read_only=True)
    use_map_origin: bool = parameter(
        False, 'Convert WGS84 database positions to the map frame at map_origin_llh (set '
        'the same origin as fusion_node); false = database frame.', read_only=True)
    map_origin_llh: tuple = parameter(
        _llh_default(), 'Map frame origin [lat deg, lon deg, alt m].', read_only=True)
    map_frame_id: str = parameter(TOPICS[MATCHES].frame_id, 'Frame of camera/matches.')
    opencv_threads: int = parameter(
        1, 'OpenCV worker threads (1 = match on one core).', low=0, high=256,
        read_only=True)
    input_queue_depth: int = parameter(
        TOPICS[IMAGE].depth, 'Subscription queue depth of camera/image_raw.', 'messages',
        low=1, high=MAX_QUEUE_DEPTH, read_only=True)
    input_reliable: bool = parameter(
        False, 'Subscribe camera/image_raw reliably instead of best effort (sensor QoS): a '
        'VGA frame is ~0.9 MB, split into many UDP fragments; best effort loses the frame '
        'with any fragment.', read_only=True)
    stale_timeout_s: float = parameter(
        2.0, 'No image for this long is reported as a stale input.', 's', low=0.01)


@dataclass(frozen=True)
class FusionNodeSettings:
    """fusion_node: its random seed, map frame, frames, STALE reports and queues (the
    filter's parameters are ``FilterConfig``'s, its waits and buffers ``InputTiming``'s)."""

    seed: int = parameter(
        -1, 'Seed of the filter random generator; -1 = fresh entropy.', low=-1,
        high=2 ** 62, read_only=True)
    use_map_origin: bool = parameter(
        False, 'Anchor the map frame at map_origin_llh; false = at the first robust fix.',
        read_only=True)
    map_origin_llh: tuple = parameter(
        _llh_default(), 'Map frame origin [lat deg, lon deg, alt m].', read_only=True)
    map_frame_id: str = parameter(
        TOPICS[POSE].frame_id, 'Frame of pose, particles, odometry/global and map/origin, '
        "and the required frame of camera/matches (camera_node's map_frame_id).")
    fix_frame_id: str = parameter(TOPICS[FIX].frame_id, 'Frame of fix.')
    base_frame_id: str = parameter(
        BASE_FRAME, 'Child frame of odometry/global (the vehicle; its twist is in it) and of '
        'odometry/dead_reckoning (others are refused).')
    odom_frame_id: str = parameter(
        TOPICS[DEAD_RECKONING].frame_id, "Frame of odometry/dead_reckoning (imu_node's "
        'odom_frame_id; others are refused).')
    gnss_timeout_s: float = parameter(
        2.0, 'No GNSS epoch (or none processed) for this long: integrity_risk STALE.', 's',
        low=0.01, high=MAX_GNSS_TIMEOUT_S)
    stale_report_period_s: float = parameter(
        1.0, 'Period of the STALE integrity_risk reports while stale.', 's', low=0.01,
        high=MAX_STALE_REPORT_PERIOD_S)
    max_published_particles: int = parameter(
        1000, 'Particles published on particles (weighted subsample); 0 = all.', low=0,
        high=100_000_000)
    odometry_queue_depth: int = parameter(
        1000, 'Subscription queue depth of odometry/dead_reckoning, deeper than the '
        "topic's: it covers a filter epoch at the IMU rate.", 'messages', low=1,
        high=1_000_000, read_only=True)
    input_queue_depth: int = parameter(
        TOPICS[GNSS_MEASUREMENTS].depth, 'Subscription queue depth of gnss/measurements and '
        'camera/matches.', 'messages', low=1, high=MAX_QUEUE_DEPTH, read_only=True)


#: The parameters every node has.
EVERY_NODE = field_specs(EveryNode, 'EveryNode')


#: The parameters every node has.
EVERY_NODE = field_specs(EveryNode, 'EveryNode')
#: A node's parameters: ``(where declared, specs)`` groups in declaration order (the
#: order of ``config/<node>.yaml``).
Groups = list[tuple[str, tuple[ParameterSpec, ...]]]


def own(cls) -> tuple[str, tuple[ParameterSpec, ...]]:
    """The group of a node's own settings dataclass."""
    return cls.__name__, field_specs(cls, cls.__name__)


GNSS_NODE: Groups = [own(GnssNodeSettings), ('every node', EVERY_NODE)]
CAMERA_NODE: Groups = [own(CameraNodeSettings), ('every node', EVERY_NODE)]
IMU_NODE: Groups = [('DeadReckoningConfig', DeadReckoningConfig.parameter_specs()),
                    own(ImuNodeSettings), ('every node', EVERY_NODE)]


def specs_of(groups: Groups) -> tuple[ParameterSpec, ...]:
    """Every parameter of the groups, in declaration order."""
    return tuple(spec for _, specs in groups for spec in specs)


def defaults_of(groups: Groups) -> dict:
    """``{name: default}`` of the groups' parameters (lists where ROS takes arrays)."""
    return {s.name: list(s.default) if isinstance(s.default, tuple) else s.default
            for s in specs_of(groups)}
