"""NPP with certificates, free of ROS: policy, certificate, trajopt, tasks, run, experiment, bench, cli.

The few things a Python user needs are exported here (see docs/tutorials/python.md)::

    import npp_ros
    result = npp_ros.learn("cartpole_swingup", seed=0, run_dir="runs/mine")
    run = npp_ros.read_run("runs/mine")
    print(run.certificate.summary(), run.policy.controller()(run.dataset.states[0]))

They load on first use, so ``import npp_ros.policy.dataset`` stays as light as it is; the imports under
TYPE_CHECKING name them for type checkers and for tests/test_layering.py, which checks them against the
table of what each part may import and against ``_EXPORTS``.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # `X as X`: re-exported
    from npp_ros.certificate.certifier import Certificate as Certificate
    from npp_ros.policy.bounds import NonparametricPolicy as NonparametricPolicy
    from npp_ros.policy.feedback import POLICY_KINDS as POLICY_KINDS
    from npp_ros.run.api import Run as Run
    from npp_ros.run.api import RunRequest as RunRequest
    from npp_ros.run.api import learn as learn
    from npp_ros.run.api import read_run as read_run
    from npp_ros.tasks.registry import TASK_NAMES as TASK_NAMES
    from npp_ros.tasks.registry import get_task as get_task
    from npp_ros.tasks.registry import task_names as task_names
    from npp_ros.tasks.rollout import rollout as rollout

_EXPORTS = {
    "learn": "npp_ros.run.api",
    "read_run": "npp_ros.run.api",
    "Run": "npp_ros.run.api",
    "RunRequest": "npp_ros.run.api",
    "get_task": "npp_ros.tasks.registry",
    "TASK_NAMES": "npp_ros.tasks.registry",
    "task_names": "npp_ros.tasks.registry",
    "Certificate": "npp_ros.certificate.certifier",
    "NonparametricPolicy": "npp_ros.policy.bounds",
    "POLICY_KINDS": "npp_ros.policy.feedback",
    "rollout": "npp_ros.tasks.rollout",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'npp_ros' has no attribute {name!r}")
    return getattr(importlib.import_module(_EXPORTS[name]), name)


def __dir__() -> list[str]:
    return __all__
