"""The tasks: what a task is, the registry and its other sources (plug-ins, task files), each plant and its expert.

The contract every task fills in is task.py; registry.py is the one lookup, over npp_ros's own tasks,
plug-in packages (sources.py) and task files (task_file*.py); then the generic rollout, the shared
MuJoCo plant base and each task's own module, and the check of an expert's answer against the task's plant
and the experts' value convention (answer_check.py). May import: npp_ros.policy, npp_ros.certificate,
npp_ros.trajopt.
"""
