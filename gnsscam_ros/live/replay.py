"""``gnsscam_replay``: play a rosbag2 bag into the nodes, lossless at any speed.

Usage::

    gnsscam_replay BAG [--rate R] [--start S] [--topics T [T ...]]

Messages go out in bag order with their original timing scaled by ``R`` (``R = 0``: as
fast as the nodes keep up), each one once the node graph has room for it (flow control on
the nodes' own outputs). ``--start S`` skips the first ``S`` seconds (bag time), except the
once-only topics ``dataset/info`` and ``map/origin``, which are always published first.
``--topics`` plays only the named topics (relative ``imu/data`` or qualified
``/imu/data``). The bag's serialised messages are published as they are.

On a ROS 2 machine ``ros2 bag play BAG`` replays the same bag in real time; it knows
nothing of the nodes' queues, so at high rates it may lose input.

The live layer, by job:

* :mod:`.player`: the replay node (:class:`~.player.BagReplayer`): timing, equal-stamp
  order, waiting for the graph, the summary's figures;
* :mod:`.flow`: the flow-control rules (:data:`~.flow.FLOW_RULES`, windows,
  acknowledgements);
* :mod:`.summary`: what a replay did (:class:`~.summary.ReplaySummary`);
* :mod:`.launch`: starting the nodes (threads or processes), their replay parameters, the
  domain id and namespace, the Fast DDS profile for camera images;
* :mod:`.replay_through_nodes`: :func:`~.replay_through_nodes.replay_through_nodes`, the
  whole chain with recording;
* :mod:`.record`: ``gnsscam_record``, the recorder;
* this module: the ``gnsscam_replay`` command line; it re-exports the names above that
  other code imports from here.

The CLI starts with the Fast DDS profile of :mod:`.launch` (a shared-memory segment large
enough for camera images) unless ``FASTRTPS_DEFAULT_PROFILES_FILE`` is set or
``--no-dds-profile`` is given.

``--namespace NS`` plays into ``NS``: the topics are published under it (as the nodes'
``__ns:=NS``), whether the bag's topics were written under ``NS`` or at the root.

Exit codes of the CLI: 0 done (also on Ctrl-C: the replay stops after the current
message), 2 bad usage, 3 bad input: the bag is missing, unreadable, truncated or empty,
has an unknown message type, a topic of the gnsscam_ros graph with another type than the
nodes use (e.g. ``std_msgs/msg/String`` on ``gnss/pseudoranges``: refused before anything
is published), or a message that does not decode (the replay stops there); 4 the
``--json`` file exists or cannot be written. Every error is one line naming the bag (and
the topic and bag time where one is at fault).

``python -m gnsscam_ros.bench.replay`` measures replay through the nodes at 10,000
particles (speed as a multiple of real time, dropped GNSS epochs).
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.validate_namespace import validate_namespace

from ..bags.errors import BagError
from ..io.atomic import check_writable, write_json_atomic
from .replay_through_nodes import ReplayOptions, replay_through_nodes
from .launch import LAYOUTS, use_dds_profile
from .player import BagReplayer
from .summary import ReplaySummary

# Importable from here as before the live layer was split (evaluation.demo imports
# replay_through_nodes, use_dds_profile and LAYOUTS from this module).
__all__ = ['BagReplayer', 'LAYOUTS', 'ReplayOptions', 'ReplaySummary', 'build_parser', 'main',
           'replay_through_nodes', 'use_dds_profile']

EXIT_OK, EXIT_USAGE, EXIT_INPUT, EXIT_OUTPUT = 0, 2, 3, 4


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='gnsscam_replay',
        description='Play a rosbag2 bag into the gnsscam_ros nodes with its original timing '
        'scaled by --rate, lossless (flow control on the nodes\' outputs). Alternative on '
        'a ROS 2 machine: ros2 bag play BAG.')
    parser.add_argument('bag', type=Path, help='bag folder (or .mcap / .db3 file)')
    parser.add_argument('--rate', type=float, default=1.0,
                        help='time scale: 2 = twice as fast; 0 = as fast as the nodes keep '
                        'up (default %(default)s)')
    parser.add_argument('--start', type=float, default=0.0, metavar='S',
                        help='skip the first S seconds of the bag (default 0)')
    parser.add_argument('--topics', nargs='+', metavar='TOPIC',
                        help='play only these topics (default: all)')
    parser.add_argument('--no-flow-control', action='store_true',
                        help='publish on time only, never wait for the nodes (may lose '
                        'input at high rates)')
    parser.add_argument('--ack-timeout', type=float, default=30.0, metavar='SECONDS',
                        help='longest wait for one acknowledgement (default %(default)s)')
    parser.add_argument('--wait', type=float, default=10.0, metavar='SECONDS',
                        help='longest wait for the nodes to appear (default %(default)s)')
    parser.add_argument('--namespace', default='/',
                        help='namespace to play into: the topics are published under it, '
                        'where nodes started with __ns:=NAMESPACE listen; the bag\'s topics '
                        'may be written under it or at the root (default /)')
    parser.add_argument('--no-dds-profile', action='store_true',
                        help='keep Fast DDS\'s default transports (by default the replay '
                        'uses a shared-memory segment large enough for camera images, unless '
                        'FASTRTPS_DEFAULT_PROFILES_FILE is set)')
    parser.add_argument('--json', type=Path, help='write the summary as JSON')
    return parser


def main(argv: list[str] | None = None) -> int:
    """``gnsscam_replay``; returns the exit code (see the module docstring)."""
    args_all = sys.argv[1:] if argv is None else list(argv)
    # --ros-args ... belongs to rclpy (remaps, parameters); the rest is ours.
    ros_at = args_all.index('--ros-args') if '--ros-args' in args_all else len(args_all)
    parser = build_parser()
    args = parser.parse_args(args_all[:ros_at])
    if args.json is not None and (args.json.exists() or args.json.is_symlink()):
        print(f'gnsscam_replay: {args.json} exists; not overwriting', file=sys.stderr)
        return EXIT_OUTPUT
    if args.json is not None:
        try:
            check_writable(args.json)       # said now, not after the whole run
        except OSError as err:
            print(f'gnsscam_replay: cannot write {args.json}: {err.strerror or err}',
                  file=sys.stderr)
            return EXIT_OUTPUT
    try:
        # The node's namespace, as __ns:= gives it (a remap in --ros-args still wins).
        namespace = '/' + args.namespace.strip('/')
        validate_namespace(namespace)
    except Exception as err:            # rclpy's InvalidNamespaceException and kin
        print(f'gnsscam_replay: --namespace {args.namespace!r}: '
              f'{str(err).splitlines()[0]}', file=sys.stderr)
        return EXIT_USAGE
    if not args.no_dds_profile:
        use_dds_profile(Path(tempfile.gettempdir()) / f'gnsscam_replay_{os.getuid()}')
    try:
        rclpy.init(args=['gnsscam_replay'] + args_all[ros_at:])
    except Exception as err:            # malformed --ros-args (rcl's own message)
        print(f'gnsscam_replay: bad ROS arguments: {str(err).splitlines()[0]}',
              file=sys.stderr)
        return EXIT_USAGE
    node = None
    summary = None
    code = EXIT_OK
    try:
        # bag_namespace None: the bag's topics are found under --namespace or at the root,
        # and published under --namespace either way.
        node = BagReplayer(args.bag, rate=args.rate, start_s=args.start, topics=args.topics,
                           flow_control=not args.no_flow_control,
                           ack_timeout_s=args.ack_timeout, wait_s=args.wait,
                           bag_namespace=None, namespace=namespace)
        summary = node.play()
    except (BagError, ValueError) as err:
        print(f'gnsscam_replay: {err}', file=sys.stderr)
        code = EXIT_INPUT if isinstance(err, BagError) else EXIT_USAGE
    except (KeyboardInterrupt, ExternalShutdownException):
        print('gnsscam_replay: interrupted', file=sys.stderr)
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    if summary is not None:
        print(summary.text())
        if args.json is not None:
            try:
                write_json_atomic(args.json, summary.as_dict())
            except (OSError, ValueError) as err:
                print(f'gnsscam_replay: cannot write {args.json}: {err}', file=sys.stderr)
                code = code or EXIT_OUTPUT
    return code


if __name__ == '__main__':
    sys.exit(main())
