"""npp-policy as a script: `python nodes/npp_policy.py [--ros-args ...]` does what the npp-policy command does."""

import sys

from npp_ros_graph.nodes.policy import main

if __name__ == "__main__":
    sys.exit(main())
