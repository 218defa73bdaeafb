"""npp-robot as a script: `python nodes/npp_robot.py [--ros-args ...]` does what the npp-robot command does."""

import sys

from npp_ros_graph.nodes.robot import main

if __name__ == "__main__":
    sys.exit(main())
