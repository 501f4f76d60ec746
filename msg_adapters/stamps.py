"""builtin_interfaces/Time <-> integer nanoseconds (the core's time unit)."""
from __future__ import annotations

from builtin_interfaces.msg import Time

from .errors import MessageError

NS_PER_S = 1_000_000_000
_MAX_SEC = 2 ** 31 - 1


def stamp_to_ns(stamp: Time) -> int:
    """Header stamp -> nanoseconds since the epoch of the clock [ns]."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def ns_to_stamp(stamp_ns: int) -> Time:
    """Nanoseconds -> header stamp.

    Raises:
        MessageError: Negative or beyond the int32 seconds of ``builtin_interfaces/Time``.
    """
    stamp_ns = int(stamp_ns)
    sec, nanosec = divmod(stamp_ns, NS_PER_S)
    if not 0 <= sec <= _MAX_SEC:
        raise MessageError(f'stamp {stamp_ns} ns does not fit builtin_interfaces/Time',
                           'stamp')
    return Time(sec=sec, nanosec=nanosec)
