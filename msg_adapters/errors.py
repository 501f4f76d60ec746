"""The one exception of msg_adapters."""
from __future__ import annotations


class MessageError(ValueError):
    """A ROS message cannot be converted: wrong fields or types, NaN where not allowed,
    empty or wrongly encoded image, bad frame.

    Attributes:
        reason: Short machine-readable cause (``'fields'``, ``'non_finite'``,
            ``'empty'``, ``'encoding'``, ``'size'``, ``'frame'``, ``'stamp'``, ``'type'``,
            ``'value'``),
            used by the nodes as the key of their rejection counters.
    """

    def __init__(self, message: str, reason: str = 'value'):
        super().__init__(message)
        self.reason = reason
