"""rclpy endpoints for bag topics, shared by the replay (publishers) and the recorder
(subscriptions): the rclpy class of a bag's message type, and no QoS event handlers.
"""
from __future__ import annotations

from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks

from msg_adapters import MessageError, message_class

from ..bags.errors import BagTypeError

# An executor wakes for every message of these endpoints and rclpy rebuilds its wait set
# at each wake, at a cost that grows with every event handler: the replay's and the
# recorder's endpoints are reliable, compatible with any peer, and need none.
NO_PUB_EVENTS = PublisherEventCallbacks(use_default_callbacks=False)
NO_SUB_EVENTS = SubscriptionEventCallbacks(use_default_callbacks=False)


def ros_message_class(msgtype: str):
    """The rclpy message class of a bag's ``pkg/msg/Type``.

    Raises:
        BagTypeError: The package or type is not installed.
    """
    try:
        return message_class(msgtype)
    except MessageError as err:
        raise BagTypeError(str(err)) from err
