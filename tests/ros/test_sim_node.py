"""The sim node over real DDS: resets, lockstep stepping, episode results, ignored bad actions."""

from __future__ import annotations

import math
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from npp_interfaces.msg import EpisodeResult, PlantDescription
from npp_interfaces.srv import ResetEpisode
from rclpy.client import Client
from rclpy.publisher import Publisher
from sensor_msgs.msg import JointState

from npp_ros.tasks.builtin.lqr import LQRExpert, LQRPlant, episode_rng, sample_initial_state
from npp_ros.tasks.rollout import rollout
from npp_ros.tasks.uncertainty import Robot
from npp_ros_graph.transport.message_seal import RunSeal
from npp_ros_graph.transport.topics import (
    ACTION,
    CONTROL_QOS,
    LATCHED_READER_QOS,
    PLANT,
    REPORT_QOS,
    RESET_SERVICE,
    ROLLOUT_DONE,
    STATE,
)

if TYPE_CHECKING:
    from tests.ros.conftest import Launcher, RosClient

TIMEOUT = 60.0
HORIZON = 20
DT_NS = 30_000_000  # lqr timestep 0.03 s
QUIET_S = 0.5  # how long "nothing happens" is watched for
RUN = "sim-test-run"  # the identity of the run whose supervisor the test plays


@dataclass
class SimHandle:
    """The test's side of the sim: a client node with its reset client, inboxes and action publisher."""

    launcher: Launcher
    proc: subprocess.Popen[bytes]
    client: RosClient
    reset: Client
    action_pub: Publisher
    received: list[JointState]  # every state as it arrived (see states)
    results: list[EpisodeResult]
    plant: PlantDescription
    seal: RunSeal  # the run's seal for the plant: the test plays this run's supervisor and policy
    episode: int = 0

    @property
    def states(self) -> list[JointState]:
        """The states received, each once: reset_to repeats a reset whose first state is slow to come,
        and the sim then sends that state again (same stamp, values and sealed context), maybe late."""
        unique: list[JointState] = []
        for msg in self.received:
            if not (unique and same_state(unique[-1], msg)):
                unique.append(msg)
        return unique

    def reset_to(self, state: list[float], episode: int = 0, robot: str = "") -> ResetEpisode.Response:
        """Reset (on a drawn robot's record, '' nominal) and wait for the episode's first state (re-sent if our
        subscription matched late)."""
        deadline = time.monotonic() + TIMEOUT
        self.episode = episode
        while True:
            seen = len(self.states)
            request = self.seal.seal(ResetEpisode.Request(state=state, episode=episode, run=RUN, robot=robot))
            answer = self.client.call(self.reset, request, TIMEOUT)
            self.seal.check(answer, "the reset answer", answering=request)
            if not answer.success:
                return answer
            try:
                self.client.wait_for(lambda n=seen: len(self.states) > n, 3.0)
                return answer
            except TimeoutError:
                if time.monotonic() > deadline:
                    raise

    def act(self, effort: list[float], stamp: Time, names: list[str] | None = None, seal: RunSeal | None = None,
            context: str | None = None) -> None:  # fmt: skip
        """Publish an action answering `stamp`, sealed as this run's policy would (or with `seal`, `context`)."""
        msg = JointState(effort=effort, name=self.plant.actuated_joint_names if names is None else names)
        msg.header.stamp = stamp
        self.action_pub.publish((seal or self.seal).seal_header(msg, context or f"{self.episode}/0"))

    def next_state(self, seen: int) -> JointState:
        self.client.wait_for(lambda: len(self.states) > seen, TIMEOUT, "the next state")
        return self.states[seen]

    def nothing_arrives(self, seen_states: int, seen_results: int = -1) -> bool:
        deadline = time.monotonic() + QUIET_S
        self.client.wait_for(lambda: time.monotonic() > deadline, QUIET_S + 5)
        return len(self.states) == seen_states and (seen_results < 0 or len(self.results) == seen_results)


def same_state(a: JointState, b: JointState) -> bool:
    return (a.header.frame_id, ns(a.header.stamp), list(a.position), list(a.velocity)) == (
        b.header.frame_id, ns(b.header.stamp), list(b.position), list(b.velocity)
    )  # fmt: skip


def as_state(msg: JointState) -> np.ndarray:
    return np.concatenate([np.asarray(msg.position), np.asarray(msg.velocity)])


def ns(stamp: Time) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


@pytest.fixture(scope="module")
def sim(launch_module: Launcher, ros_client_module: Callable[..., RosClient]) -> SimHandle:
    """One sim (lqr_2_1, seed 0, horizon 20) for the module: every test starts with its own reset."""
    launch = launch_module
    proc = launch("npp-sim", {"task": "lqr_2_1", "seed": 0, "horizon": HORIZON})
    client = ros_client_module("sim_test_client")
    plants = client.collect(PlantDescription, PLANT, LATCHED_READER_QOS)
    states = client.collect(JointState, STATE, CONTROL_QOS)
    results = client.collect(EpisodeResult, ROLLOUT_DONE, REPORT_QOS)
    action_pub = client.node.create_publisher(JointState, ACTION, CONTROL_QOS)
    reset = client.client(ResetEpisode, RESET_SERVICE, TIMEOUT)
    client.wait_for(lambda: bool(plants), TIMEOUT, "the latched plant description")
    client.wait_for(lambda: action_pub.get_subscription_count() > 0, TIMEOUT, "the sim to subscribe to actions")
    launch.assert_alive(proc)
    run_seal = RunSeal.from_environment()
    run_seal.check(plants[-1], "the plant description")
    seal = run_seal.for_plant(plants[-1].model_sha256).for_run(RUN)
    return SimHandle(launch, proc, client, reset, action_pub, states, results, plants[-1], seal)


def test_plant_description(sim: SimHandle) -> None:
    plant = LQRPlant("lqr_2_1", 0)
    d = sim.plant
    assert (d.task, d.seed, d.horizon, d.state_dim, d.action_dim) == ("lqr_2_1", 0, HORIZON, 4, 1)
    assert d.timestep == pytest.approx(0.03)
    assert list(d.joint_names) == plant.joint_names and list(d.actuated_joint_names) == plant.actuated_joint_names
    assert d.model_sha256 == plant.model_sha256()


def test_lockstep_episode_follows_the_plant_and_reports_its_return(sim: SimHandle, expert_2_1: LQRExpert) -> None:
    s0 = [0.4, -0.3, 0.2, 0.1]
    answer = sim.reset_to(s0, episode=5)
    assert answer.success, answer.message
    np.testing.assert_array_equal(answer.state, s0)
    first = sim.states[-1]
    assert list(first.name) == list(sim.plant.joint_names)
    np.testing.assert_array_equal(first.position, s0[:2])
    np.testing.assert_array_equal(first.velocity, s0[2:])
    assert (first.header.stamp.sec, first.header.stamp.nanosec) == (0, 0)

    actions = np.random.default_rng(11).normal(scale=0.5, size=(HORIZON, 1))
    visited = [as_state(first)]
    msg = first
    for t in range(HORIZON):
        seen = len(sim.states)
        sim.act(actions[t].tolist(), msg.header.stamp, names=[] if t % 2 else None)  # names are optional
        if t == HORIZON - 1:
            break
        msg = sim.next_state(seen)
        assert ns(msg.header.stamp) == (t + 1) * DT_NS
        visited.append(as_state(msg))
        np.testing.assert_allclose(
            visited[-1], expert_2_1.A @ visited[-2] + expert_2_1.B @ actions[t], rtol=0, atol=1e-9
        )

    sim.client.wait_for(lambda: bool(sim.results), TIMEOUT, "the episode result")
    result = sim.results[-1]
    assert (result.episode, result.steps) == (5, HORIZON)
    np.testing.assert_array_equal(result.initial_state, s0)
    assert not result.expert_value_known
    replay = rollout(LQRPlant("lqr_2_1", 0), _replayer(actions), s0, HORIZON)
    np.testing.assert_allclose(replay.states, np.array(visited), rtol=0, atol=1e-12)
    assert result.policy_return == replay.total_return  # the core's summation: equal to the in-process return

    # The episode is over: even an action answering the last state moves nothing.
    sim.act([0.0], msg.header.stamp)
    assert sim.nothing_arrives(len(sim.states), len(sim.results))

    # The same reset again (a supervisor that lost the result in a pause asks where the episode stands): the
    # sim does not restart the episode, it sends the finished episode's result again.
    states, results = len(sim.states), len(sim.results)
    again = sim.seal.seal(ResetEpisode.Request(state=s0, episode=5, run=RUN))
    answer = sim.client.call(sim.reset, again, TIMEOUT)
    sim.seal.check(answer, "the reset answer", answering=again)
    assert answer.success and "result sent again" in answer.message, answer.message
    sim.client.wait_for(lambda: len(sim.results) > results, TIMEOUT, "the result sent again")
    assert sim.results[-1] == result
    assert sim.nothing_arrives(states)


def _drive(sim: SimHandle, controller: Callable[[np.ndarray], np.ndarray]) -> EpisodeResult:
    """Answer each state the sim publishes with ``controller(state)`` until it reports the episode."""
    results = len(sim.results)
    msg = sim.states[-1]
    for t in range(HORIZON):
        seen = len(sim.states)
        sim.act(controller(as_state(msg)).tolist(), msg.header.stamp)
        if t < HORIZON - 1:
            msg = sim.next_state(seen)
    sim.client.wait_for(lambda: len(sim.results) > results, TIMEOUT, "the episode result")
    return sim.results[-1]


def test_an_episode_on_a_drawn_robot_returns_the_in_process_rollouts_return(
    sim: SimHandle, expert_2_1: LQRExpert
) -> None:
    """The reset's robot is the plant for that episode only: its masses and gear, its delayed commands and the noise
    on the states the policy reads, as rollout() applies them, so the return is the in-process one bit for bit."""
    robot = Robot(
        (("mass", "body_0", 1.3), ("gear", "motor_0", 0.7), ("damping", "joint_1", 1.4)), 2, 0.01, noise_seed=5
    )
    s0 = [0.4, -0.3, 0.2, 0.1]
    controller = lambda x: -expert_2_1.K @ x  # noqa: E731  # reads the noisy states it is sent
    answer = sim.reset_to(s0, episode=7, robot=robot.record())
    assert answer.success and "on the robot" in answer.message, answer.message
    on_robot = _drive(sim, controller)
    assert (on_robot.episode, on_robot.robot) == (7, robot.record())  # the report names the robot it ran
    plant = LQRPlant("lqr_2_1", 0)
    assert on_robot.policy_return == rollout(plant, controller, s0, HORIZON, robot).total_return

    # The next episode, nominal: the sim's model is the task's again, and so is the return.
    assert sim.reset_to(s0, episode=8).success
    nominal = _drive(sim, controller)
    assert nominal.robot == "" and nominal.policy_return == rollout(plant, controller, s0, HORIZON).total_return
    assert nominal.policy_return != on_robot.policy_return

    # A damaged record is refused with the reason, and starts nothing.
    refused = sim.reset_to(s0, episode=9, robot='{"scales": "no"}')
    assert not refused.success and "not a robot record" in refused.message, refused.message
    foreign = sim.reset_to(s0, episode=9, robot=Robot((("mass", "pole", 1.1),)).record())  # another model's body
    assert not foreign.success and "no body 'pole'" in foreign.message, foreign.message


def _replayer(actions: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """A controller that plays back recorded actions in order."""
    it = iter(actions)
    return lambda _state: next(it)


def test_stale_and_malformed_actions_are_ignored(sim: SimHandle) -> None:
    answer = sim.reset_to([0.5, 0.0, 0.0, 0.0])
    assert answer.success, answer.message
    first = sim.states[-1]
    seen = len(sim.states)
    stale = Time(sec=99, nanosec=0)
    bad: list[tuple[list[float], Time, list[str] | None]] = [
        ([0.1], stale, None),  # answers a state that was never published
        ([0.1], first.header.stamp, ["joint_1"]),  # not the actuated joint
        ([0.1, 0.2], first.header.stamp, None),  # too many entries
        ([], first.header.stamp, None),  # none
        ([math.nan], first.header.stamp, None),
        ([math.inf], first.header.stamp, None),
    ]
    for effort, stamp, names in bad:
        sim.act(effort, stamp, names)
    assert sim.nothing_arrives(seen)
    sim.launcher.assert_alive(sim.proc)
    for fragment in ("stale", "wrong joint names", "effort has 2 entries", "effort is empty", "effort must be finite"):
        sim.client.wait_for(lambda f=fragment: f in sim.launcher.log(sim.proc), 10.0, f"a warning about {fragment!r}")

    sim.act([0.1], first.header.stamp)  # the proper answer still works
    assert ns(sim.next_state(seen).header.stamp) == DT_NS


def test_resets(sim: SimHandle) -> None:
    answer = sim.reset_to([0.1, 0.2, 0.3])
    assert not answer.success
    assert "3 entries" in answer.message and "expected 4" in answer.message, answer.message
    answer = sim.reset_to([0.1, math.nan, 0.3, 0.4])
    assert not answer.success and "state[1] = nan" in answer.message, answer.message

    answer = sim.reset_to([], episode=7)  # s0 ~ rho, reproducible per (seed, episode)
    assert answer.success, answer.message
    expected = sample_initial_state("lqr_2_1", episode_rng(0, 7))
    np.testing.assert_array_equal(answer.state, expected)
    np.testing.assert_array_equal(as_state(sim.states[-1]), expected)
    assert ns(sim.states[-1].header.stamp) == 0


def test_only_this_runs_resets_and_actions_move_the_plant(sim: SimHandle) -> None:
    """A stray publisher or another run's supervisor on the domain cannot reset or drive the plant."""
    answer = sim.reset_to([0.3, 0.0, 0.0, 0.0], episode=3)
    assert answer.success, answer.message
    first, seen = sim.states[-1], len(sim.states)
    assert sim.seal.check_header(first, "the state") == "3"

    stray = ResetEpisode.Request(state=[0.9, 0.9, 0.9, 0.9], episode=4, run=RUN)  # unsealed: a user's hand-made call
    refused = sim.client.call(sim.reset, stray, TIMEOUT)
    assert not refused.success and "seal" in refused.message, refused.message
    other_run = RunSeal(b"another run's key", private=True).for_plant(sim.plant.model_sha256).for_run(RUN)
    refused = sim.client.call(sim.reset, other_run.seal(stray), TIMEOUT)
    assert not refused.success and "seal" in refused.message, refused.message

    unsealed = JointState(effort=[5.0], name=list(sim.plant.actuated_joint_names))
    unsealed.header.stamp = first.header.stamp
    sim.action_pub.publish(unsealed)  # the state's own stamp, no seal
    sim.act([5.0], first.header.stamp, seal=other_run)  # another run's key
    sim.act([5.0], first.header.stamp, context="2/0")  # this run's key, an earlier episode with the same stamp
    fragment = "does not carry this run's seal"
    sim.client.wait_for(lambda: fragment in sim.launcher.log(sim.proc), 10.0, f"a warning about {fragment!r}")
    deadline = time.monotonic() + QUIET_S
    sim.client.wait_for(lambda: time.monotonic() > deadline, QUIET_S + 5)
    # Nothing moved: at most the unanswered first state was sent again.
    assert all(ns(msg.header.stamp) == 0 for msg in sim.states[seen:])
    assert "episode 3 abandoned" not in sim.launcher.log(sim.proc)  # the stray resets were refused

    seen = len(sim.states)
    sim.act([0.1], first.header.stamp)  # this run's answer still moves the plant
    sim.client.wait_for(lambda: any(ns(m.header.stamp) == DT_NS for m in sim.states[seen:]), TIMEOUT, "step 1")
