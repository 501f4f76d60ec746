"""builtin_interfaces/Time and std_msgs/Header <-> integer nanoseconds (the core's time unit).

The ns <-> (sec, nanosec) arithmetic is :mod:`.wire`'s; this module builds and reads the
messages.
"""
from __future__ import annotations

from .kit import RCLPY, MessageKit
from .wire import NS_PER_S, join_ns, split_ns

__all__ = ['NS_PER_S', 'make_header', 'ns_to_stamp', 'stamp_to_ns']


def stamp_to_ns(stamp) -> int:
    """Header stamp -> nanoseconds since the epoch of the clock [ns]."""
    return join_ns(stamp.sec, stamp.nanosec)


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
