"""A run that chooses its policy's own L (policy_lipschitz select) through the graph: the supervisor chooses at each
doubling of the policy's data, the policy node acts by each new L with the trajectory that brought it, and the run
ends exactly as the in-process run does (its checks, its returns, its choices)."""

from __future__ import annotations

from pathlib import Path

import pytest
from graph import npp_run_to_its_end
from reference import decisions

from npp_ros.run.read import read_run
from npp_ros.run.request import RunRequest, resolve_run
from npp_ros.run.setup import build_loop

pytestmark = [pytest.mark.slow, pytest.mark.long]  # a whole graph run: make test-long

# lqr_6_2 at H = 300, oracle checks, the open-loop policy: the choice at 8 trajectories moves the policy to 10 times
# the claim's L (a higher mean return from the held-out starts; the task states no success criterion), and the one
# at 16 back to the claim's: the policy node follows both.
TASK, HORIZON, EPSILON, MAX_EPISODES = "lqr_6_2", 300, 5.0, 60


def test_a_selected_policy_l_through_the_graph_gives_the_in_process_run(tmp_path: Path, ros_domain: int) -> None:
    run_dir = tmp_path / "graph"
    options = ["--task", TASK, "--horizon", str(HORIZON), "--epsilon", str(EPSILON), "--lipschitz", "analytic",
               "--certify", "oracle", "--policy", "open-loop", "--policy-lipschitz", "select"]  # fmt: skip
    npp_run_to_its_end(options, run_dir, MAX_EPISODES)
    graph = read_run(run_dir)
    assert graph.metadata.policy_lipschitz == "select" and graph.lipschitz_choices

    request = RunRequest(
        task=TASK, horizon=HORIZON, epsilon=EPSILON, lipschitz="analytic", certify="oracle", policy="open-loop",
        policy_lipschitz="select",
    )  # fmt: skip
    resolved = resolve_run(request)
    loop = build_loop(resolved.config, resolved.expert)
    local = loop.run(max_episodes=MAX_EPISODES)
    assert decisions(graph.episodes) == decisions(local.rows)
    assert [(r.checked_gap, r.policy_return) for r in graph.episodes] == [
        (r.checked_gap, r.policy_return) for r in local.rows
    ]
    assert {k: c.value for k, c in graph.lipschitz_choices.items()} == {k: c.value for k, c in loop.choices.items()}
    chosen = {c.value for c in graph.lipschitz_choices.values()}
    assert chosen != {graph.spec.lipschitz.value}, "no choice moved the policy off the claim's L: nothing was tested"
    policy_log = "".join(p.read_text() for p in (run_dir / "logs").glob("*policy*.log"))
    assert "the run's policy now acts by L =" in policy_log
