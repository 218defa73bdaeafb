"""Load: many expert clients at once, and a state stream faster than the policy answers.

- 8 client nodes send 200 expert requests, all in flight at once. Every request is accounted for:
  answered with the closed-form trajectory, or refused with "busy:"; none may be lost silently. With
  the default queue (100) and with a tiny one (2), where most requests must be refused as busy.
- The policy under a flood of states answers only the newest, drops the ones overtaken while it
  was busy, reports the count on /npp/policy/dropped_states and in its log, and builds no backlog.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from expert_checks import TIMEOUT, check_good, request, wait_until_modelling
from npp_interfaces.msg import PlantDescription
from npp_interfaces.srv import ExpertTrajectory, GetTrajectories
from sensor_msgs.msg import JointState
from std_msgs.msg import UInt32, UInt64

from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import Dataset
from npp_ros.policy.feedback import ControlSpace
from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.policy.spec import PolicySpec
from npp_ros.tasks.builtin.lqr import LQRExpert, LQRPlant, episode_rng, sample_initial_state
from npp_ros_graph.transport.convert import policy_spec_to_msg, trajectory_to_msg
from npp_ros_graph.transport.message_seal import RunSeal
from npp_ros_graph.transport.topics import (
    ACTION,
    BUSY,
    CONTROL_QOS,
    DATASET_SERVICE,
    EXPERT_SERVICE,
    LATCHED_QOS,
    LATCHED_READER_QOS,
    PLANT,
    POLICY_DROPPED,
    POLICY_STATUS,
    REPORT_QOS,
    STATE,
)

if TYPE_CHECKING:
    from tests.ros.conftest import Launcher, RosClient

CLIENTS = 8
REQUESTS = 200
FLOOD = 3000


@pytest.mark.parametrize(("max_queue", "max_horizon"), [(100, 1000), (2, 10_000)])
def test_expert_serves_8_clients_200_requests_and_loses_none(
    launch: Launcher, ros_client: Callable[..., RosClient], expert_2_1: LQRExpert, max_queue: int, max_horizon: int
) -> None:
    launch("npp-sim", {"task": "lqr_2_1", "seed": 0})
    expert = launch("npp-expert", {"max_queue": max_queue})
    clients = [ros_client(f"load_client_{i}") for i in range(CLIENTS)]
    services = [c.client(ExpertTrajectory, EXPERT_SERVICE, TIMEOUT) for c in clients]
    for client, service in zip(clients, services, strict=True):
        wait_until_modelling(client, service)  # also proves each client's response path is matched
    outcomes: list[Counter[str]] = [Counter() for _ in clients]
    errors: list[BaseException] = []
    start = threading.Barrier(CLIENTS)

    def work(i: int) -> None:
        try:
            rng = np.random.default_rng(1000 + i)
            cases = [(rng.normal(size=4), int(rng.integers(1, max_horizon + 1))) for _ in range(REQUESTS // CLIENTS)]
            start.wait()
            pending = [(s0, h, services[i].call_async(request(s0, h))) for s0, h in cases]  # all in flight
            deadline = time.monotonic() + 300.0  # a hang guard, not a speed requirement
            for s0, horizon, future in pending:
                try:
                    answer = clients[i].wait_for(future, max(deadline - time.monotonic(), 0.1), "an answer")
                except TimeoutError:
                    outcomes[i]["lost"] += 1
                    continue
                if not answer.success and answer.message.startswith(BUSY):
                    assert f"max_queue {max_queue}" in answer.message, answer.message
                    outcomes[i]["busy"] += 1
                    continue
                check_good(answer, expert_2_1, s0, horizon)
                outcomes[i]["answered correctly"] += 1
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(CLIENTS)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(400.0)
    assert not errors, errors
    total = sum(outcomes, Counter())
    print(f"\nexpert load (max_queue {max_queue}): {CLIENTS} clients, {REQUESTS} requests: {dict(total)}")
    assert total["lost"] == 0
    assert total["answered correctly"] + total["busy"] == REQUESTS
    assert total["answered correctly"] >= 1
    if max_queue == 2:  # 200 requests at once, of up to 10,000 steps each, cannot all fit a queue of 2
        assert total["busy"] > 0
    assert all(sum(c.values()) == REQUESTS // CLIENTS for c in outcomes)
    launch.assert_alive(expert)
    s0 = np.array([0.2, -0.1, 0.0, 0.3])
    check_good(clients[0].call(services[0], request(s0, 20)), expert_2_1, s0, 20)


def _dataset(expert: LQRExpert, trajectories: int) -> Dataset:
    data = Dataset(4, 1)
    for k in range(trajectories):
        data.append(expert.trajectory(sample_initial_state("lqr_2_1", episode_rng(5, k))))
    return data


def test_policy_under_a_state_flood_drops_stale_states_and_reports_them(
    launch: Launcher, ros_client: Callable[..., RosClient], expert_2_1: LQRExpert
) -> None:
    """The test plays sim and supervisor: a plant description, a dataset service, then a flood of states."""
    ns = "/flood"
    data = _dataset(expert_2_1, 20)
    lipschitz = float(expert_2_1.analytic_lipschitz().value)
    local = NonparametricPolicy(data, lipschitz)
    tester = ros_client("flood_tester", namespace=ns)
    node = tester.node
    plant = LQRPlant("lqr_2_1", 0)
    plant_pub = node.create_publisher(PlantDescription, PLANT, LATCHED_QOS)
    run_seal = RunSeal.from_environment()  # the test plays this run's sim and supervisor
    run = "load-test-run"
    seal = run_seal.for_plant(plant.model_sha256()).for_run(run)
    plant_pub.publish(
        run_seal.seal(PlantDescription(
            task="lqr_2_1", seed=0, horizon=1000, timestep=plant.dt, state_dim=4, action_dim=1,
            joint_names=plant.joint_names, actuated_joint_names=plant.actuated_joint_names,
            model_sha256=plant.model_sha256(),
        ))
    )  # fmt: skip

    control = ControlSpace.of(4, (), [-np.inf], [np.inf])  # the lqr plant: no angles, no actuator limit

    def serve(req: GetTrajectories.Request, res: GetTrajectories.Response) -> GetTrajectories.Response:
        res.success, res.total, res.run = True, data.num_trajectories, run
        res.policy = policy_spec_to_msg(PolicySpec("open-loop", LipschitzConstant(lipschitz, "lqr-analytic"), control))
        stop = min(req.start + (req.max_count or 50), data.num_trajectories)
        res.trajectories = [seal.seal(trajectory_to_msg(k, data.trajectory(k), run)) for k in range(req.start, stop)]
        return seal.seal(res, answering=req)

    node.create_service(GetTrajectories, DATASET_SERVICE, serve)
    held = tester.collect(UInt32, POLICY_STATUS, LATCHED_READER_QOS)
    actions = tester.collect(JointState, ACTION, CONTROL_QOS)
    dropped = tester.collect(UInt64, POLICY_DROPPED, REPORT_QOS)
    state_pub = node.create_publisher(JointState, STATE, CONTROL_QOS)
    policy = launch("npp-policy", namespace=ns)
    tester.wait_for(lambda: bool(held) and held[-1].data == 20, TIMEOUT, "the policy to hold the dataset")
    tester.wait_for(lambda: state_pub.get_subscription_count() > 0, TIMEOUT, "the policy's state subscription")

    rng = np.random.default_rng(8)
    states = rng.normal(scale=0.5, size=(FLOOD, 4))
    for k, x in enumerate(states):  # as fast as Python can publish, never waiting for an answer
        msg = JointState(name=plant.joint_names, position=x[:2].tolist(), velocity=x[2:].tolist())
        msg.header.stamp = Time(sec=k // 1000, nanosec=(k % 1000) * 1_000_000)
        state_pub.publish(seal.seal_header(msg, "0"))
        if k % 100 == 0:
            tester.executor.spin_once(timeout_sec=0)  # keep our inboxes drained

    def index(msg: JointState) -> int:
        return msg.header.stamp.sec * 1000 + msg.header.stamp.nanosec // 1_000_000

    last = FLOOD - 1
    tester.wait_for(lambda: bool(actions) and index(actions[-1]) == last, TIMEOUT, "the answer to the newest state")
    tester.wait_for(lambda: bool(dropped) and dropped[-1].data > 0, TIMEOUT, "a dropped-states report")
    settled = len(actions)
    quiet_until = time.monotonic() + 1.0
    tester.wait_for(lambda: time.monotonic() > quiet_until, 10.0)
    assert len(actions) == settled, "answers kept coming after the newest state: a backlog was queued"

    answered = [index(a) for a in actions]
    assert answered == sorted(set(answered)), "an older state was answered after a newer one, or one twice"
    for msg, k in zip(actions, answered, strict=True):  # every answer is the greedy action for its state
        np.testing.assert_array_equal(msg.effort, local.act(states[k]))
    reported = dropped[-1].data
    assert 0 < reported and len(answered) + reported <= FLOOD
    launch.assert_alive(policy)
    tester.wait_for(lambda: "stale states" in launch.log(policy), TIMEOUT, "the log line about dropped states")
    print(f"\npolicy flood: {FLOOD} states sent, {len(answered)} answered, {reported} reported dropped by the policy")
