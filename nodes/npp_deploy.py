"""npp-deploy as a script: `python nodes/npp_deploy.py [--ros-args ...]` does what the npp-deploy command does."""

import sys

from npp_ros_graph.nodes.deploy.node import main

if __name__ == "__main__":
    sys.exit(main())
