"""The front door for Python users: learn a certified policy in process, and read a run folder back.

What ``npp-learn`` does, without a terminal: :func:`learn` builds the run exactly as the command does
(``npp_ros.run.setup``: the task's expert, L, config and loop) and runs Algorithm 1 to its certificate or its
budget; :func:`read_run` (npp_ros.run.read, the one reader the deployment gate uses too) opens any run folder
(made by ``npp-learn``, ``npp-run`` or ``npp-experiment``) and gives its data, its episode log, its certificate as
the typed record the loop resumes from, and the policy that certificate names. Both are exported by ``npp_ros``
itself.
"""

from __future__ import annotations

from pathlib import Path

from npp_ros.certificate.certifier import CheckedQuantity, StoppingRule
from npp_ros.policy.feedback import DEFAULT_POLICY, PolicyKind
from npp_ros.run.loop import RunResult
from npp_ros.run.read import Run, read_run
from npp_ros.run.setup import build_config, build_loop, resolve_lipschitz
from npp_ros.run.store import RUN_FILE
from npp_ros.tasks.registry import ExpertOptions, get_task

__all__ = ["Run", "learn", "read_run"]


def learn(
    task: str,
    seed: int = 0,
    *,
    run_dir: str | Path | None = None,
    epsilon: float | None = None,
    lipschitz: str | float | None = None,
    policy: PolicyKind = DEFAULT_POLICY,
    certify: CheckedQuantity | None = None,
    rule: StoppingRule | None = None,
    horizon: int | None = None,
    max_episodes: int = 1000,
    explore: float = 0.0,
) -> RunResult:
    """Algorithm 1 in process on ``task`` until its certificate or ``max_episodes``; None means the task's default.

    With ``run_dir`` the run is stored there (``run.sqlite``) and resumes from it when it exists, as
    ``npp-learn --run-dir`` does; without, nothing is written. Raises ValueError for settings the run refuses.
    """
    definition = get_task(task)
    steps = definition.default_horizon if horizon is None else horizon
    expert = definition.make_expert(seed, steps, ExpertOptions())
    store_path = None if run_dir is None else Path(run_dir) / RUN_FILE
    constant = resolve_lipschitz(task, lipschitz, expert, seed=seed, horizon=steps, run_file=store_path)
    config = build_config(
        task, seed, constant, definition.epsilon(epsilon), horizon=steps, certify=certify, rule=rule, policy=policy,
        explore=explore,
    )  # fmt: skip
    loop = build_loop(config, expert, store_path=store_path)
    try:
        return loop.run(max_episodes)
    finally:
        if loop.store is not None:
            loop.store.close()
