"""Model uncertainty through the graph: each episode's robot travels with the reset and the expert request, and the
run equals the in-process one, robot for robot and return for return.

The sim runs each episode on the robot its reset names (the model scaled, the command delayed as rollout() delays
it), the expert plans on the robot its request names, and the supervisor checks each answer on its own plant made
into that robot. The expert stops by convergence or its iteration cap (a generous time budget), so the numbers do not
depend on the machine's speed. Seed 2 of the cartpole draws a one-step delay for three of its first five episodes.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from reference import decisions

from npp_ros.run.setup import build_config, build_loop, resolve_lipschitz
from npp_ros.run.store import RunStore
from npp_ros.tasks.registry import ExpertOptions, get_task
from npp_ros.tasks.uncertainty import Robot

TASK = "cartpole_swingup"
SEED = 2
HORIZON = 80
EPSILON = 20.0
LIPSCHITZ = 4300.0
EPISODES = 5
BUDGET = 120.0  # seconds per request: never reached, so iterations decide (deterministic)
ITERATIONS = 5


@pytest.mark.parametrize(
    ("certify", "expert_model"), [("oracle", "robot"), ("success", "robot"), ("oracle", "nominal")]
)
@pytest.mark.long
def test_a_run_under_uncertainty_gives_the_in_process_robots_returns_and_checks(
    tmp_path: Path, certify: str, expert_model: str
) -> None:
    """The gap claim (oracle: the expert answers every episode) and the success claim (the expert only after a
    failed check) alike; and an expert that plans on the nominal model, its plans run on each robot by the
    supervisor as in process."""
    run_dir = tmp_path / "graph"
    command = [
        sys.executable, "-m", "npp_ros_graph.tools.run", "--task", TASK, "--seed", str(SEED),
        "--horizon", str(HORIZON), "--epsilon", str(EPSILON), "--lipschitz", str(LIPSCHITZ),
        "--max-episodes", str(EPISODES), "--run-dir", str(run_dir), "--time-budget", str(BUDGET),
        "--max-iterations", str(ITERATIONS), "--uncertainty", "1", "--certify", certify, "--expert-model", expert_model,
    ]  # fmt: skip
    run = subprocess.run(command, capture_output=True, text=True, timeout=600)
    logs = {p.stem: p.read_text() for p in sorted((run_dir / "logs").glob("*.log"))}
    tails = "\n".join(f"== {name}\n{text[-3000:]}" for name, text in logs.items())
    assert run.returncode in (0, 1), f"{run.stderr[-3000:]}\n{tails}"  # 1: not certified within the budget
    with RunStore.open(run_dir / "run.sqlite") as store:
        graph_data = store.load_dataset()
        graph_rows = store.episodes()
        metadata = store.metadata
        graph_certificate = store.certificate()
    assert len(graph_rows) == EPISODES, tails

    task = get_task(TASK)
    expert = task.make_expert(SEED, HORIZON, ExpertOptions(time_budget=BUDGET, max_iterations=ITERATIONS))
    lipschitz = resolve_lipschitz(TASK, LIPSCHITZ, expert)
    config = build_config(
        TASK, SEED, lipschitz, EPSILON, horizon=HORIZON, uncertainty=1.0, certify=certify, expert_model=expert_model
    )
    loop = build_loop(config, expert)
    local = loop.run(max_episodes=EPISODES)
    assert metadata.uncertainty == config.uncertainty != "" and metadata.expert_model == expert_model

    robots = [r.robot for r in graph_rows]
    assert robots == [r.robot for r in local.rows] and all(robots)
    delayed = [r.episode for r in graph_rows if Robot.from_record(str(r.robot)).action_delay]
    driven = [r.episode for r in graph_rows if r.policy_return is not None]
    assert set(delayed) & set(driven), "no driven episode had a delay: the test shows nothing of RobotEffects"
    assert decisions(graph_rows) == decisions(local.rows)
    assert [(r.checked_gap, r.policy_return, r.expert_value) for r in graph_rows] == [
        (r.checked_gap, r.policy_return, r.expert_value) for r in local.rows
    ]
    for name in ("states", "actions", "values", "gains"):  # the gains too: every expert plans on its request's robot
        np.testing.assert_array_equal(getattr(graph_data, name), getattr(loop.dataset, name))
    assert (graph_certificate is None) == (local.certificate is None)

    # Each node says which robot it ran or planned on.
    for episode in driven:
        described = Robot.from_record(str(graph_rows[episode].robot)).describe()
        assert f"episode {episode} done: {HORIZON} steps" in logs["sim"] and described in logs["sim"]
