"""One run of Algorithm 1: its records, the loop, its set-up, the run file and its lock, evaluation, the held-out
check of a certificate (held_out: npp-learn's and npp-experiment's one), progress and exploration; and the robots
of a run's set one by one (per_robot: where in the set it fails, a per-robot claim).
Deploying a certified run on a robot is npp_ros.deployment's.

May import: npp_ros.policy, npp_ros.certificate, npp_ros.trajopt, npp_ros.tasks.
"""
