"""npp-expert as a script: `python nodes/npp_expert.py [--ros-args ...]` does what the npp-expert command does."""

import sys

from npp_ros_graph.nodes.expert import main

if __name__ == "__main__":
    sys.exit(main())
