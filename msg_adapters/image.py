"""sensor_msgs/Image <-> numpy (8-bit mono and colour encodings)."""
from __future__ import annotations

import numpy as np

from .errors import MessageError
from .message_classes import RCLPY, MessageKit
from .limits import (MAX_IMAGE_HEIGHT_PX, MAX_IMAGE_STEP_BYTES, MAX_IMAGE_WIDTH_PX,
                     MAX_MESSAGE_BYTES, MIN_IMAGE_SIDE_PX)
from .stamps import make_header, stamp_to_ns
from .wire import CAMERA_FRAME, IMAGE, header_dims

# Encoding -> channels. The camera pipeline (ORB on grey) takes 8-bit images only.
ENCODINGS = {'mono8': 1, 'bgr8': 3, 'rgb8': 3}


def check_image(msg, what: str = IMAGE) -> tuple[int, int, int]:
    """Check an Image message's header fields, before its pixels are touched.

    Returns:
        ``(height, width, channels)``.

    Raises:
        MessageError: An invalid stamp (``'stamp'``, checked first), unsupported
            encoding (``'encoding'``), empty image (``'empty'``),
            sides outside [:data:`.limits.MIN_IMAGE_SIDE_PX`,
            :data:`.limits.MAX_IMAGE_WIDTH_PX` x :data:`.limits.MAX_IMAGE_HEIGHT_PX`]
            (``'size'``), or a buffer that does not match ``height x step`` (``'size'``).
    """
    stamp_to_ns(msg.header.stamp, what)       # first: a refused frame is answered at it
    channels = ENCODINGS.get(msg.encoding)
    if channels is None:
        raise MessageError(f'{what}: encoding {msg.encoding!r} not supported (use '
                           f'{", ".join(ENCODINGS)})', 'encoding')
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h == 0 or w == 0:
        raise MessageError(f'{what}: empty image ({w}x{h})', 'empty')
    check_image_size(w, h, what)
    if step < w * channels:
        raise MessageError(f'{what}: step {step} < width {w} x {channels} channels', 'size')
    if step > MAX_IMAGE_STEP_BYTES:
        raise MessageError(f'{what}: step {step} bytes per row, at most '
                           f'{MAX_IMAGE_STEP_BYTES}', 'size')
    if len(msg.data) != h * step:
        raise MessageError(f'{what}: {len(msg.data)} data bytes, expected height x step = '
                           f'{h * step}', 'size')
    return h, w, channels


def check_image_size(width: int, height: int, what: str = IMAGE) -> None:
    """Refuse image sides outside the limits of :mod:`.limits` (reason ``'size'``)."""
    if not (MIN_IMAGE_SIDE_PX <= width <= MAX_IMAGE_WIDTH_PX
            and MIN_IMAGE_SIDE_PX <= height <= MAX_IMAGE_HEIGHT_PX):
        raise MessageError(f'{what}: image {width}x{height} px outside the accepted '
                           f'{MIN_IMAGE_SIDE_PX}..{MAX_IMAGE_WIDTH_PX} x '
                           f'{MIN_IMAGE_SIDE_PX}..{MAX_IMAGE_HEIGHT_PX} px', 'size')


def check_serialized_image(raw: bytes, what: str = IMAGE) -> None:
    """Refuse a CDR-serialised Image whose sides or size are beyond the limits, before it
    is decoded (an 8000 x 8000 bgr8 frame would be copied into 192 MB first); a zero side
    is left to :func:`check_image` (reason ``'empty'``).

    Raises:
        MessageError: See :func:`check_image_size`.
    """
    dims = header_dims(raw)
    if dims is not None and dims[0] and dims[1]:
        check_image_size(dims[1], dims[0], what)
    limit = MAX_IMAGE_HEIGHT_PX * MAX_IMAGE_STEP_BYTES + MAX_MESSAGE_BYTES
    if len(raw) > limit:
        raise MessageError(f'{what}: {len(raw)} bytes, at most {limit}', 'size')


def image_to_array(msg, what: str = IMAGE) -> tuple[np.ndarray, str]:
    """An Image message -> ``(array, encoding)``.

    The array is (H, W) for mono8 and (H, W, 3) for bgr8/rgb8, uint8, a view of the
    message buffer when rows are not padded (no copy).

    Raises:
        MessageError: See :func:`check_image`.
    """
    h, w, channels = check_image(msg, what)
    step = int(msg.step)
    buf = np.frombuffer(msg.data, dtype=np.uint8)
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
        kit: Message classes to build with (:mod:`.message_classes`).

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
