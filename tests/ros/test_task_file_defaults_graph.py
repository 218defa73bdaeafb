"""A task file's defaults through npp-run: L = data is fixed by the supervisor as npp-learn fixes it and recorded with
its source; a file without epsilon stops the run with the line that names the key and the flag."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from npp_ros.run.setup import resolve_lipschitz
from npp_ros.run.store import RunStore
from npp_ros.tasks.registry import ExpertOptions, get_task

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "examples" / "two_link_arm"
HORIZON = 20


def npp_run(task_file: Path, run_dir: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    command = [
        sys.executable, "-m", "npp_ros_graph.tools.run", "--task", str(task_file), "--horizon", str(HORIZON),
        "--max-episodes", "2", "--run-dir", str(run_dir), *extra,
    ]  # fmt: skip
    return subprocess.run(command, capture_output=True, text=True, timeout=600, cwd=REPO)


@pytest.mark.long
def test_npp_run_fixes_l_from_data_as_npp_learn_does(tmp_path: Path, ros_domain: int) -> None:
    run_dir = tmp_path / "arm"
    run = npp_run(EXAMPLE / "task.toml", run_dir, "--lipschitz", "data", "--epsilon", "5")
    with RunStore.open(run_dir / "run.sqlite") as store:
        metadata = store.metadata
    task = get_task(str(EXAMPLE / "task.toml"))
    expert = task.make_expert(0, HORIZON, ExpertOptions())
    in_process = resolve_lipschitz(task.name, "data", expert, seed=0, horizon=HORIZON)
    assert (metadata.lipschitz_source, metadata.lipschitz) == ("data", in_process.value), run.stderr[-2000:]
    assert f"L = {in_process.value:.6g} (data)" in (run_dir / "logs" / "supervisor.log").read_text()


def test_npp_run_names_the_missing_epsilon_key_and_flag(tmp_path: Path, ros_domain: int) -> None:
    shutil.copy(EXAMPLE / "arm.xml", tmp_path / "arm.xml")
    text = (EXAMPLE / "task.toml").read_text()
    kept = "\n".join(line for line in text.splitlines() if not line.startswith("epsilon"))
    (tmp_path / "task.toml").write_text(kept + "\n")
    run_dir = tmp_path / "run"
    run = npp_run(tmp_path / "task.toml", run_dir)
    assert run.returncode != 0
    said = run.stdout + run.stderr + (run_dir / "logs" / "supervisor.log").read_text()
    assert "the task file gives no epsilon: add `epsilon = ...` to it or pass --epsilon" in said
