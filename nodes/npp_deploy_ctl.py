"""npp-deploy-ctl as a script: `python nodes/npp_deploy_ctl.py COMMAND` does what the npp-deploy-ctl command does."""

import sys

from npp_ros_graph.tools.deploy_ctl import main

if __name__ == "__main__":
    sys.exit(main())
