"""A certified policy whose state holds a target, deployed over DDS: npp-robot runs the point-mass reach
(tests/fixtures/point_reach) in real time and reports the mass's joints only, and npp-deploy takes the target
from its topic: nothing but the watchdog's safe command before a target, a point in another frame and one
outside rho's box refused with the reason and the target before kept, and a target inside the box reached, as
the robot's own joint states show.

The run is a real certified run of the fixture made here with the core loop (tests/deploy_runs.py). No test
asserts a speed: each waits, with a timeout, for the robot's states to show what it checks."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from deploy_nodes import KEEP_ALL, START_TIMEOUT_S, Deploy, count
from deploy_runs import REACH, SEED, make_reach_run
from geometry_msgs.msg import Point, PointStamped
from sensor_msgs.msg import JointState

from npp_ros.tasks.registry import get_task
from npp_ros_graph.runtime.diagnostics import OK, WARN
from npp_ros_graph.transport.topics import CONTROL_QOS, JOINT_STATES

TARGET_TOPIC = "/npp_deploy/target"  # npp-deploy's default, ~/target
BOX = "x [0.1, 0.3], y [0, 0.2], z [0, 0] m"
BAND = 0.02  # m: the fixture's success band on the distance
REACH_TIMEOUT_S = 120.0  # the robot steps in real time; a busy machine makes a reach slower, never wrong


@pytest.fixture(scope="module")
def reach_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_reach_run(tmp_path_factory.mktemp("reach") / "run")


class RobotStates:
    """The robot's joint states as this test hears them: names and the mass's position, in order."""

    def __init__(self, client: Any) -> None:
        self.client = client
        self.names: set[tuple[str, ...]] = set()
        self.positions: list[np.ndarray] = []
        self.sub = client.node.create_subscription(JointState, JOINT_STATES, self._on_state, KEEP_ALL)

    def _on_state(self, msg: JointState) -> None:
        self.names.add(tuple(msg.name))
        self.positions.append(np.array(msg.position, dtype=np.float64))

    def settles_at(self, goal: np.ndarray, label: str) -> float:
        """Wait until the mass has stayed within the band of ``goal`` (x, y) over the task's success window, and
        a window more: the largest distance over that later window, which must stay in the band too."""
        success = get_task(REACH).success
        assert success is not None
        window = success.steps
        since = len(self.positions)

        def settled() -> bool:
            recent = self.positions[since:][-window:]
            return len(recent) == window and max(np.linalg.norm(p - goal[:2]) for p in recent) <= BAND

        self.client.wait_for(settled, REACH_TIMEOUT_S, f"the mass within {BAND} m of {goal.tolist()} ({label})")
        after = len(self.positions)
        self.client.wait_for(lambda: len(self.positions) >= after + window, REACH_TIMEOUT_S, "a window more")
        miss = max(float(np.linalg.norm(p - goal[:2])) for p in self.positions[after : after + window])
        assert miss <= BAND, f"{label}: the mass left the band, {miss:.4f} m from {goal.tolist()}"
        return miss


def point(x: float, y: float, z: float = 0.0, frame: str = "world") -> PointStamped:
    msg = PointStamped(point=Point(x=x, y=y, z=z))
    msg.header.frame_id = frame
    return msg


def warnings_of(log: str) -> list[str]:
    return [line for line in log.splitlines() if "[WARN]" in line]


def test_npp_deploy_waits_for_a_target_reaches_one_inside_the_box_and_refuses_the_others(
    reach_run, launch, ros_client
) -> None:
    start = "0.04,-0.03,-0.1,0.1,0.0,0,0,0,0,0"  # the robot's simulated target at (0.1, 0.2, 0): not npp-deploy's
    launch("npp-robot", {"task": REACH, "seed": SEED, "initial_state": start})
    proc = launch("npp-deploy")
    client = ros_client("target_test")
    robot = RobotStates(client)
    client.wait_for(lambda: robot.sub.get_publisher_count() > 0, START_TIMEOUT_S, "the robot's joint states")
    deploy = Deploy(client)
    deploy.deploy(reach_run, fingerprint=None, state_timeout=1.0)
    targets = client.node.create_publisher(PointStamped, TARGET_TOPIC, CONTROL_QOS)
    client.wait_for(lambda: targets.get_subscription_count() > 0, 30.0, "npp-deploy's target subscription")

    # No target yet: the watchdog's safe command is all that goes out, and the node says what it waits for.
    health = deploy.health_where(lambda h: count(h, "watchdog expiries") >= 1, "the watchdog expired")
    assert (health.level, health.doing) == (OK, f"active: waiting for a target on {TARGET_TOPIC}"), health
    assert health.values["target"] == f"none received on {TARGET_TOPIC}" and count(health, "answered") == 0
    assert robot.names == {("mass_x", "mass_y")}  # the target's joints are in no joint state
    assert f"waiting for a target on {TARGET_TOPIC}" in launch.log(proc)

    # A point in another frame is refused with the reason; there is still no target, and nothing is commanded.
    seen = len(deploy.statuses)
    targets.publish(point(0.25, 0.15, frame="map"))
    refused = "target (0.25, 0.15, 0.0) is in frame 'map', not 'world': give it in 'world'"
    health = deploy.health_where(lambda h: h.level == WARN, "the frame refused", since=seen)
    assert health.error == f"target refused: {refused}; there is still no target", health
    assert health.doing == f"active: waiting for a target on {TARGET_TOPIC}"
    assert any(refused in line for line in warnings_of(launch.log(proc)))

    # A target inside the box: the mass goes there and stays, measured on the robot's own joint states.
    assert all(command == [0.0, 0.0] for _, command in deploy.commands), deploy.commands
    first = np.array([0.25, 0.15, 0.0])
    targets.publish(point(*first))
    miss = robot.settles_at(first, "the first target")
    health = deploy.health_where(lambda h: h.doing == "active: commanding the robot", "commanding")
    assert health.level == OK and health.values["target"] == "(0.25, 0.15, 0) in world", health
    assert count(health, "refused states") == 0

    # A target outside the box: refused (not clamped), the user told which point and which box; the first is kept.
    seen = len(deploy.statuses)
    targets.publish(point(0.35, 0.1))
    health = deploy.health_where(lambda h: h.level == WARN, "the target refused", since=seen)
    outside = f"target (0.35, 0.1, 0) lies outside the box {BOX} that rho draws targets from"
    assert health.error.startswith(f"target refused: {outside}"), health.error
    assert health.error.endswith("the target kept is (0.25, 0.15, 0) in world"), health.error
    assert health.values["target"] == "(0.25, 0.15, 0) in world"
    client.wait_for(lambda: any(outside in line for line in warnings_of(launch.log(proc))), 30.0, "the WARN line")
    kept = robot.settles_at(first, "the target kept")  # still there, a success window after the refusal

    # A new target inside the box is taken and the warning ends. (The mass now rests where rho draws no start, far
    # from the policy's data: npp-deploy warns that the certificate says nothing of such a state.)
    seen = len(deploy.statuses)
    targets.publish(point(0.12, 0.19))
    health = deploy.health_where(lambda h: h.values["target"] == "(0.12, 0.19, 0) in world", "taken", since=seen)
    assert "target refused" not in health.values and "target refused" not in health.error, health
    log = launch.log(proc)
    assert re.search(r"target \(0\.12, 0\.19, 0\) in world taken", log), log[-2000:]
    assert "the certificate says nothing about it" in log
    print(f"\nthe mass ended within {miss * 1e3:.1f} mm of the target over the success window after it, "
          f"{kept * 1e3:.1f} mm after a refused one")  # fmt: skip


def test_npp_trial_rehearses_a_reach_giving_each_episode_its_target(reach_run: Path, tmp_path: Path) -> None:
    """npp-trial on a reach: each episode's target (s0's) goes to npp-deploy on its topic, the robot moves exactly as
    the model does with it, and the episode is judged on the task's success criterion on the robot and in process."""
    cmd = [sys.executable, "-m", "npp_ros_graph.bench.trial", str(reach_run), "--episodes", "2",
           "--out", str(tmp_path)]  # fmt: skip
    subprocess.run(cmd, check=True, timeout=600)
    out = json.loads((tmp_path / "trial.json").read_text())
    assert len(out["episodes"]) == 2
    for episode in out["episodes"]:
        assert episode["replay_mismatches"] == 0, episode  # the robot moved exactly as the model does
        assert episode["first_command_answers_s0"], episode  # its first command answered s0 with its target
        assert episode["robot_success"] is not None and episode["in_process_success"] is not None
        if episode["fresh_command_share"] == 1.0:  # no command missed its period: the in-process episode exactly
            assert episode["robot_success"] == episode["in_process_success"], episode
    assert "success robot / in process" in (tmp_path / "trial.md").read_text()
