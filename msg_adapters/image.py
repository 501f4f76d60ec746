"""sensor_msgs/Image <-> numpy (8-bit mono and colour encodings)."""
from __future__ import annotations

import numpy as np

from .errors import MessageError
from .kit import RCLPY, MessageKit
from .stamps import make_header
from .wire import CAMERA_FRAME, IMAGE

# Encoding -> channels. The camera pipeline (ORB on grey) takes 8-bit images only.
ENCODINGS = {'mono8': 1, 'bgr8': 3, 'rgb8': 3}


def image_to_array(msg, what: str = IMAGE) -> tuple[np.ndarray, str]:
    """An Image message -> ``(array, encoding)``.

    The array is (H, W) for mono8 and (H, W, 3) for bgr8/rgb8, uint8, a view of the
    message buffer when rows are not padded (no copy).

    Raises:
        MessageError: Unsupported encoding, empty image, or a buffer that does not match
            ``height x step``.
    """
    channels = ENCODINGS.get(msg.encoding)
    if channels is None:
        raise MessageError(f'{what}: encoding {msg.encoding!r} not supported (use '
                           f'{", ".join(ENCODINGS)})', 'encoding')
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h == 0 or w == 0:
        raise MessageError(f'{what}: empty image ({w}x{h})', 'empty')
    if step < w * channels:
        raise MessageError(f'{what}: step {step} < width {w} x {channels} channels', 'size')
    buf = np.frombuffer(msg.data, dtype=np.uint8)
    if buf.size != h * step:
        raise MessageError(f'{what}: {buf.size} data bytes, expected height x step = '
                           f'{h * step}', 'size')
    rows = buf.reshape(h, step)[:, :w * channels]
    shape = (h, w) if channels == 1 else (h, w, channels)
    return rows.reshape(shape), msg.encoding


def array_to_image(array: np.ndarray, stamp_ns: int, encoding: str | None = None,
                   frame_id: str = CAMERA_FRAME, kit: MessageKit = RCLPY):
    """A uint8 (H, W) or (H, W, 3) array -> Image message.

    Args:
        array: The image.
        stamp_ns: Header stamp [ns].
        encoding: ``mono8``, ``bgr8`` or ``rgb8`` (default: mono8 for 2-D, bgr8 for 3-D).
        frame_id: Camera frame.
        kit: Message classes to build with (:mod:`.kit`).

    Raises:
        MessageError: Not uint8, empty, or a shape that does not fit the encoding.
    """
    array = np.asarray(array)
    if array.dtype != np.uint8:
        raise MessageError(f'image dtype {array.dtype}, expected uint8', 'encoding')
    if encoding is None:
        encoding = 'mono8' if array.ndim == 2 else 'bgr8'
    channels = ENCODINGS.get(encoding)
    if channels is None:
        raise MessageError(f'encoding {encoding!r} not supported', 'encoding')
    want_ndim = 2 if channels == 1 else 3
    if array.ndim != want_ndim or (channels > 1 and array.shape[2] != channels):
        raise MessageError(f'shape {array.shape} does not fit {encoding}', 'encoding')
    if array.size == 0:
        raise MessageError('empty image', 'empty')
    h, w = array.shape[:2]
    return kit['sensor_msgs/msg/Image'](
        header=make_header(stamp_ns, frame_id, kit), height=h, width=w, encoding=encoding,
        is_bigendian=0, step=w * channels, data=kit.octets(np.ascontiguousarray(array)))
