"""The front door for Python users: learn a certified policy in process, and read a run folder back.

What ``npp-learn`` does, without a terminal: :func:`learn` takes the same settings (a
:class:`~npp_ros.run.request.RunRequest` or its fields), builds the run exactly as the command does
(``npp_ros.run.request.resolve_run``: the task's expert, L and config; ``npp_ros.run.setup``: the loop) and runs
Algorithm 1 to its certificate or its budget; :func:`read_run` (npp_ros.run.read, the one reader the deployment
gate uses too) opens any run folder (made by ``npp-learn``, ``npp-run`` or ``npp-experiment``) and gives its data,
its episode log, its certificate as the typed record the loop resumes from, and the policy that certificate names.
Both are exported by ``npp_ros`` itself, with ``RunRequest``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from npp_ros.run.loop import RunResult
from npp_ros.run.read import Run, read_run
from npp_ros.run.request import RunRequest, resolve_run
from npp_ros.run.setup import build_loop
from npp_ros.run.store import RUN_FILE

__all__ = ["Run", "RunRequest", "learn", "read_run"]


def learn(
    task: str | RunRequest, seed: int | None = None, *, run_dir: str | Path | None = None, **settings: Any
) -> RunResult:
    """Algorithm 1 in process on ``task`` until its certificate or ``max_episodes``; None means the task's default.

    ``task`` is a task's name or a whole :class:`RunRequest`; ``settings`` are the request's fields (epsilon,
    lipschitz, policy, certify, rule, condition, p, delta, horizon, max_episodes, the expert's options...: see
    ``npp-learn --help``), over it. An unknown one is a TypeError. With ``run_dir`` the run is stored there
    (``run.sqlite``) and resumes from it when it exists, as ``npp-learn --run-dir`` does; without, nothing is
    written. Raises ValueError for settings the run refuses.
    """
    base = task if isinstance(task, RunRequest) else RunRequest(task=task)
    request = RunRequest.of(base, **({} if seed is None else {"seed": seed}), **settings)
    store_path = None if run_dir is None else Path(run_dir) / RUN_FILE
    run = resolve_run(request, run_file=store_path)
    loop = build_loop(run.config, run.expert, store_path=store_path)
    try:
        return loop.run(request.max_episodes)
    finally:
        if loop.store is not None:
            loop.store.close()
