"""The command lines npp-learn, npp-experiment, npp-bench, npp-sign and npp-identify: options, progress, exit codes.

May import: every other part of npp_ros (never the ROS package).
"""
