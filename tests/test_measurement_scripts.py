"""The measurement scripts behind docs/results.md: what they compute is what their docs say they compute."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from npp_ros.cli.learn import main as learn
from npp_ros.run.setup import task_control_space
from npp_ros.tasks.registry import get_task

ROOT = Path(__file__).resolve().parents[1]


def script(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def lqr_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three path-policy episodes of lqr_2_1: expert trajectories with the optimal LQR's gains."""
    run_dir = tmp_path_factory.mktemp("lqr") / "run"
    argv = ["--task", "lqr_2_1", "--seed", "0", "--policy", "path", "--max-episodes", "3", "--evaluate", "0"]
    assert learn([*argv, "--run-dir", str(run_dir)]) == 1  # three episodes: stored, not yet certified
    return run_dir


def test_tvlqr_gains_are_the_lqr_gain_on_a_linear_plant() -> None:
    """With the task's own cost, the Riccati pass along a path of a linear plant converges to the optimal LQR gain
    its expert acts with, so the finite differences and the recursion are both right. Its closed loop decays by
    0.997 a step, so the path is long enough (5,000 steps) for the pass to settle."""
    task = get_task("lqr_2_1")
    plant, expert = task.make_plant(0), task.make_expert(0, 5000)
    path = expert.trajectory(task.initial_state(0, 0))
    weights = list(np.diag(np.asarray(plant.state_cost)))
    control = float(np.asarray(plant.control_cost)[0, 0])
    gains = script("path_basin").tvlqr_gains(plant, task_control_space("lqr_2_1", 0), path, weights, control)
    assert path.gains is not None
    np.testing.assert_allclose(gains[0], path.gains[0], rtol=1e-5, atol=1e-8)
    assert not np.allclose(gains[-1], path.gains[-1], rtol=1e-2)  # a finite pass: near its end it has not settled


def test_path_basin_replays_its_expert_at_distance_zero(lqr_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "basin.md"
    command = [sys.executable, str(ROOT / "scripts" / "path_basin.py"), str(lqr_run), "--trajectories", "2",
               "--directions", "2", "--starts", "5", "--radii", "0.1", "--out", str(out)]  # fmt: skip
    subprocess.run(command, check=True, capture_output=True, cwd=ROOT)
    (result,) = json.loads(out.with_suffix(".json").read_text())
    at_zero = [row for row in result["rows"] if row["radius"] == 0.0]
    assert len(at_zero) == 2 and all(row["rollouts"] == 1 == row["within_epsilon"] for row in at_zero)
    assert {row["radius"] for row in result["rows"]} == {0.0, 0.1}
    assert result["stored_trajectories"] == 3 and result["fresh_s0"] == 5
    assert "| expert | 0.1 |" in out.read_text()


def test_path_compare_gives_one_row_per_prefix_kind_and_l(lqr_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "compare.md"
    command = [sys.executable, str(ROOT / "scripts" / "path_compare.py"), str(lqr_run), "--starts", "3",
               "--prefixes", "1,0", "--kinds", "feedback,path", "--lipschitz", "100,300", "--expert", "2",
               "--out", str(out)]  # fmt: skip
    subprocess.run(command, check=True, capture_output=True, cwd=ROOT)
    rows = json.loads(out.with_suffix(".json").read_text())
    assert [(r["trajectories"], r["policy"], r["lipschitz"]) for r in rows] == [
        (count, kind, value) for count in (1, 3) for kind in ("feedback", "path") for value in (100.0, 300.0)
    ]
    for row in rows:
        assert row["asked"] == 2 and 0 <= row["within_epsilon"] <= 2
        assert len(row["outside_epsilon"]) == 2 - row["within_epsilon"]
