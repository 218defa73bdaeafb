"""How a node process runs: run_node and release, the Mailbox, service calls with deadlines, /diagnostics.

May import: npp_ros_graph.transport (and the npp_ros core).
"""
