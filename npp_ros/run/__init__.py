"""One run of Algorithm 1: its records, the loop, its set-up, the run file and its lock, evaluation, progress and
exploration; and the robots of a run's set one by one (per_robot: where in the set it fails, a per-robot claim).
Deploying a certified run on a robot is npp_ros.deployment's.

May import: npp_ros.policy, npp_ros.certificate, npp_ros.trajopt, npp_ros.tasks.
"""
