"""The uninterrupted in-process run a graph run must reproduce, shared by the graph, restart and fault tests."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from npp_ros.policy.dataset import Dataset
from npp_ros.policy.feedback import DEFAULT_POLICY
from npp_ros.run.loop import NPPLoop, RunResult
from npp_ros.run.records import EpisodeRow
from npp_ros.run.setup import build_config, build_loop, resolve_lipschitz
from npp_ros.run.store import RunStore
from npp_ros.tasks.builtin.lqr import LQRExpert

# Restart and fault tests certify on the paper's surrogate gap: its decisions do not depend on the
# policy's rollouts, so a killed sim or a restarted policy cannot change them and a faulted run
# must repeat the uninterrupted one decision for decision. (In the rollout and oracle modes a lost
# rollout is a failed check, which is sound but changes the run.)
ROLLOUT_FREE = {"certify": "surrogate", "rule": "paper", "policy": "open-loop"}


def uninterrupted_run(
    task_seed: int = 0,
    epsilon: float = 50.0,
    horizon: int = 1000,
    max_episodes: int = 400,
    certify: str = "rollout",
    rule: str = "sequential",
    policy: str = DEFAULT_POLICY,
) -> tuple[NPPLoop, RunResult]:
    """lqr_2_1 with the analytic L through the same loop the supervisor runs (no store)."""
    expert = LQRExpert("lqr_2_1", task_seed, horizon=horizon)
    lipschitz = resolve_lipschitz("lqr_2_1", "analytic", expert)
    config = build_config(
        "lqr_2_1",
        task_seed,
        lipschitz,
        epsilon,
        horizon=horizon,
        certify=certify,
        rule=rule,
        policy=policy,  # type: ignore[arg-type]
    )
    loop = build_loop(config, expert)
    return loop, loop.run(max_episodes=max_episodes)


def decisions(rows: list[EpisodeRow]) -> list[tuple[Any, ...]]:
    """What Algorithm 1 decided per episode: the numbers a resumed or faulted run must repeat."""
    return [(r.initial_state, r.gap, r.oracle_called) for r in rows]


def assert_stored_run_is_uninterrupted(
    run_file: Path, horizon: int, max_episodes: int
) -> tuple[Dataset, list[EpisodeRow], NPPLoop]:
    """A graph run on the surrogate check (ROLLOUT_FREE) that was disturbed ends exactly as the in-process run:
    the same certificate, decisions and dataset. Returns the stored dataset and rows, and the in-process loop."""
    time.sleep(0.5)  # the supervisor's worker closes the run file after certifying
    local_loop, local = uninterrupted_run(horizon=horizon, max_episodes=max_episodes, **ROLLOUT_FREE)
    data, rows = assert_same_run(run_file, local_loop, local, returns=False)
    return data, rows, local_loop


def assert_same_run(
    run_file: Path, local_loop: NPPLoop, local: RunResult, returns: bool = True
) -> tuple[Dataset, list[EpisodeRow]]:
    """The run file holds exactly the in-process run: its certificate, every episode's decision (and, with
    `returns`, the policy's return and the checked quantity, bit for bit), and its dataset."""
    with RunStore.open(run_file) as store:
        data, rows, certificate = store.load_dataset(), store.episodes(), store.certificate()
    assert local.certificate is not None and certificate == local.certificate.record()
    assert decisions(rows) == decisions(local.rows)
    if returns:
        assert [(r.policy_return, r.checked_gap) for r in rows] == [
            (r.policy_return, r.checked_gap) for r in local.rows
        ]
    np.testing.assert_array_equal(data.states, local_loop.dataset.states)
    np.testing.assert_array_equal(data.actions, local_loop.dataset.actions)
    np.testing.assert_array_equal(data.values, local_loop.dataset.values)
    return data, rows
