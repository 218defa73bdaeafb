"""The acrobot as a task file (examples/acrobot, no Python) and as npp_ros's own task run the same Algorithm 1
at a small horizon: the same decisions, every answer stored with its feedback gains, and the expert's and the
policy's success judged in every episode by each task's own criterion. At their full horizon both miss their
certificate for the same measured reason, a policy that does not follow its expert (docs/tutorials/own-robot.md)."""

from __future__ import annotations

from pathlib import Path

import pytest

import npp_ros

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "acrobot" / "task.toml"
HORIZON = 100  # 1 s: both success criteria judge the whole episode
EPISODES = 2


@pytest.mark.long
def test_the_acrobot_file_runs_algorithm_1_as_the_built_in_acrobot_does(tmp_path: Path) -> None:
    decisions = {}
    for name, task in (("built-in", "acrobot_swingup"), ("file", str(EXAMPLE))):
        result = npp_ros.learn(
            task, seed=0, horizon=HORIZON, max_episodes=EPISODES, epsilon=130.0, lipschitz=4300.0,
            policy="feedback", run_dir=tmp_path / name,
        )  # fmt: skip
        run = npp_ros.read_run(tmp_path / name)
        assert not result.certified and result.episodes == EPISODES
        assert all(isinstance(row.expert_success, bool) for row in result.rows if row.oracle_called), result.rows
        assert all(isinstance(row.policy_success, bool) for row in result.rows[1:]), result.rows  # once a policy acts
        assert run.dataset.num_trajectories == result.oracle_calls
        assert all(run.dataset.trajectory(k).gains is not None for k in range(run.dataset.num_trajectories))
        decisions[name] = [row.oracle_called for row in result.rows]
    assert decisions["file"] == decisions["built-in"], decisions
