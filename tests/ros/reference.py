"""The uninterrupted in-process run a graph run must reproduce, shared by the graph, restart and fault tests."""

from __future__ import annotations

from typing import Any

from npp_ros.loop import NPPLoop, RunResult
from npp_ros.lqr import LQRExpert
from npp_ros.run_setup import build_config, build_loop, resolve_lipschitz
from npp_ros.storage import EpisodeRow

# Restart and fault tests certify on the paper's surrogate gap: its decisions do not depend on the
# policy's rollouts, so a killed sim or a restarted policy cannot change them and a faulted run
# must repeat the uninterrupted one decision for decision. (In the rollout and oracle modes a lost
# rollout is a failed check, which is sound but changes the run.)
ROLLOUT_FREE = {"certify": "surrogate", "rule": "paper"}


def uninterrupted_run(
    task_seed: int = 0,
    epsilon: float = 50.0,
    horizon: int = 1000,
    max_episodes: int = 400,
    certify: str = "rollout",
    rule: str = "sequential",
) -> tuple[NPPLoop, RunResult]:
    """lqr_2_1 with the analytic L through the same loop the supervisor runs (no store)."""
    expert = LQRExpert("lqr_2_1", task_seed, horizon=horizon)
    lipschitz = resolve_lipschitz("lqr_2_1", "analytic", expert)
    config = build_config("lqr_2_1", task_seed, lipschitz, epsilon, horizon=horizon, certify=certify, rule=rule)  # type: ignore[arg-type]
    loop = build_loop(config, expert)
    return loop, loop.run(max_episodes=max_episodes)


def decisions(rows: list[EpisodeRow]) -> list[tuple[Any, ...]]:
    """What Algorithm 1 decided per episode: the numbers a resumed or faulted run must repeat."""
    return [(r.initial_state, r.gap, r.oracle_called) for r in rows]
