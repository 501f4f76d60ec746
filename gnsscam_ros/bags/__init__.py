"""rosbag2 bags: dataset -> bag converter, bag -> dataset reader, result-bag reading.

* :func:`convert_drive` (``gnsscam_convert``): a :class:`~gnsscam_ros.core.types.Drive`
  into a new MCAP (or sqlite3) bag with the input topics of design.md §3 and ground truth.
* :mod:`.read` (``read_drive``: the inverse; ``read_results``: the nodes' output topics
  ``pose``, ``fix``, ``particles``, ``integrity_risk`` for the evaluation). Import it
  explicitly: it parses with ``msg_adapters`` (ROS message packages), while the converter
  needs rosbags only.

The topic table, frames and field layouts are in :mod:`.schema`; errors in :mod:`.errors`.
"""
from .convert import ConvertSummary, convert_drive
from .errors import BagContentError, BagError, BagExistsError, BagReadError, BagTypeError

__all__ = ['BagContentError', 'BagError', 'BagExistsError', 'BagReadError', 'BagTypeError',
           'ConvertSummary', 'convert_drive']
