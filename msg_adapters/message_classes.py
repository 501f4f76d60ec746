"""The message classes the writers build: rclpy's, or a rosbags typestore's.

The writers of this package that the bag converter shares with the nodes
(:func:`~.pointcloud.gnss_epoch_to_pointcloud2`, :func:`~.image.array_to_image`,
:func:`~.motion.sample_to_imu`, :func:`~.motion.sample_to_twist`,
:func:`~.geometry.fix_to_navsatfix`, :func:`~.geometry.pose_stamped`) take a
:class:`MessageKit`: :data:`RCLPY` (the default) builds rclpy messages for publishing;
``gnsscam_ros.bags.schema.rosbags_kit()`` builds the dataclasses of the rosbags typestore
that the converter serialises, with no rclpy involved. One writer per layout, so a bag
holds exactly what a node would publish.

Both kinds of class take every field as a keyword. They differ in two ways, which the
writers respect: rosbags fields have no defaults (the writers give every field), and
numeric arrays: rosbags wants numpy arrays, rclpy takes them for fixed-size float arrays
but copies a ``uint8[]`` from ``bytes`` without a Python loop (:meth:`MessageKit.octets`).
"""
from __future__ import annotations

import importlib
from typing import Callable, Mapping

import numpy as np

from .errors import MessageError


def message_class(msgtype: str):
    """The rclpy message class of ``pkg/msg/Type``.

    Raises:
        MessageError: The package or type is not installed (reason ``'type'``).
    """
    try:
        pkg, kind, name = msgtype.split('/')
        return getattr(importlib.import_module(f'{pkg}.{kind}'), name)
    except (ValueError, ImportError, AttributeError) as err:
        raise MessageError(f'message type {msgtype} is not available to rclpy: {err}',
                           'type') from err


class _RclpyClasses(dict):
    """``{'pkg/msg/Type': rclpy class}``, imported on first use."""

    def __missing__(self, msgtype: str):
        cls = self[msgtype] = message_class(msgtype)
        return cls


class MessageKit:
    """Message classes by type name, and how a ``uint8[]`` field takes its bytes.

    Args:
        classes: ``{'pkg/msg/Type': class}`` (looked up when a writer needs the class).
        octets: A C-contiguous numpy array -> the value of a ``uint8[]`` field holding
            its bytes.
        name: For messages.
    """

    def __init__(self, classes: Mapping[str, type], octets: Callable[[np.ndarray], object],
                 name: str):
        self._classes = classes
        self.octets = octets
        self.name = name

    def __getitem__(self, msgtype: str) -> type:
        return self._classes[msgtype]

    def __repr__(self) -> str:
        return f'MessageKit({self.name})'


def _rclpy_octets(array: np.ndarray) -> bytes:
    # bytes: rclpy copies them into its array.array in one go; a numpy array would be
    # converted element by element (~15 ms per VGA frame).
    return array.tobytes()


def _numpy_octets(array: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(array).reshape(-1).view(np.uint8)


#: The rclpy message classes (for publishing).
RCLPY = MessageKit(_RclpyClasses(), _rclpy_octets, 'rclpy')


def numpy_kit(classes: Mapping[str, type], name: str) -> MessageKit:
    """A kit of dataclasses that take numpy arrays for every numeric array field (the
    rosbags typestores)."""
    return MessageKit(classes, _numpy_octets, name)
