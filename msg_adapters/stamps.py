"""builtin_interfaces/Time and std_msgs/Header <-> integer nanoseconds (the core's time unit).

The ns <-> (sec, nanosec) arithmetic is :mod:`.wire`'s; this module builds and reads the
messages.
"""
from __future__ import annotations

from .errors import MessageError
from .message_classes import RCLPY, MessageKit
from .limits import MAX_NANOSEC, MAX_STAMP_SEC, MIN_STAMP_SEC
from .wire import NS_PER_S, join_ns, split_ns

__all__ = ['NS_PER_S', 'make_header', 'ns_to_stamp', 'stamp_to_ns']


def stamp_to_ns(stamp, what: str = 'stamp') -> int:
    """Header stamp -> nanoseconds since the epoch of the clock [ns].

    Only stamps that are valid ``builtin_interfaces/Time`` values come through, so that
    every stamp taken in can be written again (a node publishes its outputs at its input
    stamps).

    Raises:
        MessageError: ``sec`` negative or beyond int32, or ``nanosec`` not below one
            second (reason ``'stamp'``).
    """
    sec, nanosec = int(stamp.sec), int(stamp.nanosec)
    if not (MIN_STAMP_SEC <= sec <= MAX_STAMP_SEC and 0 <= nanosec <= MAX_NANOSEC):
        raise MessageError(f'{what}: stamp sec={sec} nanosec={nanosec} is not a valid '
                           f'builtin_interfaces/Time (sec in [{MIN_STAMP_SEC}, '
                           f'{MAX_STAMP_SEC}], nanosec < {NS_PER_S})', 'stamp')
    return join_ns(sec, nanosec)


def ns_to_stamp(stamp_ns: int, kit: MessageKit = RCLPY):
    """Nanoseconds -> header stamp (``builtin_interfaces/Time`` of ``kit``).

    Raises:
        MessageError: Negative or beyond the int32 seconds of ``builtin_interfaces/Time``.
    """
    sec, nanosec = split_ns(stamp_ns)
    return kit['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec)


def make_header(stamp_ns: int, frame_id: str, kit: MessageKit = RCLPY):
    """``std_msgs/Header`` of ``kit``.

    Raises:
        MessageError: See :func:`ns_to_stamp`.
    """
    return kit['std_msgs/msg/Header'](stamp=ns_to_stamp(stamp_ns, kit), frame_id=frame_id)
