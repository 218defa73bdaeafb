"""npp_ros's own tasks: the lqr systems (lqr.py) and the dm_control swing-ups (pendulum, cartpole, acrobot).

Each module declares the task object the registry names (registry.py's REGISTRY); the swing-ups' plants share
tasks/suite_plant.py, and their experts one base (swingup.py).

May import what npp_ros.tasks may, and the contract beside it (task, success, uncertainty, rollout, suite_plant).
"""
