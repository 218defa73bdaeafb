"""The tools around a run: npp-run (run.py), npp-monitor, npp-record (bag), npp-replay, npp-dashboard, and
npp-deploy-ctl (deploy_ctl), which drives npp-deploy's lifecycle, and npp-identify on a bag (identify).

May import: npp_ros_graph.transport, npp_ros_graph.runtime, npp_ros_graph.graph (and the npp_ros core); never a node.
"""
