"""The four-node graph described once (roles, commands, parameters), for npp-run and the tests.

May import: npp_ros_graph.transport (and the npp_ros core); never a node or a tool.
"""
