"""npp-deploy: one certified run's policy drives a robot; its helpers (settings, description, robot_check,
model_watch) get what they use.

node: the lifecycle node (its docstring says what it does) and main; settings: its parameters and the settings they
make; description: the robot's model as the robot publishes it, and the fingerprint the gate checks; robot_check:
configure's check at the robot identified from its own motion; model_watch: the model monitor of a run certified on
a set of robots.

May import: npp_ros_graph.transport, npp_ros_graph.runtime (and the npp_ros core, its deployment part too).
"""
