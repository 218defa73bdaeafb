"""npp-dashboard as a script: `python nodes/npp_dashboard.py ...` does what the npp-dashboard command does."""

import sys

from npp_ros_graph.tools.dashboard import main

if __name__ == "__main__":
    sys.exit(main())
