"""The trajectory optimizer: box-constrained iLQR over MuJoCo dynamics and its compiled kernels.

May import: npp_ros.policy, npp_ros.certificate (value conventions).
"""
