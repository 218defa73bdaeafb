"""NPP with certificates, free of ROS: policy, certificate, trajopt, tasks, run, experiment, bench, cli.

The few things a Python user needs are exported here (see docs/tutorials/python.md)::

    import npp_ros
    result = npp_ros.learn("cartpole_swingup", seed=0, run_dir="runs/mine")
    run = npp_ros.read_run("runs/mine")
    print(run.certificate.summary(), run.policy.act(run.dataset.states[0]))

They load on first use, so ``import npp_ros.policy.dataset`` stays as light as it is. Each subpackage says
what it may import; tests/test_layering.py holds the whole table and checks it.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "learn": "npp_ros.run.api",
    "read_run": "npp_ros.run.api",
    "Run": "npp_ros.run.api",
    "get_task": "npp_ros.tasks.registry",
    "TASK_NAMES": "npp_ros.tasks.registry",
    "Certificate": "npp_ros.certificate.certifier",
    "NonparametricPolicy": "npp_ros.policy.bounds",
    "POLICY_KINDS": "npp_ros.policy.feedback",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'npp_ros' has no attribute {name!r}")
    return getattr(importlib.import_module(_EXPORTS[name]), name)


def __dir__() -> list[str]:
    return __all__
