"""How a node process runs (run_node, release, Mailbox, deadlines, /diagnostics); which reports viewers show.

May import: npp_ros_graph.transport (and the npp_ros core).
"""
