"""One run of Algorithm 1: its records, the loop, its set-up, the run file and its lock, evaluation, progress,
and the gate and safety checks for deploying a run on a robot (deploy).

May import: npp_ros.policy, npp_ros.certificate, npp_ros.trajopt, npp_ros.tasks.
"""
