"""The four nodes, one Node subclass each: sim, expert, policy and the supervisor (a package of its own); and
npp-deploy (deploy, a package of its own too), which runs a certified run's policy on a robot, with npp-robot (robot)
to test it against.

May import: npp_ros_graph.transport, npp_ros_graph.runtime (and the npp_ros core); never a tool or another node.
"""
