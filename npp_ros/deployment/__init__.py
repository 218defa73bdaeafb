"""Deploying a certified run on a robot, without ROS: the gate that checks a run file's certificate (gate, over
npp_ros.run.read), the robot's model fingerprint (robot_model), its joints (joints), what it is commanded (commands),
how far its states lie from the data (coverage), the watchdog (timing), signed runs (signing), and what
npp-deploy does and did, as one typed record (state). npp-deploy, npp-robot and npp-sign call these.

May import: npp_ros.policy, npp_ros.certificate, npp_ros.trajopt, npp_ros.tasks, npp_ros.run.
"""
