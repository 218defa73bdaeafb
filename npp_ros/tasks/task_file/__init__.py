"""The task-file format: a TOML file (a model, rho, a reward, an expert) to a Task, no Python.

loader.py makes the task (plant, expert, Task) from a file's definition; schema.py reads the file into that
definition, with the model's parts in model.py, the reward's terms in terms.py, the expert's cost in cost.py,
the success criterion in success.py, the set of robots in uncertainty.py, and every refusal's wording in
reader.py. docs/tutorials/own-task.md documents the format.

May import what npp_ros.tasks may, and the contract beside it; registry.py reaches it through sources.py.
"""
