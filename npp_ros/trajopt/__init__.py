"""The trajectory optimizer: MuJoCo dynamics, box-constrained iLQR over them, and the optimizing expert.

May import: npp_ros.policy, npp_ros.certificate (value conventions).
"""
