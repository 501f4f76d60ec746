"""Exceptions of :mod:`gnsscam_ros.bags`.

Every error names the bag (and the topic when one is at fault) in its message, so a user
sees what to fix without a traceback. The CLI maps the classes to exit codes.
"""
from __future__ import annotations

from pathlib import Path


class BagError(Exception):
    """A bag could not be written or read.

    Attributes:
        path: The bag at fault (or None).
        topic: The topic at fault (or None).
    """

    def __init__(self, message: str, path: str | Path | None = None,
                 topic: str | None = None):
        # One line: the tools print the message as their one error line, and the errors
        # of rosbags, YAML and sqlite they quote may span several.
        super().__init__(' '.join(str(message).split()))
        self.path = None if path is None else Path(path)
        self.topic = topic


class BagExistsError(BagError, FileExistsError):
    """The output path exists; a converter never overwrites anything."""


class BagReadError(BagError):
    """The bag is missing, unreadable, truncated or corrupt, or a message does not decode."""


class BagTypeError(BagError):
    """A topic carries a message type other than the expected one, or one not known to the
    typestore."""


class BagContentError(BagError):
    """The bag decodes but its content does not fit: a required topic is missing, a frame
    or field layout is wrong, or the data cannot be converted."""
