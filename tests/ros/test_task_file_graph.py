"""A task file through the graph: npp-run certifies the example arm; the nodes agree on the file or refuse it."""

from __future__ import annotations

import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import pytest
from expert_checks import TIMEOUT, request, wait_until_modelling
from npp_interfaces.msg import PlantDescription
from npp_interfaces.srv import ExpertTrajectory

from npp_ros.run.store import RunStore
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.task_file.loader import HASH_MARK
from npp_ros_graph.transport.topics import EXPERT_SERVICE, LATCHED_READER_QOS, PLANT

if TYPE_CHECKING:
    from tests.ros.conftest import Launcher, RosClient

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "examples" / "two_link_arm"


@pytest.mark.long
def test_npp_run_certifies_the_example_arm_from_its_task_file(tmp_path: Path, ros_domain: int) -> None:
    """The README's command at a short horizon: 50 steps, epsilon 8 (of at most 55 per episode)."""
    run_dir = tmp_path / "arm"
    command = [
        sys.executable, "-m", "npp_ros_graph.tools.run", "--task", "examples/two_link_arm/task.toml",
        "--horizon", "50", "--epsilon", "8", "--max-episodes", "400", "--time-budget", "60", "--run-dir", str(run_dir),
    ]  # fmt: skip
    run = subprocess.run(command, capture_output=True, text=True, timeout=900, cwd=REPO)
    logs = "\n".join(f"== {p.name}\n{p.read_text()[-3000:]}" for p in sorted((run_dir / "logs").glob("*.log")))
    assert run.returncode == 0, f"{run.stderr[-3000:]}\n{logs}"
    assert "[certificate] condition (i), epsilon 8" in run.stdout
    with RunStore.open(run_dir / "run.sqlite") as store:
        metadata, rows, certificate = store.metadata, store.episodes(), store.certificate()
    task = get_task(str(EXAMPLE / "task.toml"))
    assert metadata.task == task.name and HASH_MARK in metadata.task
    assert metadata.plant_fingerprint == task.make_plant(0).model_sha256()
    assert (metadata.certify, metadata.horizon) == ("oracle", 50)
    assert certificate is not None and certificate["episodes"] == len(rows)
    assert all(row.oracle_called for row in rows)
    assert sum(row.policy_return is not None for row in rows) >= len(rows) - 5  # the policy drove through the sim


def test_the_expert_refuses_a_task_file_that_changed_under_the_sim(
    launch: Launcher, ros_client: Callable[..., RosClient], tmp_path: Path
) -> None:
    for name in ("arm.xml", "task.toml"):
        shutil.copy(EXAMPLE / name, tmp_path / name)
    task_file = tmp_path / "task.toml"
    launch("npp-sim", {"task": str(task_file), "horizon": 50})
    client = ros_client("task_file_client")
    plants = client.collect(PlantDescription, PLANT, LATCHED_READER_QOS)
    client.wait_for(lambda: bool(plants), TIMEOUT, "the sim's plant description")
    published = plants[0].task
    assert published == get_task(str(task_file)).name
    task_file.write_text(task_file.read_text().replace("epsilon = 20.0", "epsilon = 21.0"))
    launch("npp-expert", {})
    service = client.client(ExpertTrajectory, EXPERT_SERVICE, TIMEOUT)
    wait_until_modelling(client, service)
    answer = client.call(service, request([0.1, 0.2, 0.0, 0.0], 10))
    assert not answer.success
    assert "task file mismatch" in answer.message, answer.message
    assert published.split(HASH_MARK)[1][:16] in answer.message
    assert get_task(str(task_file)).name.split(HASH_MARK)[1][:16] in answer.message


def test_the_sim_refuses_a_bad_task_file_in_one_line(launch: Launcher, tmp_path: Path) -> None:
    for name in ("arm.xml", "task.toml"):
        shutil.copy(EXAMPLE / name, tmp_path / name)
    task_file = tmp_path / "task.toml"
    task_file.write_text(task_file.read_text().replace('joints = ["shoulder", "elbow"]', 'joints = ["shoulder"]'))
    sim = launch("npp-sim", {"task": str(task_file)})
    assert sim.wait(timeout=60) == 2
    log = launch.log(sim)
    lines = [line for line in log.splitlines() if line.strip() and "GLFW" not in line and "warn" not in line]
    assert "Traceback" not in log
    assert lines[-1].startswith("npp-sim: bad parameter: task file")
    assert "state.joints: must list every joint" in lines[-1]
