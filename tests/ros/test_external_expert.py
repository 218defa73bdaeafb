"""An expert in a process of its own (examples/external_expert): the supervisor certifies a run it serves, and
refuses, with the reason and storing nothing, an answer with wrong dimensions, non-finite values, or values that
contradict its own trajectory."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest
from expert_checks import TIMEOUT, request, wait_until_modelling
from misbehaving_expert import FAULTS
from npp_interfaces.msg import Certificate
from npp_interfaces.srv import ExpertTrajectory

from npp_ros.run.store import RunStore
from npp_ros.tasks.builtin.lqr import LQRExpert
from npp_ros.tasks.uncertainty import Robot
from npp_ros_graph.transport.expert_api import robot_refusal
from npp_ros_graph.transport.message_seal import KEY_ENV, RunSeal
from npp_ros_graph.transport.topics import CERTIFICATE, EXPERT_SERVICE, LATCHED_READER_QOS

if TYPE_CHECKING:
    from tests.ros.conftest import Launcher, RosClient

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = "examples.external_expert.lqr_expert"
HORIZON = 300
EPSILON = 200.0  # certified after some 130 episodes (366 at the default 50): the expert's answers are the point


@pytest.mark.long
def test_the_supervisor_certifies_a_run_served_by_an_external_expert(
    launch: Launcher, ros_client: Callable[..., RosClient], tmp_path: Path
) -> None:
    key = {KEY_ENV: RunSeal.new_key()}
    run_dir = tmp_path / "run"
    launch("npp-sim", {"task": "lqr_2_1", "horizon": HORIZON}, extra_env=key)
    expert = launch(EXAMPLE, extra_env=key)
    launch("npp-policy", extra_env=key)
    supervisor = launch(
        "npp-supervisor", {"run_dir": str(run_dir), "epsilon": EPSILON, "max_episodes": 400}, extra_env=key
    )
    client = ros_client("certificate_watch")
    certificates = client.collect(Certificate, CERTIFICATE, LATCHED_READER_QOS)
    client.wait_for(lambda: bool(certificates) or supervisor.poll() is not None, 900, "the certificate")
    launch.assert_alive(supervisor)
    launch.assert_alive(expert)
    assert "modelling lqr_2_1 seed 0" in launch.log(expert)
    launch.stop(supervisor)
    with RunStore.open(run_dir / "run.sqlite") as store:
        data, rows, certificate = store.load_dataset(), store.episodes(), store.certificate()
    assert certificate is not None and certificate["episodes"] == len(rows) and certificate["proven"]
    assert data.num_trajectories == sum(row.oracle_called for row in rows) > 0
    # The stored values are the example's own Riccati solution: npp_ros's closed form agrees to rounding.
    reference = LQRExpert("lqr_2_1", 0, horizon=HORIZON)
    np.testing.assert_allclose(data.values, reference.value(data.states), rtol=1e-9, atol=1e-7)


@pytest.mark.parametrize(
    ("fault", "reason"),
    [
        ("wrong_dimensions", "wrong dimensions: 3 state and 1 action entries per step, the plant has 4 and 1"),
        ("non_finite", "values"),
        ("inflated_values", "contradicts its own trajectory"),
        ("inconsistent_values", "values[9] - values[10]"),
    ],
)
def test_a_wrong_answer_is_refused_with_the_reason_and_nothing_is_stored(
    launch: Launcher, tmp_path: Path, fault: str, reason: str
) -> None:
    assert fault in FAULTS
    key = {KEY_ENV: RunSeal.new_key()}
    run_dir = tmp_path / "run"
    launch("npp-sim", {"task": "lqr_2_1", "horizon": 50}, extra_env=key)
    expert = launch(
        "misbehaving_expert", extra_env={**key, "NPP_TEST_FAULT": fault, "PYTHONPATH": str(REPO / "tests" / "ros")}
    )
    supervisor = launch(
        "npp-supervisor",
        {"run_dir": str(run_dir), "certify": "surrogate", "rollouts": False, "expert_retries": 2},
        extra_env=key,
    )
    assert supervisor.wait(timeout=180) == 1
    launch.assert_alive(expert)  # it answered; the supervisor refused what it said
    log = launch.log(supervisor)
    refusals = [line for line in log.splitlines() if "refused the expert's answer" in line]
    assert len(refusals) >= 2 and all(reason in line for line in refusals), log[-3000:]
    assert "Algorithm 1 stopped: the expert did not deliver after 2 attempts" in log
    with RunStore.open(run_dir / "run.sqlite") as store:
        assert store.load_dataset().num_trajectories == 0 and store.episodes() == []


def test_an_external_expert_refuses_a_drawn_robot_as_the_contract_says(
    launch: Launcher, ros_client: Callable[..., RosClient]
) -> None:
    """The example plans on its nominal Riccati solution only: a request naming a robot gets the contract's
    refusal, and a nominal one is answered as before."""
    namespace = "/robotless"
    launch("npp-sim", {"task": "lqr_2_1", "horizon": 30}, namespace=namespace)
    launch(EXAMPLE, namespace=namespace)
    client = ros_client("robot_request", namespace=namespace)
    service = client.client(ExpertTrajectory, EXPERT_SERVICE, TIMEOUT)
    wait_until_modelling(client, service)
    asked = request([0.3, -0.2, 0.1, 0.0], 10)
    asked.robot = Robot((("mass", "body_0", 1.1),)).record()
    answer = client.call(service, asked)
    assert not answer.success and answer.message == robot_refusal("lqr_2_1"), answer.message
    assert client.call(service, request([0.3, -0.2, 0.1, 0.0], 10)).success
