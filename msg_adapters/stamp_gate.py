"""The stamp gate: one input topic's stamps stay within a window of its recent stream.

A single stamp far from the stream (a glitch: a flipped bit, a clock read wrongly) is
refused, and the stream goes on as if it had not come: refusing it instead of taking it
as the newest stamp keeps one bad message from making every later valid one "out of
order". A deliberate change of the time base (a bag replayed from its start again, a
clock set anew) shows as a run of messages that agree with each other but not with the
stream before: after :data:`.limits.NEW_TIME_BASE_MESSAGES` of them, received over at
least :data:`.limits.NEW_TIME_BASE_SPAN_S` (a burst of consistent garbage is over within
milliseconds), the gate adopts the new time base and says so, so that the node can reset
what it keeps of the old one. The gate never blocks for good.

A stream that starts again from an earlier time *from a new publisher* (a bag played again
by a new player process or node: its sequence numbers start anew) is a new time base at
once: a glitch comes from the publisher of the stream, not with a new one, and a source
restarted live (a driver, imu_node) goes on from a later time.

Plain Python, no ROS: the nodes hold one gate per subscribed topic.
"""
from __future__ import annotations

from .errors import MessageError
from .limits import (NEW_TIME_BASE_MESSAGES, NEW_TIME_BASE_SPAN_S, NS_PER_S,
                     STAMP_WINDOW_NS)

#: Verdicts of :meth:`StampGate.admit`.
ADVANCE = 'advance'        # after the newest accepted stamp, within the window
BEHIND = 'behind'          # not after it but within the window: the node's order rules
NEW_BASE = 'new_base'      # the message completes a new time base: reset, then take it


class StampGate:
    """Admits the stamps of one input topic.

    ``newest_ns`` is the newest stamp accepted as the stream's. A stamp

    * after it by at most ``window_ns`` advances it (:data:`ADVANCE`);
    * not after it, by at most ``window_ns``, is passed on (:data:`BEHIND`): whether such
      a message is out of order (a duplicate, a late one) is the node's rule, as before;
    * further away either way is refused (``MessageError``, reason ``'stamp_jump'``).

    Every message that does not advance the stream (behind or refused) is also a
    candidate of a new time base: ``confirm`` consecutive ones, each after the previous
    and within ``window_ns`` of it, received over at least ``span_s`` (when receipt
    times are given), make the last one the new ``newest_ns`` (:data:`NEW_BASE`; the
    earlier ones stay refused or passed on as they were). A message that advances the
    stream ends the run. That bookkeeping is the only state a refused message changes.

    Args:
        window_ns: Largest distance from the newest stamp [ns].
        confirm: Consecutive consistent messages that make a new time base.
        what: Topic name for the messages.
        span_s: Receipt time the run must span [s].
    """

    def __init__(self, window_ns: int = STAMP_WINDOW_NS, confirm: int = NEW_TIME_BASE_MESSAGES,
                 what: str = 'stamp', span_s: float = NEW_TIME_BASE_SPAN_S):
        if window_ns <= 0 or confirm < 1 or not span_s >= 0.0:
            raise ValueError('window_ns must be > 0, confirm >= 1 and span_s >= 0')
        self.window_ns = int(window_ns)
        self.confirm = int(confirm)
        self.span_s = float(span_s)
        self.what = what
        self.newest_ns: int | None = None
        self.time_base_changes = 0
        self._run_last_ns: int | None = None
        self._run_length = 0
        self._run_first_s: float | None = None

    def reset(self) -> None:
        """Forget the stream: the next stamp is taken as its start."""
        self.newest_ns = None
        self._run_last_ns = None
        self._run_length = 0
        self._run_first_s = None

    @property
    def rewinding_ns(self) -> int | None:
        """The last stamp of the current run of candidates when the run went back in
        time (before the newest accepted stamp), else None."""
        last, newest = self._run_last_ns, self.newest_ns
        return last if last is not None and newest is not None and last < newest else None

    def adopt(self, stamp_ns: int) -> str:
        """Take ``stamp_ns`` as the newest stamp of a new time base (the caller knows it
        is one, e.g. every input of a node went back together); :data:`NEW_BASE`."""
        return self._adopt(int(stamp_ns))

    def _adopt(self, stamp_ns: int) -> str:
        """Take ``stamp_ns`` as the newest stamp of a new time base."""
        self.newest_ns = stamp_ns
        self._run_last_ns, self._run_length, self._run_first_s = None, 0, None
        self.time_base_changes += 1
        return NEW_BASE

    def admit(self, stamp_ns: int, received_s: float | None = None,
              new_publisher: bool = False) -> str:
        """Judge one stamp (of a message otherwise valid).

        Args:
            stamp_ns: The message's stamp [ns].
            received_s: When it was received (a monotonic clock) [s]; None: the run of a
                new time base needs no receipt span (offline use).
            new_publisher: The message is the first of a publisher that the stream did not
                have before: one that goes back in time is a new time base at once.

        Returns:
            :data:`ADVANCE`, :data:`BEHIND` or :data:`NEW_BASE`.

        Raises:
            MessageError: Too far from the stream, and not (yet) a new time base (reason
                ``'stamp_jump'``).
        """
        stamp_ns = int(stamp_ns)
        newest = self.newest_ns
        if newest is None:
            self.newest_ns = stamp_ns
            return ADVANCE
        offset = stamp_ns - newest
        if 0 < offset <= self.window_ns:
            self.newest_ns = stamp_ns
            self._run_last_ns, self._run_length, self._run_first_s = None, 0, None
            return ADVANCE
        if new_publisher and offset < 0:
            return self._adopt(stamp_ns)
        last = self._run_last_ns
        if last is not None and 0 < stamp_ns - last <= self.window_ns:
            self._run_length += 1
        else:
            self._run_length = 1
            self._run_first_s = received_s
        self._run_last_ns = stamp_ns
        spanned = (received_s is None or self._run_first_s is None
                   or received_s - self._run_first_s >= self.span_s)
        if self._run_length >= self.confirm and spanned:
            return self._adopt(stamp_ns)
        if offset <= 0 and -offset <= self.window_ns:
            return BEHIND
        raise MessageError(
            f'{self.what}: stamp {stamp_ns} ns is {offset / NS_PER_S:+.3f} s from the '
            f'newest accepted one (window +-{self.window_ns / NS_PER_S:g} s); a new time '
            f'base needs {self.confirm} consistent messages over {self.span_s:g} s',
            'stamp_jump')
