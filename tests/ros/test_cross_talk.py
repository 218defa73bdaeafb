"""Nothing from outside a run enters it, however careless or hostile the rest of the domain.

The run's four nodes share a random NPP_RUN_KEY, as npp-run gives them. While they run lqr_2_1 on
their usual topics, the domain holds at once:

- a second sim (seed 1, another plant, no key), started mid-run, which describes its plant latched
  and serves resets on the same names;
- injected one-point trajectories on /npp/dataset/trajectory (the next index, Q = 1e6, action 42),
  unsealed and sealed with another key;
- an impostor /npp/dataset/get (answers with action 42, sealed with another key);
- a stray /npp/action publisher answering every state at once with its stamp, its seal copied from
  the state, and action 42;
- a stray /npp/state stream at 200 Hz, replaying the latest state's stamp and seal with other values.

The run must end with exactly the in-process run's dataset, decisions and certificate (the paper's
surrogate check: its decisions do not depend on rollouts), every stored return must be the one the
run's own greedy policy earns from that episode's s0 (recomputed here in MuJoCo), and the nodes'
logs must name what they refused.

An impostor expert is tested on its own: DDS hands a service call to every server of its name and
rclpy keeps the first answer, so an impostor that always answers first leaves the run no trajectory
from its own expert. The supervisor refuses every such answer and stops with the reason.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest
from graph import graph_parameters, start_graph
from npp_interfaces.msg import Certificate, GapReport
from npp_interfaces.msg import Trajectory as TrajectoryMsg
from npp_interfaces.srv import ExpertTrajectory, GetTrajectories
from reference import ROLLOUT_FREE, assert_stored_run_is_uninterrupted
from sensor_msgs.msg import JointState
from std_msgs.msg import UInt32

from npp_ros.certificate.certifier import CertificationSpec
from npp_ros.policy.feedback import ControlSpace
from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.policy.spec import PolicySpec
from npp_ros.run.setup import policy_for
from npp_ros.run.store import RunStore
from npp_ros.tasks.builtin.lqr import LQRPlant
from npp_ros.tasks.rollout import rollout
from npp_ros_graph.transport.convert import float64_array, policy_spec_to_msg
from npp_ros_graph.transport.message_seal import KEY_ENV, RunSeal
from npp_ros_graph.transport.topics import (
    ACTION,
    CERTIFICATE,
    CONTROL_QOS,
    DATASET_SERVICE,
    DATASET_TOPIC,
    EXPERT_SERVICE,
    GAP,
    LATCHED_READER_QOS,
    POLICY_STATUS,
    REPORT_QOS,
    STATE,
)

if TYPE_CHECKING:
    from tests.ros.conftest import Launcher, RosClient

pytestmark = pytest.mark.slow

HORIZON = 50
MAX_EPISODES = 400
SECOND_SIM_AFTER = 10  # episodes
TIMEOUT = 900.0
RESTARTS = 3  # of the policy, until the impostor dataset service has answered it


class Intruder:
    """Everything a stray or hostile process on the domain can send, from one node of the test."""

    def __init__(self, client: RosClient, fingerprint: str) -> None:
        self.client, node = client, client.node
        self.other = RunSeal(b"another run's key", private=True).for_plant(fingerprint)
        self.fingerprint = fingerprint
        self.rng = np.random.default_rng(3)
        self.last_state: JointState | None = None
        self.held = 0
        self.actions = node.create_publisher(JointState, ACTION, CONTROL_QOS)
        self.states = node.create_publisher(JointState, STATE, CONTROL_QOS)
        self.trajectories = node.create_publisher(TrajectoryMsg, DATASET_TOPIC, REPORT_QOS)
        node.create_subscription(JointState, STATE, self.on_state, CONTROL_QOS)
        node.create_subscription(UInt32, POLICY_STATUS, self.on_status, LATCHED_READER_QOS)
        self.sent = {"actions": 0, "states": 0, "trajectories": 0, "dataset answers": 0, "expert answers": 0}

    def start(self) -> None:
        node = self.client.node
        node.create_service(GetTrajectories, DATASET_SERVICE, self.serve_dataset)
        node.create_timer(0.005, self.flood_states)  # 200 Hz
        node.create_timer(0.5, self.inject_trajectory)

    def on_status(self, msg: UInt32) -> None:
        self.held = int(msg.data)

    def on_state(self, msg: JointState) -> None:
        if msg.position and abs(msg.position[0]) == 9.0:
            return  # our own flood
        self.last_state = msg
        action = JointState(name=["joint_0"], effort=[42.0])
        action.header = msg.header  # the state's stamp and its seal, copied
        self.actions.publish(action)
        self.sent["actions"] += 1

    def flood_states(self) -> None:
        if self.last_state is None:
            return
        fake = JointState(name=list(self.last_state.name), position=[9.0, 9.0], velocity=[9.0, 9.0])
        fake.header = self.last_state.header  # a genuine stamp and seal over other values
        self.states.publish(fake)
        self.sent["states"] += 1

    def fake_trajectory(self, index: int) -> TrajectoryMsg:
        return TrajectoryMsg(
            index=index, state_dim=4, action_dim=1, states=float64_array(self.rng.normal(size=4)),
            actions=float64_array([42.0]), values=float64_array([1e6]),
        )  # fmt: skip

    def inject_trajectory(self) -> None:
        self.trajectories.publish(self.fake_trajectory(self.held))  # unsealed
        self.trajectories.publish(self.other.seal(self.fake_trajectory(self.held)))  # another run's seal
        self.sent["trajectories"] += 2

    def serve_dataset(self, request: GetTrajectories.Request, response: GetTrajectories.Response) -> Any:
        response.success, response.total = True, self.held + 1
        response.policy = policy_spec_to_msg(
            PolicySpec("open-loop", LipschitzConstant(1.0, "user"), ControlSpace.of(4, (), [-np.inf], [np.inf]))
        )
        response.trajectories = [self.other.seal(self.fake_trajectory(k)) for k in range(request.start, self.held + 1)]
        self.sent["dataset answers"] += 1
        return self.other.seal(response, answering=request)

    def serve_expert(self, request: ExpertTrajectory.Request, response: ExpertTrajectory.Response) -> Any:
        steps = HORIZON
        response.success, response.message, response.plant = True, "", self.fingerprint
        response.state_dim, response.action_dim = 4, 1
        response.states = float64_array(np.tile(np.asarray(request.state), steps))
        response.actions = float64_array(np.full(steps, 42.0))
        response.values = float64_array(np.full(steps, 1e6))
        response.expert_return = 1e6
        self.sent["expert answers"] += 1
        return self.other.seal(response, answering=request)


def expected_return(data: Any, spec: CertificationSpec, row: Any, plant: LQRPlant) -> float:
    """What the run's own policy earns from the episode's s0 with the data it held then."""
    policy = policy_for(data.prefix(row.dataset_size // HORIZON), spec, "lqr_2_1", 0)
    return rollout(plant, policy.act, np.asarray(row.initial_state), HORIZON).total_return


@pytest.mark.long
def test_nothing_from_outside_the_run_enters_it(
    launch: Launcher, ros_client: Callable[..., RosClient], tmp_path: Path
) -> None:
    run_dir = tmp_path / "run"
    key = {KEY_ENV: RunSeal.new_key()}
    client = ros_client("intruder")
    gaps = client.collect(GapReport, GAP, REPORT_QOS)
    certificates = client.collect(Certificate, CERTIFICATE, LATCHED_READER_QOS)
    fingerprint = LQRPlant("lqr_2_1", 0).model_sha256()
    intruder = Intruder(client, fingerprint)
    params = graph_parameters("lqr_2_1", 0, HORIZON, run_dir, supervisor={"max_episodes": MAX_EPISODES, **ROLLOUT_FREE})
    procs = start_graph(launch, params, extra_env=key)
    client.wait_for(lambda: len(gaps) >= SECOND_SIM_AFTER, TIMEOUT, f"{SECOND_SIM_AFTER} episodes")
    second_sim = launch("npp-sim", {"task": "lqr_2_1", "seed": 1, "horizon": HORIZON})
    intruder.start()
    # A restarted policy catches up through /npp/dataset/get, where the impostor answers too, if the new
    # process has discovered the impostor by the time it asks: discovery order decides, so restart it
    # until the impostor has answered once (the assertion below still requires that it did).
    for _ in range(RESTARTS):
        launch.stop(procs["policy"])
        procs["policy"] = launch("npp-policy", {}, extra_env=key)
        with contextlib.suppress(TimeoutError):
            client.wait_for(lambda: intruder.sent["dataset answers"] > 0, 20.0, "the impostor's dataset answer")
            break
    # The second sim's plant description reached the run's nodes (what the logs are checked for below); the
    # refusals are waited for, not this client's copy, which its one-deep latched history can miss.
    client.wait_for(
        lambda: (
            "publishers of /npp/sim/plant" in launch.log(procs["supervisor"])
            and "does not carry this run's seal" in launch.log(procs["expert"])
        ),
        120.0,
        "the run's supervisor and expert refusing the second sim's plant description",
    )
    client.wait_for(lambda: bool(certificates), TIMEOUT, "the run's certificate")
    for proc in procs.values():
        launch.assert_alive(proc)
    launch.assert_alive(second_sim)
    print(f"\nintruders sent: {intruder.sent}")
    kinds = ("actions", "states", "trajectories", "dataset answers")
    assert all(intruder.sent[kind] > 0 for kind in kinds), intruder.sent

    data, rows, local_loop = assert_stored_run_is_uninterrupted(run_dir / "run.sqlite", HORIZON, MAX_EPISODES)
    assert not np.any(data.actions == 42.0)

    spec = local_loop.config.spec
    plant = LQRPlant("lqr_2_1", 0)
    driven = [row for row in rows if row.policy_return is not None]
    assert len(driven) >= len(rows) - 5, "the intruders kept the policy from driving"
    for row in driven:
        assert row.policy_return == pytest.approx(expected_return(data, spec, row, plant), rel=1e-9, abs=1e-9)

    logs = {name: launch.log(proc) for name, proc in procs.items()}
    assert "does not carry this run's seal" in logs["policy"]  # states, trajectories
    assert "ignored an action: foreign" in logs["sim"]
    assert "refused" in logs["supervisor"] and "publishers of /npp/sim/plant" in logs["supervisor"]
    assert "does not carry this run's seal" in logs["expert"]  # the second sim's plant description
    assert "only this run's supervisor resets the sim" in launch.log(second_sim)


def test_an_impostor_expert_stops_the_run_with_the_reason(
    launch: Launcher, ros_client: Callable[..., RosClient], tmp_path: Path
) -> None:
    run_dir = tmp_path / "run"
    key = {KEY_ENV: RunSeal.new_key()}
    client = ros_client("impostor")
    gaps = client.collect(GapReport, GAP, REPORT_QOS)
    intruder = Intruder(client, LQRPlant("lqr_2_1", 0).model_sha256())
    supervisor = {"max_episodes": MAX_EPISODES, "expert_timeout": 2.0, **ROLLOUT_FREE}
    procs = start_graph(launch, graph_parameters("lqr_2_1", 0, HORIZON, run_dir, supervisor=supervisor), extra_env=key)
    client.wait_for(lambda: len(gaps) >= 3, TIMEOUT, "3 episodes")
    client.node.create_service(ExpertTrajectory, EXPERT_SERVICE, intruder.serve_expert)
    supervisor = procs["supervisor"]
    client.wait_for(lambda: supervisor.poll() is not None, TIMEOUT, "the supervisor to stop")
    assert supervisor.returncode == 1
    log = launch.log(supervisor)
    assert (
        "Algorithm 1 stopped: the expert did not deliver after 3 attempts: refused: the expert's answer does "
        "not carry this run's seal" in log
    ), log[-2000:]
    assert "2 servers of /npp/expert/trajectory on the domain" in log
    with RunStore.open(run_dir / "run.sqlite") as store:
        data = store.load_dataset()
    assert intruder.sent["expert answers"] >= 3
    assert data.num_trajectories >= 1 and not np.any(data.actions == 42.0) and not np.any(data.values == 1e6)
