"""The command lines npp-learn, npp-experiment, npp-bench and npp-sign: options, progress lines, exit codes.

May import: every other part of npp_ros (never the ROS package).
"""
