"""The four nodes, one Node subclass each: sim, expert, policy and the supervisor (a package of its own).

May import: npp_ros_graph.transport, npp_ros_graph.runtime (and the npp_ros core); never a tool or another node.
"""
