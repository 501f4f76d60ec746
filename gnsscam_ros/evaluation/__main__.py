"""``python -m gnsscam_ros.evaluation`` is ``gnsscam_eval``."""
import sys

from .cli import main

sys.exit(main())
