"""The ROS loop benchmark (npp-bench-ros): the sim <-> policy lockstep against a bare ping-pong; and
npp-deploy's latency and watchdog (npp-bench-deploy, deploy).

May import: npp_ros_graph.transport, npp_ros_graph.runtime, npp_ros_graph.graph and the core's bench report.
"""
