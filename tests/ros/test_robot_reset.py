"""npp-robot's reset service and its clock, as separate processes over DDS: a reset puts the plant at the asked state
and answers it as measured, the robot holds it until the next command, which it applies at once; a bad state is
refused with its reason and changes nothing; stamps follow the robot's clock (dt apart, faster than the wall clock
with time_scale, never back across resets; a held start repeats its measurement's stamp); the robot it runs is not
told through its parameters.

Three robots live for the module: real time at time_scale 1 on the default topics; time_scale 5 with an action
delay and state noise under /fast; lockstep under /step. No test fails because the machine is busy: stamps are
compared, and the one wall-clock figure (time_scale's speed) is excused by the robot's own overrun count."""

from __future__ import annotations

import itertools
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from npp_interfaces.srv import ResetRobot
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from npp_ros.tasks.registry import get_task
from npp_ros_graph.runtime.diagnostics import DIAGNOSTICS, DIAGNOSTICS_QOS, Health, health_of
from npp_ros_graph.transport.convert import float64_array, stamp_ns
from npp_ros_graph.transport.topics import CONTROL_QOS, FORWARD_COMMANDS, JOINT_STATES

TASK, SEED = "lqr_2_1", 0
START_TIMEOUT_S = 120.0  # processes importing rclpy and MuJoCo on a shared, busy machine
WAIT_S = 60.0  # for what must come: a busy machine only makes it slower
OWN_START = np.array([0.3, -0.2, 0.0, 0.1])  # robot A's initial_state: where an empty reset brings it
ASKED = np.array([0.5, 0.25, -0.1, 0.2])
NOISE = 1e-3  # robot B's state noise
KEEP_ALL = QoSProfile(depth=100_000, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)


@dataclass(frozen=True)
class Seen:
    """One joint state as the test received it."""

    ns: int  # its stamp
    state: np.ndarray  # qpos then qvel
    effort: float
    arrived: float  # the test's monotonic clock


class RobotHandle:
    """The test's side of one npp-robot: its joint states, its command topic, its reset service, its statuses."""

    def __init__(self, client: Any, namespace: str = "") -> None:
        self.client, self.namespace = client, namespace
        self.seen: list[Seen] = []
        self.statuses: list[Health] = []
        states = f"{namespace}/joint_states" if namespace else JOINT_STATES
        commands = f"{namespace}/commands" if namespace else FORWARD_COMMANDS
        self.subscription = client.node.create_subscription(JointState, states, self._on_state, KEEP_ALL)
        self.publisher = client.node.create_publisher(Float64MultiArray, commands, CONTROL_QOS)
        client.node.create_subscription(DiagnosticArray, DIAGNOSTICS, self._on_diagnostics, DIAGNOSTICS_QOS)
        self.resetter = client.client(ResetRobot, f"{namespace}/npp_robot/reset", START_TIMEOUT_S)
        client.wait_for(lambda: self.publisher.get_subscription_count() > 0, WAIT_S, f"{namespace} command reader")
        client.wait_for(lambda: self.subscription.get_publisher_count() > 0, WAIT_S, f"{namespace} joint states")

    def _on_state(self, msg: JointState) -> None:
        state = np.concatenate([msg.position, msg.velocity])
        self.seen.append(Seen(stamp_ns(msg.header.stamp), state, float(msg.effort[0]), time.monotonic()))

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        self.statuses += [health_of(s) for s in msg.status if s.name == f"{self.namespace}/npp_robot"]

    def reset(self, state: Any = ()) -> ResetRobot.Response:
        return self.client.call(self.resetter, ResetRobot.Request(state=float64_array(state)))

    def command(self, value: float) -> None:
        self.publisher.publish(Float64MultiArray(data=float64_array([value])))

    def after(self, ns: int) -> list[Seen]:
        return [s for s in self.seen if s.ns > ns]

    def wait_after(self, ns: int, count: int, label: str, holds: Any = None) -> list[Seen]:
        """The states stamped after ``ns``, once ``count`` of them (for which ``holds``, if given) have come."""
        ok = holds or (lambda _: True)
        self.client.wait_for(lambda: sum(map(ok, self.after(ns))) >= count, WAIT_S, label)
        return self.after(ns)

    def held(self, response: ResetRobot.Response, count: int = 6) -> list[Seen]:
        """The states from the reset on, once ``count`` have come (republished every 50 ms while it holds)."""
        at = stamp_ns(response.stamp)
        return self.wait_after(at - 1, count, f"{count} states of {self.namespace or 'A'} after its reset")

    def status(self, holds: Any, label: str) -> Health:
        start = len(self.statuses)
        self.client.wait_for(lambda: any(holds(h) for h in self.statuses[start:]), WAIT_S, label)
        return next(h for h in self.statuses[start:] if holds(h))


@dataclass(frozen=True)
class Robots:
    a: RobotHandle  # real time, time_scale 1, initial_state OWN_START
    b: RobotHandle  # real time, time_scale 5, action delay 1, state noise
    c: RobotHandle  # lockstep
    dt: float


def own_topics(namespace: str) -> dict[str, str]:
    return {"joint_states_topic": f"{namespace}/joint_states", "command_topic": f"{namespace}/commands",
            "robot_description_topic": f"{namespace}/robot_description"}  # fmt: skip


@pytest.fixture(scope="module")
def robots(launch_module: Any, ros_client_module: Any) -> Iterator[Robots]:
    start = ",".join(repr(float(x)) for x in OWN_START)
    launch_module("npp-robot", {"task": TASK, "seed": SEED, "initial_state": start})
    launch_module("npp-robot", {"task": TASK, "seed": SEED, "time_scale": 5.0, "action_delay": 1,
                                "state_noise": NOISE, **own_topics("/fast")}, namespace="/fast")  # fmt: skip
    launch_module("npp-robot", {"task": TASK, "seed": SEED, "lockstep": True, **own_topics("/step")}, "/step")
    client = ros_client_module("robot_reset_test")
    handles = [RobotHandle(client, namespace) for namespace in ("", "/fast", "/step")]
    yield Robots(*handles, get_task(TASK).make_plant(SEED).dt)


def gaps(seen: list[Seen]) -> list[int]:
    """The stamp differences of consecutive states, nanoseconds."""
    return [y.ns - x.ns for x, y in itertools.pairwise(seen)]


def one_step(start: np.ndarray, action: float) -> np.ndarray:
    plant = get_task(TASK).make_plant(SEED)
    plant.reset(start)
    plant.step([action])
    return plant.state()


def test_a_reset_answers_the_state_as_measured_and_holds_it_until_a_command(robots: Robots) -> None:
    a = robots.a
    a.command(0.8)  # a command in force before the reset: the reset forgets it
    a.wait_after(0, 1, "a step on the command", lambda s: s.effort == 0.8)
    answer = a.reset(ASKED)
    assert answer.success, answer.message
    np.testing.assert_array_equal(answer.state, ASKED)
    held = a.held(answer)
    assert held[0].ns == stamp_ns(answer.stamp)  # the state it answered is the one it published
    for seen in held:
        np.testing.assert_array_equal(seen.state, ASKED)  # no step while no command comes
        assert seen.effort == 0.0
    assert set(gaps(held)) == {0}  # held: the answered measurement again, its stamp with it
    # A command after the reset is applied at once: the first step is the model's step from the start on it.
    a.command(1.0)
    moved = a.wait_after(stamp_ns(answer.stamp), 5, "five steps on the command", lambda s: s.effort == 1.0)
    stepped = [s for s in moved if s.effort == 1.0]
    first = moved.index(stepped[0])
    assert all(s.effort == 0.0 for s in moved[:first])  # before it: the held start only
    np.testing.assert_array_equal(stepped[0].state, one_step(ASKED, 1.0))
    dt_ns = round(robots.dt * 1e9)
    assert gaps(stepped) == [dt_ns] * (len(stepped) - 1)
    # time_scale 1: the robot's clock is the wall clock's pace, never ahead of it.
    assert all(s.ns * 1e-9 <= time.time() + 0.5 for s in moved)


def test_a_bad_state_is_refused_with_its_reason_and_changes_nothing(robots: Robots) -> None:
    a = robots.a
    answer = a.reset(ASKED)
    assert answer.success, answer.message
    a.held(answer, 2)
    for bad, says in (([0.1, 0.2, 0.3], "state has 3 entries, expected 4 (qpos then qvel of joint_0, joint_1"),
                      ([0.1, float("nan"), 0.0, 0.0], "state must be finite: state[1] = nan"),
                      ([0.0, 0.0, float("inf"), 0.0], "state must be finite: state[2] = inf")):  # fmt: skip
        refused = a.reset(bad)
        assert not refused.success and says in refused.message, refused.message
        assert "\n" not in refused.message and list(refused.state) == []
    after = a.held(answer, 10)  # still held at the start it had, as it was measured
    for seen in after:
        np.testing.assert_array_equal(seen.state, ASKED)
        assert seen.effort == 0.0
    assert set(gaps(after)) == {0}
    health = a.status(lambda h: int(h.values["refused resets"]) >= 3, "the refusals counted")
    assert int(health.values["resets"]) >= 2 and "holding the start" in health.doing, health


def test_an_empty_state_resets_to_the_robots_own_start_and_stamps_never_go_back(robots: Robots) -> None:
    a = robots.a
    answers = []
    for asked, value in ((ASKED, 0.5), ((), -0.5), ((), None), (OWN_START * 2, 0.2), ((), None)):
        answer = a.reset(asked)
        assert answer.success, answer.message
        want = OWN_START if len(asked) == 0 else asked
        np.testing.assert_array_equal(answer.state, want)
        np.testing.assert_array_equal(a.held(answer, 1)[0].state, want)
        if value is not None:
            a.command(value)
            a.wait_after(stamp_ns(answer.stamp), 2, "steps after the reset", lambda s, v=value: s.effort == v)
        answers.append(stamp_ns(answer.stamp))
    assert answers == sorted(set(answers))  # each reset's stamp after the one before
    assert min(gaps(a.seen)) >= 0, "a stamp went back"  # every state the module saw from robot A, in their order
    assert int(a.status(lambda h: int(h.values["resets"]) >= 5, "the resets counted").values["resets"]) >= 5


def test_time_scale_5_runs_faster_than_the_wall_clock_with_states_dt_apart(robots: Robots) -> None:
    b, dt_ns = robots.b, round(robots.dt * 1e9)
    b.command(0.7)  # in the delay queue when the reset comes: the reset empties it
    b.wait_after(0, 1, "a step on the command", lambda s: s.effort == 0.7)
    overruns = int(b.status(lambda h: "overruns" in h.values, "a status").values["overruns"])
    answer = b.reset(ASKED)
    assert answer.success, answer.message
    at = stamp_ns(answer.stamp)
    first = b.held(answer, 1)[0]
    assert first.ns == at
    np.testing.assert_array_equal(first.state, answer.state)  # answered as measured: its noise included
    assert 0 < np.abs(np.asarray(answer.state) - ASKED).max() < 10 * NOISE
    b.command(0.3)
    steps = 100
    seen = b.wait_after(at, steps + 1, f"{steps} steps on the command", lambda s: s.effort == 0.3)
    on = [s for s in seen if s.effort == 0.3]
    # One step with the delay's zero before the command reaches the actuator, never the 0.7 of before the reset.
    assert all(s.effort == 0.0 for s in seen[: seen.index(on[0])])
    assert seen[seen.index(on[0]) - 1].ns == on[0].ns - dt_ns
    assert gaps(on) == [dt_ns] * (len(on) - 1)
    robot_s = (on[-1].ns - on[0].ns) * 1e-9
    wall_s = on[-1].arrived - on[0].arrived
    now = int(b.status(lambda h: "overruns" in h.values, "a status").values["overruns"])
    print(f"time_scale 5: {robot_s:.2f} s of robot time in {wall_s:.2f} s wall, {now - overruns} overruns")
    assert robot_s > 2 * wall_s or now > overruns, (robot_s, wall_s)  # only a stalled machine may slow it
    empty = b.reset()  # its own start: s0 of episode 0, as measured
    assert empty.success and np.abs(np.asarray(empty.state) - get_task(TASK).initial_state(SEED, 0)).max() < 10 * NOISE
    assert stamp_ns(empty.stamp) > on[-1].ns


def test_a_lockstep_reset_publishes_the_start_with_a_new_stamp_and_steps_on_commands(robots: Robots) -> None:
    c, dt_ns = robots.c, round(robots.dt * 1e9)
    c.wait_after(-1, 1, "lockstep's first state")
    c.command(0.4)
    c.wait_after(-1, 1, "a lockstep step", lambda s: s.effort == 0.4)
    before = c.seen[-1].ns
    answer = c.reset(ASKED)
    assert answer.success, answer.message
    np.testing.assert_array_equal(answer.state, ASKED)
    assert stamp_ns(answer.stamp) > before
    start = c.held(answer, 1)[0]
    assert start.ns == stamp_ns(answer.stamp) and start.effort == 0.0
    c.command(-1.0)
    stepped = c.wait_after(start.ns, 1, "the step from the start")[0]
    assert stepped.ns == start.ns + dt_ns and stepped.effort == -1.0
    np.testing.assert_array_equal(stepped.state, one_step(ASKED, -1.0))


def test_the_robot_it_runs_is_not_told_through_its_parameters(robots: Robots) -> None:
    """Robot B's delay and noise are parameters: it serves none (no parameter services) and announces none on
    /parameter_events, where rclpy would publish each with its value."""
    node = robots.b.client.node
    for namespace in ("/", "/fast", "/step"):
        services = dict(node.get_service_names_and_types_by_node("npp_robot", namespace))
        prefix = namespace.rstrip("/")
        assert f"{prefix}/npp_robot/reset" in services, services
        assert not [name for name in services if "parameter" in name], services
    announcers = [(p.node_namespace, p.node_name) for p in node.get_publishers_info_by_topic("/parameter_events")]
    assert not [who for who in announcers if who[1] == "npp_robot"], announcers
