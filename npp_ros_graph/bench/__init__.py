"""The ROS loop benchmark (npp-bench-ros): the sim <-> policy lockstep against a bare ping-pong; npp-deploy's
latency and watchdog (npp-bench-deploy, deploy); and the rehearsal of a certified run on the real-time robot
(npp-trial, trial: its node and npp-robot's start in trial_nodes, an episode judged against the policy in process
in trial_judge, the report in trial_report, --outside in trial_outside).

May import: npp_ros_graph.transport, npp_ros_graph.runtime, npp_ros_graph.graph and the core's bench report.
"""
