"""A swing-up certified through the graph with the feedback policy, equal to the in-process run bit for bit.

The cartpole's expert gives its iLQR gains with every answer; the policy node acts with them (the stored action
plus the gain times the wrapped state difference, clamped), in the same floating-point operations as the
in-process loop. The expert stops by convergence or its iteration cap (a generous time budget), so its answers
do not depend on the machine's speed.

A whole swing-up certification through the graph and a rehearsal on the real-time robot: a long run, in
`make test-long` (`make test` runs the feedback policy through the graph on lqr_2_1, test_replayed_run.py).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from reference import decisions

from npp_ros.run.setup import build_config, build_loop, resolve_lipschitz
from npp_ros.run.store import RunStore
from npp_ros.tasks.registry import ExpertOptions, get_task

pytestmark = pytest.mark.long

TASK = "cartpole_swingup"
HORIZON = 300
EPSILON = 20.0
LIPSCHITZ = 4300.0
MAX_EPISODES = 120
BUDGET = 120.0  # seconds per request: never reached, so iterations decide (deterministic)
ITERATIONS = 10


def test_the_cartpole_certifies_through_the_graph_with_the_feedback_policy(tmp_path: Path, ros_domain: int) -> None:
    run_dir = tmp_path / "graph"
    command = [
        sys.executable, "-m", "npp_ros_graph.tools.run", "--task", TASK, "--horizon", str(HORIZON),
        "--epsilon", str(EPSILON), "--lipschitz", str(LIPSCHITZ), "--policy", "feedback",
        "--max-episodes", str(MAX_EPISODES), "--run-dir", str(run_dir), "--time-budget", str(BUDGET),
        "--max-iterations", str(ITERATIONS),
    ]  # fmt: skip
    run = subprocess.run(command, capture_output=True, text=True, timeout=900)
    logs = "\n".join(f"== {p.name}\n{p.read_text()[-3000:]}" for p in sorted((run_dir / "logs").glob("*.log")))
    assert run.returncode == 0, f"{run.stdout[-2000:]}\n{run.stderr[-3000:]}\n{logs}"
    assert "acting with its experts' feedback gains" in run.stdout + run.stderr
    with RunStore.open(run_dir / "run.sqlite") as store:
        graph_data = store.load_dataset()
        graph_rows = store.episodes()
        assert store.metadata.policy == "feedback" and store.certificate() is not None
    assert graph_data.trajectories_with_gains == graph_data.num_trajectories > 0

    task = get_task(TASK)
    expert = task.make_expert(0, HORIZON, ExpertOptions(time_budget=BUDGET, max_iterations=ITERATIONS))
    lipschitz = resolve_lipschitz(TASK, LIPSCHITZ, expert)
    config = build_config(TASK, 0, lipschitz, EPSILON, horizon=HORIZON, policy="feedback")
    loop = build_loop(config, expert)
    local = loop.run(max_episodes=MAX_EPISODES)
    assert local.certified and len(graph_rows) == local.episodes
    assert decisions(graph_rows) == decisions(local.rows)
    assert [(r.checked_gap, r.policy_return) for r in graph_rows] == [
        (r.checked_gap, r.policy_return) for r in local.rows
    ]
    for name in ("states", "actions", "values", "gains"):
        np.testing.assert_array_equal(getattr(graph_data, name), getattr(loop.dataset, name))

    # The certified feedback policy on the real-time robot, through npp-deploy's gate.
    trial = tmp_path / "trial"
    command = [sys.executable, "-m", "npp_ros_graph.bench.trial", str(run_dir), "--episodes", "2", "--out", str(trial)]
    subprocess.run(command, check=True, timeout=600)
    out = json.loads((trial / "trial.json").read_text())
    assert out["policy"] == "feedback" and len(out["episodes"]) == 2
    for episode in out["episodes"]:
        assert episode["replay_mismatches"] == 0, episode  # the robot moved exactly as the model does
        assert episode["first_command_answers_s0"], episode
        if episode["fresh_command_share"] == 1.0:  # no command missed its period: the in-process episode exactly
            assert episode["robot_return"] == episode["in_process_return"], episode
