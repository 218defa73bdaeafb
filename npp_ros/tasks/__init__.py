"""The tasks: the registry, the generic rollout, the shared MuJoCo plant base, each plant and its expert.

May import: npp_ros.policy, npp_ros.certificate, npp_ros.trajopt.
"""
