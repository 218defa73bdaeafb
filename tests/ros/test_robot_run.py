"""npp-robot-run against npp-robot, each its own process over DDS: a run whose plant is the robot, a robot the run is
not told about (its damping and its sensor noise are npp-robot's, its description the nominal model's).

It certifies on that robot from the robot's own episodes; stopped with Ctrl-C mid-run and started again, it goes on
where it stopped with no episode counted twice; the gate then plays the run back and takes it for that robot only.
A robot of another structure is refused before it moves; a real-time robot faster than real time stores its
episodes on its own clock."""

from __future__ import annotations

import signal
import time
from pathlib import Path
from typing import Any

import pytest

from npp_ros.deployment.gate import Acceptance, GateRefusal, load_deployment
from npp_ros.run.on_robot.identity import RobotIdentity
from npp_ros.run.read import read_run
from npp_ros.run.rederive import rederive
from npp_ros.run.store import RUN_FILE, RunStore
from npp_ros.tasks.registry import get_task

TASK, SEED = "lqr_2_1", 0
HIDDEN = {"damping_scale": 1.3, "state_noise": 1e-4, "publish_description": "nominal"}
RUN_TIMEOUT_S = 600.0  # a whole certification on a busy machine: only a stuck run takes this long


def robot_run_params(run_dir: Path, **more: Any) -> dict[str, Any]:
    return {"task": TASK, "seed": SEED, "run_dir": str(run_dir), "certify": "success", **more}


def wait_exit(proc: Any, timeout: float) -> int:
    deadline = time.monotonic() + timeout
    while proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    assert proc.poll() is not None, "npp-robot-run did not finish in time"
    return int(proc.returncode)


def wait_for_rows(path: Path, rows: int, timeout: float = 300.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.exists():
            try:
                with RunStore.open(path) as store:
                    if len(store.episodes()) >= rows:
                        return
            except Exception:  # being created: look again
                pass
        time.sleep(0.5)
    pytest.fail(f"{path} did not reach {rows} episodes")


@pytest.mark.long
def test_a_run_on_a_hidden_robot_certifies_resumes_after_ctrl_c_and_deploys_to_that_robot_only(
    launch: Any, tmp_path: Path
) -> None:
    launch("npp-robot", {"task": TASK, "seed": SEED, "lockstep": True, **HIDDEN})
    run_dir = tmp_path / "run"
    first = launch("npp-robot-run", robot_run_params(run_dir))
    wait_for_rows(run_dir / RUN_FILE, 6)
    first.send_signal(signal.SIGINT)
    assert wait_exit(first, 60.0) == 0, launch.log(first)
    stopped = read_run(run_dir)
    assert stopped.certificate is None and len(stopped.episodes) >= 6
    second = launch("npp-robot-run", robot_run_params(run_dir))
    assert wait_exit(second, RUN_TIMEOUT_S) == 0, launch.log(second)
    assert "[certificate]" in launch.log(second) and "this robot's resets" in launch.log(second)
    run = read_run(run_dir)
    assert run.on_robot and run.certificate is not None and run.certificate.proven
    counted = [k.episode for k in run.robot_episodes if k.role == "check" and k.fault is None]
    assert len(counted) == len(set(counted)) == len(run.episodes) - 1  # no episode counted twice across the stop
    assert [row.episode for row in run.episodes[: len(stopped.episodes)]] == [r.episode for r in stopped.episodes]
    found = rederive(run)
    assert found.agrees, found.differences
    nominal = get_task(TASK).make_plant(SEED).model_sha256()
    assert RobotIdentity.from_record(run.metadata.robot_run).fingerprint == nominal  # what its description says
    assert load_deployment(run_dir, Acceptance(model_fingerprint=nominal, rederive=False)).certificate is not None
    with pytest.raises(GateRefusal, match="of that one robot only"):
        load_deployment(run_dir, Acceptance(model_fingerprint="0" * 64, rederive=False))


def test_a_robot_of_another_structure_is_refused_before_it_moves(launch: Any, tmp_path: Path) -> None:
    launch("npp-robot", {"task": "pendulum_swingup", "seed": SEED, "lockstep": True})
    run_dir = tmp_path / "run"
    proc = launch("npp-robot-run", robot_run_params(run_dir))
    assert wait_exit(proc, 120.0) == 1
    log = launch.log(proc)
    assert "is not a lqr_2_1 robot" in log and "its structure is not the certified model's" in log, log
    assert not (run_dir / RUN_FILE).exists()  # nothing stored, nothing commanded


def test_a_real_time_robot_faster_than_real_time_gives_episodes_on_its_own_clock(launch: Any, tmp_path: Path) -> None:
    launch("npp-robot", {"task": TASK, "seed": SEED, "time_scale": 5.0, **HIDDEN})
    run_dir = tmp_path / "run"
    horizon = 60
    proc = launch("npp-robot-run", robot_run_params(run_dir, horizon=horizon, max_episodes=3))
    assert wait_exit(proc, 300.0) == 0, launch.log(proc)
    run = read_run(run_dir)
    assert len(run.episodes) == 3 and run.certificate is None
    ran = [k for k in run.robot_episodes if k.fault is None and k.role in ("check", "answer")]
    assert ran and all(k.steps >= horizon for k in ran)
    dt = get_task(TASK).make_plant(SEED).dt
    for k in ran:  # the robot's clock: a period a step (and its hold at the start, which runs with the clock)
        assert k.robot_time >= (k.steps - 1) * dt - 1e-6 and k.late_commands >= 0
    assert run.certificate is None and "the certificate can no longer be reached" in launch.log(proc)
