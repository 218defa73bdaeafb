"""npp-supervisor as a script: `python nodes/npp_supervisor.py [--ros-args ...]` is the npp-supervisor command."""

import sys

from npp_ros_graph.nodes.supervisor.node import main

if __name__ == "__main__":
    sys.exit(main())
