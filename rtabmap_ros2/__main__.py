"""``python3 -m rtabmap_ros2 COMMAND ...``: the ``rtabmap-ros2`` command line without relying on PATH."""

import sys

from rtabmap_ros2.cli.cli import main

sys.exit(main())
