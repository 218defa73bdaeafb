"""The expert service over real DDS: closed-form values, plant-consistent states, precise refusals."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import pytest
from expert_checks import TIMEOUT, check_good, request, wait_until_modelling
from npp_interfaces.msg import PlantDescription
from npp_interfaces.srv import ExpertTrajectory
from rclpy.client import Client

from npp_ros.tasks.builtin.lqr import LQRExpert, LQRPlant
from npp_ros.tasks.uncertainty import Robot
from npp_ros_graph.transport.message_seal import RunSeal, SealError
from npp_ros_graph.transport.topics import EXPERT_SERVICE, LATCHED_QOS, PLANT

if TYPE_CHECKING:
    from tests.ros.conftest import Launcher, RosClient


@pytest.fixture(scope="module")
def graph_2_1(launch_module: Launcher) -> Launcher:
    """One sim and one expert for the module: lqr_2_1, seed 0, default horizon 1000."""
    launch_module("npp-sim", {"task": "lqr_2_1", "seed": 0})
    launch_module("npp-expert", {})
    return launch_module


@pytest.fixture(scope="module")
def expert_client(graph_2_1: Launcher, ros_client_module: Callable[..., RosClient]) -> tuple[RosClient, Client]:
    client = ros_client_module("expert_test_client")
    service = client.client(ExpertTrajectory, EXPERT_SERVICE, TIMEOUT)
    wait_until_modelling(client, service)
    return client, service


def test_good_requests_match_closed_form_and_plant(
    expert_client: tuple[RosClient, Client], expert_2_1: LQRExpert
) -> None:
    client, service = expert_client
    rng = np.random.default_rng(3)
    for s0 in rng.normal(scale=1.0, size=(3, 4)):
        check_good(client.call(service, request(s0, 0)), expert_2_1, s0, 1000)
        check_good(client.call(service, request(s0, 50)), expert_2_1, s0, 50)


@pytest.mark.parametrize(
    ("state", "horizon", "fragments"),
    [
        ([0.1, 0.2, 0.3], 0, ["3 entries", "expected 4"]),
        ([0.1, 0.2, 0.3, 0.4, 0.5], 10, ["5 entries", "expected 4"]),
        ([0.1, 0.2, math.nan, 0.4], 0, ["finite", "state[2] = nan"]),
        ([math.inf, 0.2, 0.3, -math.inf], 0, ["finite", "state[0] = inf", "state[3] = -inf"]),
        ([], 0, ["empty", "expected 4"]),
        ([0.1, 0.2, 0.3, 0.4], 4_000_000_000, ["horizon 4000000000", "max_horizon 10000"]),
        ([0.1, 0.2, 0.3, 0.4], 10_001, ["horizon 10001", "max_horizon 10000"]),
    ],
)
def test_bad_requests_get_precise_errors_and_the_node_keeps_serving(
    expert_client: tuple[RosClient, Client],
    expert_2_1: LQRExpert,
    state: list[float],
    horizon: int,
    fragments: list[str],
) -> None:
    client, service = expert_client
    answer = client.call(service, request(state, horizon))
    assert not answer.success
    for fragment in fragments:
        assert fragment in answer.message, answer.message
    assert len(answer.states) == len(answer.actions) == len(answer.values) == 0
    s0 = np.array([0.5, -0.5, 0.1, 0.0])
    check_good(client.call(service, request(s0, 30)), expert_2_1, s0, 30)


def test_an_expert_that_plans_on_its_nominal_model_only_refuses_a_drawn_robot(
    expert_client: tuple[RosClient, Client], expert_2_1: LQRExpert
) -> None:
    """The closed-form lqr expert cannot plan on a robot: asked about one, it says so rather than answer for the
    nominal model; a damaged robot record is refused naming it; the nominal request is served as before."""
    client, service = expert_client
    s0 = np.array([0.5, -0.5, 0.1, 0.0])
    robot = Robot((("mass", "body_0", 1.1),), action_delay=1)
    asked = request(s0, 30)
    asked.robot = robot.record()
    answer = client.call(service, asked)
    assert not answer.success and len(answer.states) == 0
    assert "cannot plan on a drawn robot" in answer.message and "lqr_2_1" in answer.message, answer.message
    asked.robot = "{broken"
    answer = client.call(service, asked)
    assert not answer.success and answer.message.startswith("robot: not a robot record"), answer.message
    check_good(client.call(service, request(s0, 30)), expert_2_1, s0, 30)


def test_expert_follows_the_sims_plant_description(launch: Launcher, ros_client: Callable[..., RosClient]) -> None:
    """Task, seed and horizon come from the sim, not from the expert's own parameters."""
    launch("npp-sim", {"task": "lqr_6_2", "seed": 1, "horizon": 300}, namespace="/iso62")
    launch("npp-expert", {"max_horizon": 500}, namespace="/iso62")
    client = ros_client("expert_6_2_client", namespace="/iso62")
    service = client.client(ExpertTrajectory, EXPERT_SERVICE, TIMEOUT)
    wait_until_modelling(client, service)
    expert = LQRExpert("lqr_6_2", 1, horizon=300)
    s0 = np.random.default_rng(7).normal(size=12)
    check_good(client.call(service, request(s0, 0)), expert, s0, 300)
    answer = client.call(service, request(s0, 501))
    assert not answer.success and "max_horizon 500" in answer.message, answer.message


def test_expert_waits_for_the_plant_and_refuses_a_foreign_model(
    launch: Launcher, ros_client: Callable[..., RosClient], expert_2_1: LQRExpert
) -> None:
    """No sim: the test plays it, first with a wrong fingerprint, then with the true one."""
    proc = launch("npp-expert", {}, namespace="/fake")
    client = ros_client("fake_sim", namespace="/fake")
    service = client.client(ExpertTrajectory, EXPERT_SERVICE, TIMEOUT)
    s0 = [0.3, 0.1, 0.0, 0.0]
    answer = client.call(service, request(s0))
    assert not answer.success
    assert answer.message == "not ready: no plant description received yet from the sim on /fake/npp/sim/plant"

    plant = LQRPlant("lqr_2_1", 0)
    desc = PlantDescription(
        task="lqr_2_1",
        seed=0,
        horizon=1000,
        timestep=plant.dt,
        state_dim=4,
        action_dim=1,
        joint_names=plant.joint_names,
        actuated_joint_names=plant.actuated_joint_names,
        model_sha256="0" * 64,
    )
    publisher = client.node.create_publisher(PlantDescription, PLANT, LATCHED_QOS)
    publisher.publish(desc)  # without the run's seal: not this run's sim, ignored
    deadline = time.monotonic() + TIMEOUT
    client.wait_for(lambda: "does not carry this run's seal" in launch.log(proc), TIMEOUT, "the refusal in the log")
    assert client.call(service, request(s0)).message.startswith("not ready:")

    run_seal = RunSeal.from_environment()
    publisher.publish(run_seal.seal(desc))
    while "model mismatch" not in (answer := client.call(service, request(s0))).message:
        assert time.monotonic() < deadline, answer.message
        time.sleep(0.05)
    assert not answer.success and "refusing" in answer.message

    desc.model_sha256 = plant.model_sha256()
    publisher.publish(run_seal.seal(desc))
    while not (answer := client.call(service, ask := request(s0, 10))).success:
        assert time.monotonic() < deadline, answer.message
        time.sleep(0.05)
    check_good(answer, expert_2_1, np.array(s0), 10)
    # The answer names its plant and carries the run's seal for it, bound to the request it answers.
    assert answer.plant == plant.model_sha256()
    seal = run_seal.for_plant(answer.plant)
    seal.check(answer, "the expert's answer", answering=ask)
    with pytest.raises(SealError):
        seal.check(answer, "the expert's answer", answering=request(s0, 11))

    # Once modelling a plant, a description of another (a second sim on the domain) changes nothing.
    other = LQRPlant("lqr_2_1", 1)
    desc.seed, desc.model_sha256 = 1, other.model_sha256()
    publisher.publish(run_seal.seal(desc))
    client.wait_for(lambda: "ignored a description of another plant" in launch.log(proc), TIMEOUT, "the refusal")
    answer = client.call(service, request(s0, 10))
    assert answer.success and answer.plant == plant.model_sha256(), answer.message
    launch.assert_alive(proc)
