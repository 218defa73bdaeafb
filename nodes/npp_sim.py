"""npp-sim as a script: `python nodes/npp_sim.py [--ros-args ...]` does what the npp-sim command does."""

import sys

from npp_ros_graph.nodes.sim import main

if __name__ == "__main__":
    sys.exit(main())
