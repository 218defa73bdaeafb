"""npp-deploy and npp-robot as separate processes over DDS: the gate, the robot's model from its description, the
lockstep and real-time loops against the in-process policy, the watchdog, the stop service, bad joint states
and what /diagnostics says at each step.

The run folders are real short-horizon lqr_2_1 runs made here with the core loop (tests/deploy_runs.py).
No test asserts a speed: the watchdog is checked to wait at least its timeout, never how soon it acts (the
measured figures are in results/, from npp-bench-deploy). A test that reads a status waits for the status
that reflects what it checks (Deploy.health_where): a status published a moment earlier may not have
counted the last answer yet."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from deploy_nodes import KEEP_ALL, START_TIMEOUT_S, Deploy, count
from deploy_runs import EPSILON, FINGERPRINT, HORIZON, SEED, TASK, bad_folders, make_run, with_robots
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger

from npp_ros.deployment.robot_model import model_mjcf
from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.run.setup import policy_for, spec_of
from npp_ros.run.store import RunStore
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.rollout import rollout
from npp_ros.tasks.uncertainty import Robot
from npp_ros_graph.runtime.diagnostics import ERROR, OK, WARN
from npp_ros_graph.transport.convert import float64_array, stamp
from npp_ros_graph.transport.topics import CONTROL_QOS, JOINT_STATES, LATCHED_QOS

ROBOT_DESCRIPTION = "/robot_description"


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, tuple[Path, str]]]:
    root = tmp_path_factory.mktemp("deploy-runs")
    good = make_run(root / "good")
    return good, bad_folders(good, root)


def certified_policy(run: Path) -> NonparametricPolicy:
    """The certificate's policy, read here straight from the run file (not through npp_ros.deploy)."""
    with RunStore.open(run / "run.sqlite") as store:
        certificate, data = store.certificate(), store.load_dataset()
        spec = spec_of(store.metadata, get_task(TASK).initial_state_diameter)
    assert certificate is not None
    return policy_for(data.prefix(certificate["policy_trajectories"]), spec, TASK, 0)


def s0_text(state: np.ndarray) -> str:
    return ",".join(repr(float(x)) for x in state)


def test_the_gate_refuses_each_bad_folder_with_its_reason_and_a_valid_one_activates(runs, launch, ros_client) -> None:
    good, bad = runs
    proc = launch("npp-deploy")
    deploy = Deploy(ros_client("gate_test"))
    cases = [(folder, reason, {}) for folder, reason in bad.values()]
    cases += [
        (good, "is not the certified one", {"robot_model_fingerprint": "0" * 64}),
        (good, r"epsilon 2 is larger than this deployment accepts \(max_epsilon 1\)", {"max_epsilon": 1.0}),
    ]
    for folder, reason, extra in cases:
        deploy.set(**{"run_dir": str(folder), "robot_model_fingerprint": FINGERPRINT, "max_epsilon": 100.0, **extra})
        seen = len(deploy.statuses)
        assert not deploy.transition("configure"), f"{folder} was configured"
        assert deploy.state() == "unconfigured"
        health = deploy.health_where(lambda h, r=reason: re.search(r, h.doing) is not None, reason, since=seen)
        assert health.level == ERROR and health.doing.startswith("configure refused: "), health.doing
        assert health.values["last event"] == health.doing and health.values["last event at"].endswith(" UTC")
        assert not deploy.transition("activate")  # nothing to activate
        launch.assert_alive(proc)
    deploy.set(run_dir=str(good), robot_model_fingerprint=FINGERPRINT, max_epsilon=EPSILON, min_p=0.9, max_delta=0.1)
    assert deploy.transition("configure") and deploy.state() == "inactive"
    assert deploy.transition("activate") and deploy.state() == "active"
    health = deploy.health_where(lambda h: h.values["lifecycle state"] == "active", "it is active")
    assert "proven" in str(health.values["policy"])
    assert str(health.values["robot model fingerprint"]) == (
        f"{FINGERPRINT[:12]}... from the robot_model_fingerprint parameter"
    )
    with pytest.raises(AssertionError, match="read at configure"):
        deploy.set(max_epsilon=1000.0)  # an active deployment's parameters stay as configured
    launch.stop(proc)
    log = launch.log(proc)
    assert (
        "configure refused: the run file holds no certificate" in log
        and "no longer matches its seal: points.s_0" in log
    )
    assert "SIGINT: safe command [0.0] sent" in log  # Ctrl-C on an active node: the safe command goes out first


def test_the_robots_description_gives_its_fingerprint_and_another_model_is_refused(runs, launch, ros_client) -> None:
    """npp-robot publishes its MJCF on /robot_description; npp-deploy computes the fingerprint from it (no
    operator copies it), refuses another model, stops when the robot's model changes, and the
    robot_model_fingerprint parameter still overrides the description."""
    good, _ = runs
    other_robot = launch("npp-robot", {"seed": SEED + 1})  # lqr's stiffness is drawn from the seed
    proc = launch("npp-deploy")
    client = ros_client("description_test")
    deploy = Deploy(client)
    deploy.has_description()
    deploy.set(run_dir=str(good))
    seen = len(deploy.statuses)
    assert not deploy.transition("configure")
    health = deploy.health_where(lambda h: h.doing.startswith("configure refused"), "configure refused", since=seen)
    assert "is not the certified one" in health.doing, health.doing
    assert f"came from the MJCF the robot published on {ROBOT_DESCRIPTION}" in health.doing, health.doing

    launch.stop(other_robot)
    before = str(deploy.has_description().values["robot description"])
    launch("npp-robot")  # the certified model
    deploy.health_where(lambda h: h.values["robot description"] != before, "the new robot's description")
    deploy.deploy(good, fingerprint=None)
    health = deploy.health_where(lambda h: h.values["lifecycle state"] == "active", "it is active")
    assert health.values["robot model fingerprint"] == (
        f"{FINGERPRINT[:12]}... from the MJCF the robot published on {ROBOT_DESCRIPTION}"
    )
    client.wait_for(lambda: any(any(c) for _, c in deploy.commands), 60.0, "commands")

    # The robot now says it runs another model: npp-deploy stops, and will not activate on the old check.
    other = model_mjcf(get_task(TASK).make_plant(SEED + 1))
    assert other is not None
    client.node.create_publisher(String, ROBOT_DESCRIPTION, LATCHED_QOS).publish(String(data=other))
    health = deploy.health_where(lambda h: h.values["lifecycle state"] == "inactive", "it stopped")
    assert health.level == ERROR and "robot model changed" in health.doing, health.doing
    client.wait_for(lambda: deploy.commands[-1][1] == [0.0], 30.0, "the safe command")
    assert not deploy.transition("activate")

    # The operator's fingerprint overrides the description, and the log says so.
    assert deploy.transition("cleanup")
    deploy.deploy(good)
    deploy.health_where(lambda h: h.values["lifecycle state"] == "active", "it is active")
    assert "overrides the fingerprint of the robot's own description" in launch.log(proc)


def test_the_lockstep_robot_follows_the_in_process_policy_exactly(runs, launch, ros_client) -> None:
    good, _ = runs
    s0 = get_task(TASK).initial_state(SEED, 1000)  # an s0 ~ rho the run never drew
    want = rollout(get_task(TASK).make_plant(SEED), certified_policy(good).act, s0, HORIZON)
    launch("npp-robot", {"lockstep": True, "initial_state": s0_text(s0)})
    launch("npp-deploy")
    client = ros_client("lockstep_test")
    states: dict[tuple[int, int], np.ndarray] = {}

    def on_state(msg: JointState) -> None:
        states.setdefault(
            (msg.header.stamp.sec, msg.header.stamp.nanosec), np.concatenate([msg.position, msg.velocity])
        )

    joint_states = client.node.create_subscription(JointState, JOINT_STATES, on_state, KEEP_ALL)
    # Lockstep starts with npp-deploy's first command: this test must hear the robot before then, or it
    # misses the first states (discovery may match npp-deploy and the robot sooner than this test).
    client.wait_for(lambda: joint_states.get_publisher_count() > 0, START_TIMEOUT_S, "the robot's joint states")
    deploy = Deploy(client)
    deploy.deploy(good, fingerprint=None, state_timeout=30.0)
    # Both topics: the command answering the last state may reach this test after the state it led to.
    done = lambda: len(states) >= HORIZON and len(deploy.commands) >= HORIZON - 1  # noqa: E731
    client.wait_for(done, 120.0, f"{HORIZON} lockstep states and their commands")
    got = np.array([states[key] for key in sorted(states)][:HORIZON])
    np.testing.assert_array_equal(got, want.states)
    actions = np.array([command for _, command in deploy.commands[: HORIZON - 1]])
    np.testing.assert_array_equal(actions, want.actions[: HORIZON - 1])
    health = deploy.health_where(lambda h: count(h, "answered") >= HORIZON - 1, f"{HORIZON - 1} answered")
    assert health.level == OK and count(health, "refused states") == 0


def test_the_real_time_robot_stays_close_to_the_in_process_policy(runs, launch, ros_client) -> None:
    good, _ = runs
    s0 = get_task(TASK).initial_state(SEED, 1001)
    robot = launch("npp-robot", {"initial_state": s0_text(s0)})
    launch("npp-deploy")
    client = ros_client("real_time_test")
    states: list[np.ndarray] = []
    efforts: list[float] = []

    def on_state(msg: JointState) -> None:
        states.append(np.concatenate([msg.position, msg.velocity]))
        efforts.append(msg.effort[0])

    client.node.create_subscription(JointState, JOINT_STATES, on_state, KEEP_ALL)
    deploy = Deploy(client)
    deploy.deploy(good, state_timeout=2.0)  # a busy machine may delay a state past 0.1 s: not what is tested here
    client.wait_for(lambda: any(efforts), 60.0, "the first commanded step")
    # The state the first command answered (this test may have joined when commands already flowed).
    first = max(next(k for k, effort in enumerate(efforts) if effort) - 1, 0)
    steps = 60
    client.wait_for(lambda: len(states) > first + steps, 60.0, f"{steps} real-time steps")
    # npp-deploy measures the state period as it takes the states (what state_timeout must stay above).
    health = deploy.health_where(lambda h: count(h, "state periods measured") >= steps, "state periods measured")
    p50, p99, most = (float(x) for x in str(health.values["state period p50 / p99 / max (ms)"]).split(" / "))
    assert 0 <= p50 <= p99 <= most and most > 0
    launch.stop(robot)
    policy = certified_policy(good)
    got = np.array(states[first : first + steps])
    want = rollout(get_task(TASK).make_plant(SEED), policy.act, got[0], steps).states
    # Every command the robot applied is the certified policy's action at a state the robot was in, and the
    # robot's plant moved exactly as the model does under the commands it applied (held ones included).
    answers = [float(policy.act(state)[0]) for state in states[: first + steps]]
    plant = get_task(TASK).make_plant(SEED)
    plant.reset(got[0])
    for k in range(first, first + steps - 1):
        assert efforts[k + 1] in answers[: k + 1], f"step {k} applied {efforts[k + 1]}, no answer to a state so far"
        plant.step([efforts[k + 1]])
        np.testing.assert_array_equal(plant.state(), states[k + 1])
    # A command that misses its period leaves the previous one in force for a step: close, not equal.
    scale = float(np.abs(want).max())
    print(f"real time against in process: largest deviation {np.abs(got - want).max() / scale:.2%} of the scale")
    assert np.abs(got - want).max() <= 0.05 * scale, np.abs(got - want).max(axis=0)


def test_when_states_stop_the_safe_command_follows_and_the_status_recovers(runs, launch, ros_client) -> None:
    good, _ = runs
    timeout = 0.3
    robot = launch("npp-robot")
    proc = launch("npp-deploy")
    client = ros_client("watchdog_test")
    arrivals = client.collect(JointState, JOINT_STATES, KEEP_ALL)
    deploy = Deploy(client)
    deploy.deploy(good, fingerprint=None, state_timeout=timeout)
    client.wait_for(lambda: len(deploy.commands) >= 10 and len(arrivals) >= 10, 60.0, "the loop to run")
    before = len(deploy.commands)
    launch.stop(robot)
    client.wait_for(lambda: [0.0] in (c for _, c in deploy.commands[before:]), 30.0, "the safe command")
    health = deploy.health_where(lambda h: "joint states stopped" in h.doing, "states stopped")
    assert health.level == WARN and health.doing.startswith("active, joint states stopped: safe command sent")
    age_ms = float(re.search(r"no new joint state for (\d+) ms", health.error).group(1))
    assert age_ms >= timeout * 1e3  # it waited its timeout (how soon it acted after is npp-bench-deploy's figure)
    assert str(health.values["last event"]).startswith("watchdog expiry: no new joint state for")
    quiet = len(deploy.commands)
    time.sleep(4 * timeout)
    client.wait_for(lambda: True, 0.1)
    assert len(deploy.commands) == quiet  # no commanding while states are stopped
    launch("npp-robot")  # states flow again
    client.wait_for(lambda: any(any(c) for _, c in deploy.commands[quiet:]), START_TIMEOUT_S, "commands to resume")
    # The status says the present: commanding, OK; the expiry stays named as the last event, with its time.
    health = deploy.health_where(lambda h: h.doing == "active: commanding the robot", "it commands again")
    assert health.level == OK and health.error == "", health
    assert str(health.values["last event"]).startswith("watchdog expiry") and "last event at" in health.values
    assert "joint states flow again" in launch.log(proc)


def test_activating_before_the_robot_publishes_is_waiting_not_an_error(runs, launch, ros_client) -> None:
    """The order the docs give: npp-deploy active first, then the robot. Until its first joint state the node
    waits (OK), even when its watchdog has sent the safe command meanwhile; then it commands."""
    good, _ = runs
    launch("npp-deploy")
    client = ros_client("waiting_test")
    deploy = Deploy(client)
    deploy.deploy(good, state_timeout=0.2)
    health = deploy.health_where(lambda h: count(h, "watchdog expiries") >= 1, "the watchdog expired")
    assert health.level == OK and health.doing == "active: waiting for the robot's first joint state", health
    assert health.error == "" and count(health, "answered") == 0
    launch("npp-robot")
    client.wait_for(lambda: any(any(c) for _, c in deploy.commands), START_TIMEOUT_S, "commands")
    health = deploy.health_where(lambda h: h.doing == "active: commanding the robot", "it commands")
    assert health.level == OK


def test_commands_are_clamped_and_the_stop_service_deactivates_at_once(runs, launch, ros_client) -> None:
    good, _ = runs
    launch("npp-robot")
    launch("npp-deploy")
    client = ros_client("stop_test")
    deploy = Deploy(client)
    deploy.deploy(good, fingerprint=None, effort_limit=1e-3)  # far below what the LQR policy asks for
    client.wait_for(lambda: len([c for _, c in deploy.commands if any(c)]) >= 5, 60.0, "commands")
    assert all(abs(c[0]) <= 1e-3 for _, c in deploy.commands)
    deploy.health_where(lambda h: count(h, "clamped entries") > 0, "clamps counted")
    answer = client.call(deploy.stopper, Trigger.Request())
    assert answer.success and "inactive" in answer.message
    assert deploy.state() == "inactive"
    client.wait_for(lambda: deploy.commands[-1][1] == [0.0], 10.0, "the safe command")
    # The status says a stop was requested, and when.
    health = deploy.health_where(lambda h: h.values["lifecycle state"] == "inactive", "it is inactive")
    assert health.doing.startswith("inactive: not commanding (stop requested at "), health.doing
    assert health.values["last event"] == "stop requested" and health.level == OK
    after = len(deploy.commands)
    time.sleep(1.0)
    client.wait_for(lambda: True, 0.1)
    assert len(deploy.commands) == after  # the robot still publishes states; nothing answers them
    assert client.call(deploy.stopper, Trigger.Request()).success  # stopping a stopped node is harmless
    assert deploy.transition("activate")
    client.wait_for(lambda: any(any(c) for _, c in deploy.commands[after:]), 30.0, "commands after activate")


class StatePublisher:
    """Joint states from the test itself, each with a new stamp: what a faulty robot might send."""

    def __init__(self, client: Any) -> None:
        self.client = client
        self.publisher = client.node.create_publisher(JointState, JOINT_STATES, CONTROL_QOS)
        self.sent = 0

    def send(self, names: list[str], position: list[float], velocity: list[float]) -> None:
        self.sent += 1
        msg = JointState(name=names, position=float64_array(position), velocity=float64_array(velocity))
        msg.header.stamp = stamp(self.sent * 1_000_000)
        self.publisher.publish(msg)

    def keep_sending(self, states: list[tuple[list[str], list[float], list[float]]], until: Callable[[], bool],
                     label: str, every: float = 0.02, timeout: float = 60.0) -> None:  # fmt: skip
        """Send the states in turn, one every ``every`` seconds, until ``until()`` holds."""
        due = 0.0

        def sent_until() -> bool:
            nonlocal due
            if until():
                return True
            if time.monotonic() >= due:
                self.send(*states[self.sent % len(states)])
                due = time.monotonic() + every
            return False

        self.client.wait_for(sent_until, timeout, label)


def test_bad_joint_states_are_refused_without_a_crash(runs, launch, ros_client) -> None:
    good, _ = runs
    proc = launch("npp-deploy")
    client = ros_client("garbage_test")
    robot = StatePublisher(client)
    deploy = Deploy(client)
    deploy.deploy(good, state_timeout=60.0)
    client.wait_for(lambda: robot.publisher.get_subscription_count() > 0, 30.0, "npp-deploy's joint state subscription")
    robot.send(["joint_0", "elbow"], [0.1, 0.2], [0.0, 0.0])  # a foreign robot
    robot.send(["joint_0", "joint_1"], [0.1], [0.0, 0.0])  # counts that do not match the names
    robot.send(["joint_1", "joint_0"], [0.1, 0.2], [float("nan"), 0.0])
    robot.send([], [], [])
    robot.send(["joint_0", "joint_1"], [1e200, 0.0], [0.0, 0.0])  # finite, but too large to compare with the data
    deploy.health_where(lambda h: count(h, "refused states") == 5, "5 refused states")
    assert deploy.commands == []
    robot.send(["wrist", "joint_1", "joint_0"], [5.0, 0.2, 0.1], [0.0, 0.0, 0.0])  # a good one, extra joint ignored
    client.wait_for(lambda: len(deploy.commands) == 1, 30.0, "the answer to the good state")
    want = certified_policy(good).act(np.array([0.1, 0.2, 0.0, 0.0]))
    assert deploy.commands[0][1] == want.tolist()
    launch.assert_alive(proc)
    health = deploy.health_where(lambda h: count(h, "answered") == 1, "the answer counted")
    assert count(health, "refused states") == 5
    log = launch.log(proc)
    assert "lacks the task's joints joint_1 (it names: joint_0, elbow)" in log
    assert "joint_1 velocity = nan" in log
    assert "lacks the task's joints joint_0, joint_1 (it names: none)" in log
    assert "joint_0 position = 1e+200" in log and "could not answer" not in log

    # A state far from the certified data, with stop_outside_coverage: reported, and the node stops.
    assert deploy.transition("deactivate") and deploy.transition("cleanup")
    deploy.deploy(good, state_timeout=60.0, stop_outside_coverage=True)
    robot.send(["joint_0", "joint_1"], [0.1, 0.2], [40.0, 0.0])
    client.wait_for(lambda: deploy.state() == "inactive", 30.0, "the stop outside the coverage")
    assert "the certificate says nothing about it" in launch.log(proc)
    health = deploy.health_where(lambda h: h.values["lifecycle state"] == "inactive", "it is inactive")
    assert health.level == WARN and "stopped outside the certificate's coverage" in health.doing, health.doing
    launch.assert_alive(proc)


def test_states_naming_no_joint_are_refused_and_do_not_hold_the_watchdog_off(runs, launch, ros_client) -> None:
    """A robot whose joint states name none of the task's joints (or only some): every one is refused with its
    reason and counted, none counts as fresh, so the watchdog sends the safe command while they keep coming.
    The first state being empty matters: the joint layout's cache of names started out empty too."""
    good, _ = runs
    proc = launch("npp-deploy")
    client = ros_client("empty_states_test")
    robot = StatePublisher(client)
    deploy = Deploy(client)
    deploy.deploy(good, state_timeout=0.3)
    client.wait_for(lambda: robot.publisher.get_subscription_count() > 0, 30.0, "npp-deploy's joint state subscription")
    bad = [([], [], []), (["joint_0"], [0.1], [0.0])]
    robot.keep_sending(bad, lambda: [0.0] in (c for _, c in deploy.commands), "the safe command")
    health = deploy.health_where(lambda h: count(h, "watchdog expiries") >= 1, "the watchdog expired")
    assert [c for _, c in deploy.commands] == [[0.0]] and count(health, "answered") == 0
    health = deploy.health_where(lambda h: "unusable" in h.doing, "states unusable")
    assert health.level == WARN and "states arrived but none was usable" in health.error, health
    assert count(health, "refused states") >= 2 and count(health, "answered") == 0
    log = launch.log(proc)
    assert "lacks the task's joints joint_0, joint_1 (it names: none)" in log
    assert "lacks the task's joints joint_1 (it names: joint_0)" in log
    assert "could not answer" not in log and "IndexError" not in log
    # A usable state is answered at once, and the refused ones around it change nothing.
    robot.send(["joint_0", "joint_1"], [0.1, 0.2], [0.0, 0.0])
    client.wait_for(lambda: any(any(c) for _, c in deploy.commands), 30.0, "the answer to the usable state")
    launch.assert_alive(proc)


def deploy_ctl(*args: str) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, "-m", "npp_ros_graph.tools.deploy_ctl", *args, "--timeout", "120"]
    return subprocess.run(command, capture_output=True, text=True, timeout=300)


def test_npp_deploy_ctl_drives_the_lifecycle_and_prints_the_gate_reason(runs, launch) -> None:
    good, bad = runs
    launch("npp-deploy", {"run_dir": str(bad["uncertified"][0]), "robot_model_fingerprint": FINGERPRINT}, "/refused")
    launch("npp-deploy", {"run_dir": str(good), "robot_model_fingerprint": FINGERPRINT, "state_timeout": 30.0})
    refused = deploy_ctl("configure", "--node", "/refused/npp_deploy")
    assert refused.returncode == 1 and "the run file holds no certificate" in refused.stderr, refused.stderr
    assert deploy_ctl("state", "--node", "/refused/npp_deploy").stdout.strip().endswith("unconfigured")
    cannot = deploy_ctl("activate", "--node", "/refused/npp_deploy")  # says why activate is not possible
    why = "cannot activate: the node is unconfigured because configure was refused: the run file holds no certificate"
    assert cannot.returncode == 1 and why in cannot.stderr, cannot.stderr
    for command, says in (("configure", "unconfigured -> inactive"), ("activate", "inactive -> active"),
                          ("stop", "stopped: safe command sent"), ("state", "inactive")):  # fmt: skip
        done = deploy_ctl(command)
        assert done.returncode == 0 and says in done.stdout, (command, done.stdout, done.stderr)
    gone = subprocess.run(
        [sys.executable, "-m", "npp_ros_graph.tools.deploy_ctl", "state", "--node", "/nobody", "--timeout", "2"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert gone.returncode == 2 and "not found" in gone.stderr


def test_configure_at_once_after_the_start_waits_for_the_robots_description(runs, launch, ros_client) -> None:
    """The tutorial's order, again and again: the robot publishes its latched description, npp-deploy starts, and
    configure comes as soon as the node answers. A fresh node may not have discovered the robot yet; configure
    waits for the description (description_timeout) instead of refusing for the lack of it.
    NPP_CONFIGURE_TRIES sets how many times (2 here; docs/tutorials/robot.md gives a figure for 20)."""
    good, _ = runs
    tries = int(os.environ.get("NPP_CONFIGURE_TRIES", "2"))
    launch("npp-robot")
    client = ros_client("configure_at_once")
    waits = []
    for attempt in range(tries):
        proc = launch("npp-deploy", {"run_dir": str(good), "max_epsilon": EPSILON})
        deploy = Deploy(client)  # the lifecycle service is called the moment it is discovered
        if not deploy.transition("configure"):
            health = deploy.health_where(lambda h: h.doing.startswith("configure refused"), "the refusal", since=0)
            pytest.fail(f"try {attempt + 1} of {tries}: {health.doing}")
        assert launch.stop(proc) == 0
        waited = re.search(r"configure waited ([\d.]+) s for the robot's description", launch.log(proc))
        waits.append(float(waited.group(1)) if waited else 0.0)
    print(f"\nconfigured {tries} of {tries} at once after the start; waited for the description in "
          f"{sum(w > 0 for w in waits)}: {', '.join(f'{w:.2f}' for w in waits)} s")  # fmt: skip


def test_every_deploy_command_has_help() -> None:
    for module in ("npp_ros_graph.nodes.deploy.node", "npp_ros_graph.tools.deploy_ctl", "npp_ros_graph.nodes.robot"):
        shown = subprocess.run([sys.executable, "-m", module, "--help"], capture_output=True, text=True, timeout=120)
        assert shown.returncode == 0 and ("usage" in shown.stdout.lower() or "subscribes" in shown.stdout), module


def test_a_changed_robot_publishes_its_own_model_and_the_gate_places_it_outside_the_set(
    runs, launch, ros_client, tmp_path: Path
) -> None:
    """npp-robot running gear x3 publishes the MJCF of that model (written from the nominal model, not scaled twice),
    and for a run on a set npp-deploy's gate refuses it, naming the gear, the robot's value and the range."""
    robots = with_robots(tmp_path / "robots")
    launch("npp-robot", {"gear_scale": 3.0})
    launch("npp-deploy")
    deploy = Deploy(ros_client("changed_robot_test"))
    deploy.has_description()
    deploy.set(run_dir=str(robots))
    seen = len(deploy.statuses)
    assert not deploy.transition("configure")
    health = deploy.health_where(lambda h: h.doing.startswith("configure refused"), "configure refused", since=seen)
    assert (
        "the robot's model lies outside the certified set (gear of actuator motor_0: the robot's 3 is x3 the "
        "certified 1, outside the certified range x[0.8, 1.2])"
    ) in health.doing, health.doing


def test_npp_trial_rehearses_the_certified_run_on_the_real_time_robot(runs, tmp_path: Path) -> None:
    """npp-trial deploys through the gate and runs npp-robot in real time from fresh s0, episode by episode."""
    good, _ = runs
    cmd = [sys.executable, "-m", "npp_ros_graph.bench.trial", str(good), "--episodes", "2", "--horizon", "50",
           "--out", str(tmp_path)]  # fmt: skip
    subprocess.run(cmd, check=True, timeout=600)
    out = json.loads((tmp_path / "trial.json").read_text())
    assert out["summary"]["episodes"] == 2 and len(out["episodes"]) == 2
    assert out["certificate"]["certify"] == "oracle"
    for episode in out["episodes"]:
        assert episode["replay_mismatches"] == 0, episode  # the robot moved exactly as the model does
        assert episode["first_command_answers_s0"], episode  # it waited at s0 for the policy's answer
        assert 0.0 < episode["fresh_command_share"] <= 1.0
        if episode["fresh_command_share"] == 1.0:  # no command missed its period: the in-process episode exactly
            assert episode["robot_return"] == episode["in_process_return"], episode
    assert "npp-trial" in (tmp_path / "trial.md").read_text()


def test_npp_trial_tries_a_run_on_a_set_of_robots_on_robots_drawn_from_it(runs, tmp_path: Path) -> None:
    """Each trial episode's npp-robot is a robot drawn from the run's set; the robot moves exactly as that robot's
    model does (its efforts replayed on it), and the episode names it."""
    on_set = with_robots(tmp_path / "on-set")
    cmd = [sys.executable, "-m", "npp_ros_graph.bench.trial", str(on_set), "--episodes", "2", "--horizon", "50",
           "--out", str(tmp_path / "trial")]  # fmt: skip
    subprocess.run(cmd, check=True, timeout=600)
    out = json.loads((tmp_path / "trial" / "trial.json").read_text())
    assert out["robots"].startswith("mass of")
    robots = [Robot.from_record(episode["robot"]) for episode in out["episodes"]]
    assert len(robots) == 2 and robots[0] != robots[1] and all(robot.changes_model for robot in robots)
    for episode in out["episodes"]:
        assert episode["replay_mismatches"] == 0, episode  # the robot is the drawn robot's model, exactly


def test_a_robot_outside_the_certified_set_is_found_by_the_monitor_and_stops_it_when_asked(
    runs, launch, ros_client, tmp_path: Path
) -> None:
    """A run certified on a set of robots (its metadata records the set: tests/deploy_runs.py) and an npp-robot
    whose gear is 3 times the model's while it publishes the nominal MJCF: the gate accepts the description
    (the nominal model lies in the set), the monitor then finds the transitions outside it: WARN with the
    measure and the bound, and with on_model_mismatch stop the node deactivates and sends the safe command."""
    robots = with_robots(tmp_path / "robots")
    launch("npp-robot", {"gear_scale": 3.0, "publish_description": "nominal"})
    proc = launch("npp-deploy")
    client = ros_client("monitor_test")
    deploy = Deploy(client)
    deploy.deploy(robots, fingerprint=None, state_timeout=2.0, on_model_mismatch="warn", monitor_window=3.0)
    health = deploy.health_where(lambda h: "leave the certified set" in h.doing, "the monitor's warning")
    assert health.level == WARN and "against the set's bound" in health.error, health
    assert "robot: the nominal model, inside the certified set" in str(health.values["policy"])
    assert "model monitor: " in launch.log(proc) and "corners of the certified set" in launch.log(proc)
    windowed = deploy.health_where(lambda h: "window identification" in h.values, "a window identified", timeout=120)
    assert "the set: " in str(windowed.values["window identification"]), windowed.values  # the fit's own verdict
    cleared = client.call(deploy.clearer, Trigger.Request())  # the operator has seen it; the robot is unchanged
    assert cleared.success and cleared.message.startswith("cleared: the robot's transitions leave"), cleared.message
    assert "the operator cleared the model monitor's finding" in launch.log(proc)

    assert deploy.transition("deactivate") and deploy.transition("cleanup")
    deploy.deploy(robots, fingerprint=None, state_timeout=2.0, on_model_mismatch="stop")
    health = deploy.health_where(lambda h: h.values["lifecycle state"] == "inactive", "it stopped")
    assert health.level == WARN and "left the certified set of robots" in health.doing, health.doing
    client.wait_for(lambda: deploy.commands[-1][1] == [0.0], 30.0, "the safe command")
    assert "on_model_mismatch is stop: deactivating" in launch.log(proc)


def test_npp_trial_outside_names_a_robot_by_its_parameters() -> None:
    from npp_ros_graph.bench.trial_outside import outside_robot

    plant = get_task(TASK).make_plant(SEED)
    assert outside_robot("gear=3", plant) == Robot((("gear", "motor_0", 3.0),))
    both = outside_robot("mass[body_1]=1.5, damping=2, delay=2", plant)
    assert both == Robot((("mass", "body_1", 1.5), ("damping", "joint_0", 2.0), ("damping", "joint_1", 2.0)), 2)
    assert outside_robot(both.record(), plant) == both
    for spec, says in (("gear=0", "positive"), ("gear=x", "positive"), ("torque=2", "no parameter 'torque'"),
                       ("mass[pole]=2", "no body 'pole'"), ("delay=1.5", "whole number"), ("gear", "is not"),
                       ('{"scales": []', "not a robot record")):  # fmt: skip
        with pytest.raises(ValueError, match=re.escape(says)):
            outside_robot(spec, plant)


def test_npp_trial_outside_refuses_a_robot_inside_the_set_and_a_run_on_the_exact_model(runs, tmp_path: Path) -> None:
    good, _ = runs
    on_set = with_robots(tmp_path / "on-set")
    for run, spec, says in ((on_set, "gear=1.1", "lies inside the certified set"), (good, "gear=3", "exact model")):
        cmd = [sys.executable, "-m", "npp_ros_graph.bench.trial", str(run), "--outside", spec, "--out", str(tmp_path)]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        assert done.returncode == 2 and says in done.stderr, done.stderr


@pytest.mark.long
def test_npp_trial_tries_a_run_on_a_set_on_a_robot_outside_it(runs, tmp_path: Path) -> None:
    """npp-trial --outside gear=3 on a run certified on a set: the gate refuses the robot's true description naming
    the gear, its value and the range; past the gate on the nominal description the monitor warns on /diagnostics
    (on_model_mismatch warn), and stops npp-deploy, its commands and the robot's efforts going to zero (stop)."""
    on_set = with_robots(tmp_path / "on-set")
    folder = tmp_path / "trial"
    cmd = [sys.executable, "-m", "npp_ros_graph.bench.trial", str(on_set), "--outside", "gear=3", "--horizon", "50",
           "--out", str(folder)]  # fmt: skip
    subprocess.run(cmd, check=True, timeout=900)
    out = json.loads((folder / "trial.json").read_text())
    outside = out["outside"]
    assert Robot.from_record(outside["robot"]) == Robot((("gear", "motor_0", 3.0),))
    gate, warn, stopped = outside["gate"], outside["warn"], outside["stop"]
    assert gate["refused"] and gate["publish_description"] == "robot", gate
    assert (
        "gear of actuator motor_0: the robot's 3 is x3 the certified 1, outside the certified range x[0.8, 1.2]"
    ) in gate["reason"], gate
    assert warn["warned"] and warn["publish_description"] == "nominal", warn
    assert "leave the certified set of robots" in warn["status"] and "against the set's bound" in warn["error"], warn
    assert 0 < warn["warn_after_s"] < 600 and warn["warn_after_steps"] >= 1, warn  # no bound on how soon
    episode = warn["episode"]
    assert episode["replay_mismatches"] == 0 and episode["first_command_answers_s0"], episode  # the gear x3 robot
    assert stopped["stopped"] and stopped["commands_zero"] and stopped["safe_command"] == [0.0], stopped
    assert "left the certified set of robots" in stopped["status"], stopped
    assert stopped["commands_after_safe"] == 0 and stopped["robot_steps_zero"] >= 1, stopped
    assert 0 < stopped["stop_after_s"] < 600, stopped
    text = (folder / "trial.md").read_text()
    assert "--outside gear=3" in text and "outside its set" in text
