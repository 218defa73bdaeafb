"""npp-replay as a script: `python nodes/npp_replay.py ...` does what the npp-replay command does."""

import sys

from npp_ros_graph.tools.replay import main

if __name__ == "__main__":
    sys.exit(main())
