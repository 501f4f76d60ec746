"""Exceptions of the vision package; messages always name the offending file."""
from __future__ import annotations


class VisionError(Exception):
    """Base class of every error raised by ``gnsscam_ros.vision``.

    The message is kept on one line (``gnsscam_mapdb`` prints it as its one error line;
    the OpenCV, numpy and zipfile errors it may quote can span several).
    """

    def __init__(self, message='', *args):
        super().__init__(' '.join(str(message).split()), *args)


class ImageError(VisionError):
    """An image is missing, cannot be decoded or has an unsupported layout."""


class MapDatabaseError(VisionError):
    """A map database, its positions CSV or its image set cannot be built or loaded."""


class MapDatabaseOutputError(MapDatabaseError):
    """A map database or result file cannot be written, or exists and may not be replaced.

    A subclass of :class:`MapDatabaseError` so that existing handlers still catch it; the
    command line tells it apart (exit code 4, not 3).
    """
