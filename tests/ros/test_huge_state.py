"""A state of huge but finite magnitude, sent to the policy node as a user did: refused with a log line, not
answered. Before the check, 1e160 overflowed every distance and the policy answered with the action of index 0
(V_lb = -inf).

The policy runs alone in /huge; the test is its sim (plant description, states) and its supervisor (dataset
service with one two-point trajectory, so index 0 and the right answer differ)."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
from builtin_interfaces.msg import Time
from npp_interfaces.msg import PlantDescription
from npp_interfaces.srv import GetTrajectories
from sensor_msgs.msg import JointState
from std_msgs.msg import UInt32

from npp_ros.policy.dataset import Trajectory
from npp_ros.policy.feedback import ControlSpace
from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.policy.spec import PolicySpec
from npp_ros_graph.transport.convert import policy_spec_to_msg, trajectory_to_msg
from npp_ros_graph.transport.message_seal import RunSeal
from npp_ros_graph.transport.topics import (
    ACTION,
    CONTROL_QOS,
    DATASET_SERVICE,
    LATCHED_QOS,
    LATCHED_READER_QOS,
    PLANT,
    POLICY_STATUS,
    SERVICE_QOS,
    STATE,
)

if TYPE_CHECKING:
    from tests.ros.conftest import Launcher, RosClient

TIMEOUT = 120.0
JOINTS = ["joint_0", "joint_1"]
DATA = Trajectory(
    states=np.array([[0.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0]]),
    actions=np.array([[-1.0], [2.0]]),  # index 0 answers -1.0: the wrong answer the overflow gave
    values=np.array([0.0, -1.0]),
)


RUN_SEAL = RunSeal.from_environment()
RUN = "huge-state-run"
SEAL = RUN_SEAL.for_plant("test").for_run(RUN)  # the test plays this run's sim and supervisor


def serve_dataset(request: Any, response: Any) -> Any:
    response.success, response.total, response.run = True, 1, RUN
    response.policy = policy_spec_to_msg(
        PolicySpec(
            "open-loop", LipschitzConstant(1.0, "user"), ControlSpace.of(DATA.states.shape[1], (), [-np.inf], [np.inf])
        )
    )
    response.trajectories = [SEAL.seal(trajectory_to_msg(0, DATA, RUN))] if request.start == 0 else []
    return SEAL.seal(response, answering=request)


def state(position: list[float], velocity: list[float], sec: int) -> JointState:
    msg = JointState(name=JOINTS, position=position, velocity=velocity)
    msg.header.stamp = Time(sec=sec)
    return SEAL.seal_header(msg, "0")


def test_policy_node_refuses_a_huge_finite_state(launch: Launcher, ros_client: Callable[..., RosClient]) -> None:
    client = ros_client("huge_state_client", namespace="/huge")
    node = client.node
    plant = PlantDescription(
        task="lqr_2_1", seed=0, horizon=50, timestep=0.03, state_dim=4, action_dim=1,
        joint_names=JOINTS, actuated_joint_names=["joint_0"], model_sha256="test",
    )  # fmt: skip
    node.create_publisher(PlantDescription, PLANT, LATCHED_QOS).publish(RUN_SEAL.seal(plant))
    node.create_service(GetTrajectories, DATASET_SERVICE, serve_dataset, qos_profile=SERVICE_QOS)
    held = client.collect(UInt32, POLICY_STATUS, LATCHED_READER_QOS)
    actions = client.collect(JointState, ACTION, CONTROL_QOS)
    states = node.create_publisher(JointState, STATE, CONTROL_QOS)
    policy = launch("npp-policy", namespace="/huge")
    client.wait_for(lambda: any(m.data == 1 for m in held), TIMEOUT, "the policy to hold the trajectory")
    client.wait_for(lambda: states.get_subscription_count() >= 1, TIMEOUT, "the policy to subscribe to states")

    # A good state first (re-sent until answered: the first may go out before the policy matched us).
    deadline = time.monotonic() + TIMEOUT
    while not any(a.header.stamp.sec == 1 for a in actions):
        assert time.monotonic() < deadline, "the policy never answered a good state"
        states.publish(state([0.9, 1.0], [1.0, 1.1], 1))
        try:
            client.wait_for(lambda: any(a.header.stamp.sec == 1 for a in actions), 2.0)
        except TimeoutError:
            continue
    assert next(a.effort.tolist() for a in actions if a.header.stamp.sec == 1) == [2.0]

    for k, (position, velocity) in enumerate(
        [([1e160, 0.0], [0.0, 0.0]), ([1.0, 1.0], [-1e155, 1.0]), ([1e300, 1e300], [1e300, 1e300])]
    ):
        states.publish(state(position, velocity, 1000 + k))
        states.publish(state([0.9, 1.0], [1.0, 1.1], 2000 + k))  # same writer, in order: answered after it
        client.wait_for(lambda k=k: any(a.header.stamp.sec == 2000 + k for a in actions), TIMEOUT, "the probe")
        assert not any(a.header.stamp.sec == 1000 + k for a in actions), f"answered a huge state {position}"
    launch.assert_alive(policy)
    log = launch.log(policy)
    assert "state refused: state is too large to compare with the data: state[0] = 1e+160" in log, log
    assert "entries must be within +-1e+150" in log
