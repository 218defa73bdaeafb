"""The path policy through the graph: the policy node starts each episode's path afresh on the sim's first state
of the episode, so the run ends exactly as the in-process run does (every check, every return)."""

from __future__ import annotations

from pathlib import Path

import pytest
from graph import npp_run_to_its_end
from reference import decisions

from npp_ros.run.read import read_run
from npp_ros.run.setup import build_config, build_loop, resolve_lipschitz
from npp_ros.tasks.registry import get_task

pytestmark = pytest.mark.slow

TASK, HORIZON, EPSILON, MAX_EPISODES = "lqr_2_1", 100, 2.0, 40


def test_the_path_policy_through_the_graph_gives_the_in_process_run(tmp_path: Path, ros_domain: int) -> None:
    run_dir = tmp_path / "graph"
    options = ["--task", TASK, "--horizon", str(HORIZON), "--epsilon", str(EPSILON), "--lipschitz", "analytic",
               "--certify", "oracle", "--policy", "path"]  # fmt: skip
    npp_run_to_its_end(options, run_dir, MAX_EPISODES)
    graph = read_run(run_dir)
    assert graph.metadata.policy == "path" and graph.episodes

    expert = get_task(TASK).make_expert(0, HORIZON)
    config = build_config(
        TASK, 0, resolve_lipschitz(TASK, "analytic", expert), EPSILON, horizon=HORIZON, certify="oracle",
        policy="path",
    )  # fmt: skip
    local = build_loop(config, expert).run(max_episodes=MAX_EPISODES)
    assert decisions(graph.episodes) == decisions(local.rows)
    assert [(r.checked_gap, r.policy_return) for r in graph.episodes] == [
        (r.checked_gap, r.policy_return) for r in local.rows
    ]
