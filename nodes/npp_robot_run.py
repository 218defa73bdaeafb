"""npp-robot-run as a script: `python nodes/npp_robot_run.py [--ros-args ...]` is the npp-robot-run command."""

import sys

from npp_ros_graph.nodes.robot_run.node import main

if __name__ == "__main__":
    sys.exit(main())
