"""npp-run as a script: `python nodes/npp_run.py [--ros-args ...]` does what the npp-run command does."""

import sys

from npp_ros_graph.tools.run import main

if __name__ == "__main__":
    sys.exit(main())
