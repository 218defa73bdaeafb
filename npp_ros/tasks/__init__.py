"""The tasks, by kind: the contract, npp_ros's own tasks, and the task-file format.

- The contract every task fills in: task.py (the Task and its plant and expert protocols), success.py (a
  success criterion), uncertainty.py (a set of robots), rollout.py (the one rollout every part uses).
- The one lookup: registry.py, over npp_ros's own tasks, plug-in packages and task files (sources.py).
- suite_plant.py: the MuJoCo plant base of the swing-ups and of every task file's plant.
- builtin/: npp_ros's own tasks (the lqr systems; the dm_control swing-ups).
- task_file/: the task-file format, a file to a Task (loader.py) and its parts (schema, model, reward terms, cost,
  success, set of robots).
- expert_pool.py: a task's experts in worker processes (the expert node and npp-bench).

May import: npp_ros.policy, npp_ros.certificate, npp_ros.trajopt.
"""
