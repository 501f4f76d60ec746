"""rosbag2 bags: dataset -> bag converter, bag -> dataset reader, result-bag reading.

* :func:`convert_drive` (``gnsscam_convert``): a :class:`~gnsscam_ros.core.types.Drive`
  into a new MCAP (or sqlite3) bag with the input topics (``msg_adapters.wire``) and ground truth.
* :mod:`.read` (``read_drive``: the inverse; ``read_results``: the nodes' output topics
  ``pose``, ``fix``, ``particles``, ``integrity_risk`` for the evaluation).

Both build and parse messages with the ``msg_adapters`` functions the nodes use (rosbags
dataclasses in place of rclpy messages; no rclpy, no ROS graph). Topic and frame names and
point layouts are the wire contract's (``msg_adapters.wire``); what a bag holds, the types
and QoS are in :mod:`.schema`; errors in :mod:`.errors`.
"""
from .convert import ConvertSummary, convert_drive
from .errors import BagContentError, BagError, BagExistsError, BagReadError, BagTypeError

__all__ = ['BagContentError', 'BagError', 'BagExistsError', 'BagReadError', 'BagTypeError',
           'ConvertSummary', 'convert_drive']
