"""npp-record as a script: `python nodes/npp_record.py ...` does what the npp-record command does."""

import sys

from npp_ros_graph.tools.record import main

if __name__ == "__main__":
    sys.exit(main())
