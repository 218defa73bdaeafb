"""npp-monitor as a script: `python nodes/npp_monitor.py [--ros-args ...]` does what the npp-monitor command does."""

import sys

from npp_ros_graph.tools.monitor import main

if __name__ == "__main__":
    sys.exit(main())
