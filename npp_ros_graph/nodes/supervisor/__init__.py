"""The supervisor: Algorithm 1 over the graph; its helpers (expert, rollouts, reporter) get what they use.

May import: npp_ros_graph.transport, npp_ros_graph.runtime (and the npp_ros core).
"""
