"""npp-robot-run: Algorithm 1 with a robot as the plant, over its ros2_control topics (node, the node; link, the
robot as the core's RobotLink: its reset service, one command per control period, its joint states back).

A robot node: may import the core (npp_ros, its deployment part too), npp_ros_graph.transport and
npp_ros_graph.runtime; never another node.
"""
