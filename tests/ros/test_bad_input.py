"""Malformed input to every ROS entry point, generated with hypothesis: precise errors, no process dies,
nothing stored changes.

- A whole graph runs to its certificate in namespace /bad (lqr_2_1, horizon 50); its run file is hashed.
  Then the expert service gets wrong dimensions, empty and non-finite states and huge horizons, and
  the policy gets states with wrong joint names or counts and non-finite values. Each bad request gets
  success = false and a message naming the problem; each bad state a log line and no action. Afterwards
  all four nodes are alive, the expert still answers correctly, the policy still drives an episode, and
  the run file is byte for byte the same.
- A sim alone in /bad_sim gets actions with stale stamps, wrong joint names, wrong lengths and
  non-finite efforts: each is ignored with a log line and the plant does not move.
- Nodes started with bad parameters (unknown task, negative epsilon or L, p or delta outside (0, 1), ...)
  refuse to start, exit with code 2 and say why; a supervisor refused on an existing run leaves it as is.
- A supervisor given a run file made for other dimensions stops with the reason; the file is unchanged.

Hypothesis runs derandomized with modest example counts; each test prints how many cases it tried.
"""

from __future__ import annotations

import hashlib
import math
import string
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from expert_checks import TIMEOUT, check_good, request, wait_until_modelling
from graph import graph_parameters, start_graph, start_node
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from npp_interfaces.msg import Certificate, EpisodeResult, PlantDescription
from npp_interfaces.srv import ExpertTrajectory, ResetEpisode
from rclpy.client import Client
from rclpy.publisher import Publisher
from sensor_msgs.msg import JointState

from npp_ros.run.setup import build_config, resolve_lipschitz
from npp_ros.run.store import RunStore
from npp_ros.tasks.builtin.lqr import LQRExpert, LQRPlant
from npp_ros_graph.graph.description import NODES
from npp_ros_graph.transport.message_seal import RunSeal
from npp_ros_graph.transport.topics import (
    ACTION,
    CERTIFICATE,
    CONTROL_QOS,
    EXPERT_SERVICE,
    LATCHED_READER_QOS,
    PLANT,
    REPORT_QOS,
    RESET_SERVICE,
    ROLLOUT_DONE,
    STATE,
)

if TYPE_CHECKING:
    from tests.ros.conftest import Launcher, RosClient

HORIZON = 50
JOINTS = ["joint_0", "joint_1"]
FUZZ = settings(
    max_examples=40,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
tried: Counter[str] = Counter()
# The test plays this run's sim and supervisor, so what it sends carries the run's seal: the malformed
# content is what is tested (what lacks the seal is refused before it is read: tests/ros/test_cross_talk.py).
PLANT_SEAL = RunSeal.from_environment().for_plant(LQRPlant("lqr_2_1", 0).model_sha256())
RUN = "bad-input-run"  # the identity of the run whose supervisor the test plays to a sim of its own
SEAL = PLANT_SEAL.for_run(RUN)


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module", autouse=True)
def report_counts() -> Any:
    yield
    print("\nbad-input cases tried: " + ", ".join(f"{k} {v}" for k, v in sorted(tried.items())))


class Graph:
    """A certified graph in /bad: its processes, a client node, and the run file's hash."""

    def __init__(self, launch: Launcher, client: RosClient, run_dir: Path) -> None:
        self.launch, self.client, self.run_dir = launch, client, run_dir
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.run_hash = ""
        self.run_id = ""
        self.seal = SEAL  # the graph's run's seal, once its run file names the run
        self.expert: Client | None = None

    @property
    def run_file(self) -> Path:
        return self.run_dir / "run.sqlite"

    def all_alive(self) -> None:
        for proc in self.procs.values():
            self.launch.assert_alive(proc)


@pytest.fixture(scope="module")
def graph(launch_module: Launcher, ros_client_module: Callable[..., RosClient], tmp_path_factory: Any) -> Graph:
    ns = "/bad"
    run_dir = tmp_path_factory.mktemp("bad") / "run"
    client = ros_client_module("bad_input_client", namespace=ns)
    g = Graph(launch_module, client, run_dir)
    certificates = client.collect(Certificate, CERTIFICATE, LATCHED_READER_QOS)
    # The paper's check and rule certify this short-horizon graph quickly; the inputs below are what is tested.
    params = graph_parameters(
        "lqr_2_1", 0, HORIZON, run_dir, supervisor={"max_episodes": 400, "certify": "surrogate", "rule": "paper"}
    )
    g.procs.update(start_graph(launch_module, params, namespace=ns))
    client.wait_for(lambda: bool(certificates), 600.0, "the certificate of the /bad graph")
    time.sleep(0.5)  # the supervisor's worker closes the run file after certifying
    g.run_hash = sha256(g.run_file)
    with RunStore.open(g.run_file) as store:
        g.run_id = store.run_id
    g.seal = PLANT_SEAL.for_run(g.run_id)
    g.expert = client.client(ExpertTrajectory, EXPERT_SERVICE, TIMEOUT)
    wait_until_modelling(client, g.expert)
    return g


# ----------------------------------------------------------------------------- expert service
FLOATS = st.floats(width=64)  # with nan, inf, subnormals, -0.0
FINITE = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False)
NON_FINITE = st.sampled_from([math.nan, math.inf, -math.inf])


def with_non_finite(size: int) -> st.SearchStrategy[list[float]]:
    """`size` floats of which at least one is nan or +-inf."""
    return st.tuples(st.lists(FLOATS, min_size=size, max_size=size), st.integers(0, size - 1), NON_FINITE).map(
        lambda c: [*c[0][: c[1]], c[2], *c[0][c[1] + 1 :]]
    )


BAD_EXPERT_REQUESTS = st.one_of(
    st.tuples(st.lists(FLOATS, max_size=12).filter(lambda s: len(s) != 4), st.integers(0, 2000)),
    st.tuples(with_non_finite(4), st.integers(0, 2000)),
    st.tuples(st.lists(FINITE, min_size=4, max_size=4), st.integers(10_001, 2**32 - 1)),
)


def expected_expert_error(state: list[float], horizon: int) -> str:
    if not state:
        return "state is empty; expected 4 entries"
    if len(state) != 4:
        return f"state has {len(state)} entries, expected 4"
    bad = [i for i, x in enumerate(state) if not math.isfinite(x)]
    if bad:
        return f"state must be finite: state[{bad[0]}] = {np.float64(state[bad[0]])}"
    return f"horizon {horizon} exceeds max_horizon 10000"


@FUZZ
@given(case=BAD_EXPERT_REQUESTS)
def test_expert_refuses_malformed_requests_precisely(graph: Graph, case: tuple[list[float], int]) -> None:
    state, horizon = case
    assert graph.expert is not None
    answer = graph.client.call(graph.expert, request(state, horizon))
    tried["expert requests"] += 1
    assert not answer.success
    assert expected_expert_error(state, horizon) in answer.message, answer.message
    assert len(answer.states) == len(answer.actions) == len(answer.values) == 0


def test_expert_still_serves_and_nothing_stored_changed(graph: Graph, expert_2_1: LQRExpert) -> None:
    assert graph.expert is not None
    expert = LQRExpert("lqr_2_1", 0, horizon=HORIZON)
    s0 = np.array([0.3, -0.2, 0.1, 0.0])
    check_good(graph.client.call(graph.expert, request(s0, 0)), expert, s0, HORIZON)
    graph.all_alive()
    assert sha256(graph.run_file) == graph.run_hash


# ----------------------------------------------------------------------------- state topic -> policy
NAMES = st.text(alphabet=string.ascii_letters + string.digits + "_", max_size=10)
VALUES2 = st.lists(FINITE, min_size=2, max_size=2)
BAD_STATES = st.one_of(
    st.tuples(st.just("wrong joint names"), st.lists(NAMES, min_size=1, max_size=4).filter(lambda n: n != JOINTS),
              VALUES2, VALUES2),
    st.tuples(st.just("wrong joint count"), st.sampled_from([[], JOINTS]),
              st.lists(FINITE, max_size=5), st.lists(FINITE, max_size=5)).filter(
        lambda c: len(c[2]) != 2 or len(c[3]) != 2),
    st.tuples(st.just("non-finite state"), st.sampled_from([[], JOINTS]), with_non_finite(4)).map(
        lambda c: (c[0], c[1], c[2][:2], c[2][2:])),
)  # fmt: skip


@pytest.fixture(scope="module")
def policy_io(graph: Graph) -> tuple[Publisher, list[JointState]]:
    actions = graph.client.collect(JointState, ACTION, CONTROL_QOS)
    publisher = graph.client.node.create_publisher(JointState, STATE, CONTROL_QOS)
    graph.client.wait_for(lambda: publisher.get_subscription_count() >= 1, TIMEOUT, "the policy to subscribe")
    return publisher, actions


@FUZZ
@given(case=BAD_STATES)
def test_policy_refuses_malformed_states_and_keeps_answering(
    graph: Graph, policy_io: tuple[Publisher, list[JointState]], case: tuple[str, list[str], list[float], list[float]]
) -> None:
    kind, names, position, velocity = case
    publisher, actions = policy_io
    n = tried["policy states"]
    bad = JointState(name=names, position=position, velocity=velocity)
    bad.header.stamp = Time(sec=1000 + n)
    probe = JointState(name=JOINTS, position=[0.1, 0.2], velocity=[0.0, -0.1])
    probe.header.stamp = Time(sec=100_000 + n)
    publisher.publish(graph.seal.seal_header(bad, "0"))
    publisher.publish(graph.seal.seal_header(probe, "0"))  # answered only after the bad one was handled: in order
    graph.client.wait_for(lambda: any(a.header.stamp.sec == 100_000 + n for a in actions), TIMEOUT, "the probe")
    tried["policy states"] += 1
    tried[f"policy states: {kind}"] += 1
    assert not any(a.header.stamp.sec == 1000 + n for a in actions), f"the policy answered a bad state: {case}"


def test_policy_logged_each_kind_and_still_drives_an_episode(
    graph: Graph, policy_io: tuple[Publisher, list[JointState]]
) -> None:
    log = graph.launch.log(graph.procs["policy"])
    for kind in ("wrong joint names", "wrong joint count", "state must be finite"):
        assert f"state refused: {kind}" in log
    results = graph.client.collect(EpisodeResult, ROLLOUT_DONE, REPORT_QOS)
    reset = graph.client.client(ResetEpisode, RESET_SERVICE, TIMEOUT)
    request = ResetEpisode.Request(state=[0.2, 0.1, 0.0, 0.0], episode=9999, run=graph.run_id)
    answer = graph.client.call(reset, graph.seal.seal(request))
    assert answer.success, answer.message
    graph.client.wait_for(lambda: any(r.episode == 9999 for r in results), TIMEOUT, "the policy's episode")
    graph.all_alive()
    assert sha256(graph.run_file) == graph.run_hash


# ----------------------------------------------------------------------------- action topic -> sim
class SimAlone:
    """A sim with nobody answering its states but the test."""

    def __init__(self, launch: Launcher, client: RosClient) -> None:
        self.proc = launch("npp-sim", {"task": "lqr_2_1", "seed": 0, "horizon": 100_000}, namespace="/bad_sim")
        self.client = client
        self.states = client.collect(JointState, STATE, CONTROL_QOS)
        plants = client.collect(PlantDescription, PLANT, LATCHED_READER_QOS)
        self.actions = client.node.create_publisher(JointState, ACTION, CONTROL_QOS)
        self.reset = client.client(ResetEpisode, RESET_SERVICE, TIMEOUT)
        client.wait_for(lambda: bool(plants), TIMEOUT, "the sim's plant")
        client.wait_for(lambda: self.actions.get_subscription_count() > 0, TIMEOUT, "the sim's action subscription")
        while True:  # reset, and make sure our subscription got the first state
            seen = len(self.states)
            reset = SEAL.seal(ResetEpisode.Request(state=[0.4, -0.3, 0.2, 0.1], episode=0, run=RUN))
            assert client.call(self.reset, reset).success
            try:
                client.wait_for(lambda s=seen: len(self.states) > s, 3.0)
                break
            except TimeoutError:
                continue
        self.expert = LQRExpert("lqr_2_1", 0)

    def current(self) -> tuple[Time, np.ndarray]:
        msg = self.states[-1]
        return msg.header.stamp, np.concatenate([msg.position, msg.velocity])


@pytest.fixture(scope="module")
def sim_alone(launch_module: Launcher, ros_client_module: Callable[..., RosClient]) -> SimAlone:
    return SimAlone(launch_module, ros_client_module("bad_sim_client", namespace="/bad_sim"))


STAMPS = st.builds(Time, sec=st.integers(0, 2**31 - 1), nanosec=st.integers(0, 999_999_999))
BAD_ACTIONS = st.one_of(
    st.tuples(st.just("stale"), STAMPS, st.just(["joint_0"]), st.lists(FINITE, min_size=1, max_size=1)),
    st.tuples(st.just("wrong joint names"), st.none(), st.lists(NAMES, min_size=1, max_size=3).filter(
        lambda n: n != ["joint_0"]), st.lists(FINITE, min_size=1, max_size=1)),
    st.tuples(st.just("wrong effort length"), st.none(), st.just([]),
              st.lists(FINITE, max_size=5).filter(lambda e: len(e) != 1)),
    st.tuples(st.just("non-finite effort"), st.none(), st.just(["joint_0"]), with_non_finite(1)),
)  # fmt: skip


@FUZZ
@given(case=BAD_ACTIONS)
def test_sim_ignores_malformed_actions_and_the_plant_does_not_move(
    sim_alone: SimAlone, case: tuple[str, Time | None, list[str], list[float]]
) -> None:
    kind, stamp, names, effort = case
    sim = sim_alone
    now, x = sim.current()
    if stamp is not None and (stamp.sec, stamp.nanosec) == (now.sec, now.nanosec):
        stamp = Time(sec=now.sec + 1, nanosec=now.nanosec)  # stale means: not the current state's
    bad = JointState(name=names, effort=effort)
    bad.header.stamp = now if stamp is None else stamp
    good = JointState(name=["joint_0"], effort=[0.05])
    good.header.stamp = now
    seen = len(sim.states)
    sim.actions.publish(SEAL.seal_header(bad, "0/0"))
    sim.actions.publish(SEAL.seal_header(good, "0/0"))  # in order: had the bad one moved the plant, this is stale
    sim.client.wait_for(lambda: len(sim.states) > seen, TIMEOUT, "the state after the good action")
    nxt = sim.states[seen]
    tried["sim actions"] += 1
    tried[f"sim actions: {kind}"] += 1
    got = np.concatenate([nxt.position, nxt.velocity])
    np.testing.assert_allclose(got, sim.expert.A @ x + sim.expert.B @ np.array([0.05]), rtol=0, atol=1e-9)
    assert len(sim.states) == seen + 1


def test_sim_logged_each_kind_and_is_alive(sim_alone: SimAlone, launch_module: Launcher) -> None:
    log = launch_module.log(sim_alone.proc)
    for kinds in (["stale"], ["wrong joint names"], ["effort has", "effort is empty"], ["effort must be finite"]):
        assert any(f"ignored an action: {kind}" in log for kind in kinds), kinds
    launch_module.assert_alive(sim_alone.proc)


# ----------------------------------------------------------------------------- parameters
def quoted(text: str) -> str:
    return f"'{text}'"  # a YAML string, so "-3" stays the string parameter it is declared as


# Magnitudes whose repr has no exponent: "1e-05" would reach the node as a string, not a double.
NEGATIVE = st.floats(max_value=-1e-3, min_value=-1e9)
OUTSIDE_UNIT = st.one_of(NEGATIVE, st.just(0.0), st.floats(min_value=1.0, max_value=1e6))
BAD_SIM_PARAMS = st.one_of(
    NAMES.filter(lambda t: t not in ("lqr_2_1", "lqr_6_2")).map(lambda t: ({"task": quoted(t)}, "unknown task")),
    st.integers(-(2**31), 0).map(lambda h: ({"horizon": h}, "parameter horizon must be an integer")),
    st.integers(100_001, 2**31).map(lambda h: ({"horizon": h}, "parameter horizon must be an integer")),
)  # fmt: skip
BAD_EXPERT_PARAMS = st.one_of(
    OUTSIDE_UNIT.filter(lambda g: g != 1.0).map(lambda g: ({"gamma": g}, "gamma must")),
    st.integers(-1000, 0).map(lambda h: ({"max_horizon": h}, "parameter max_horizon must be an integer")),
    st.integers(-1000, 0).map(lambda q: ({"max_queue": q}, "parameter max_queue must be an integer in [1, inf]")),
)
BAD_SUPERVISOR_PARAMS = st.one_of(
    NEGATIVE.map(lambda e: ({"epsilon": e}, "epsilon must be finite and > 0")),
    st.one_of(NEGATIVE, st.just(0.0)).map(lambda v: ({"lipschitz": quoted(repr(v))}, "lipschitz must be")),
    OUTSIDE_UNIT.map(lambda v: ({"p": v}, "p must")),
    OUTSIDE_UNIT.map(lambda v: ({"delta": v}, "delta must")),
    NAMES.filter(lambda c: c not in ("i", "ii")).map(lambda c: ({"condition": quoted(c)}, "condition must be")),
)


@pytest.mark.long
@settings(FUZZ, max_examples=8)
@given(sim=BAD_SIM_PARAMS, expert=BAD_EXPERT_PARAMS, supervisor=BAD_SUPERVISOR_PARAMS)
def test_bad_parameters_refuse_to_start_with_the_reason(
    graph: Graph,
    launch_module: Launcher,
    sim: tuple[dict[str, Any], str],
    expert: tuple[dict[str, Any], str],
    supervisor: tuple[dict[str, Any], str],
) -> None:
    """Three nodes at once per example (they start in parallel); the supervisor points at the /bad run."""
    cases = {
        "sim": sim,
        "expert": expert,
        "supervisor": ({**supervisor[0], "run_dir": str(graph.run_dir)}, supervisor[1]),
    }
    procs = {name: start_node(launch_module, name, params, namespace="/refused") for name, (params, _) in
             cases.items()}  # fmt: skip
    for name, proc in procs.items():
        assert proc.wait(timeout=120) == 2, launch_module.log(proc)
        assert cases[name][1] in launch_module.log(proc), launch_module.log(proc)
        tried[f"parameters: {name}"] += 1
    assert sha256(graph.run_file) == graph.run_hash
    graph.all_alive()


@pytest.mark.parametrize(
    ("node", "extra", "parameter", "reason"),
    [
        ("sim", [], "horizn:=50", "unknown parameter 'horizn'; did you mean 'horizon'?"),
        ("policy", [], "lipschitz:=3.0", "unknown parameter 'lipschitz'; known: none"),
        ("supervisor", [], "run_dir:=", "parameter run_dir has no value"),
        ("expert", ["stray"], "gamma:=0.5", "unexpected argument 'stray'"),
    ],
)
def test_unknown_empty_and_stray_arguments_are_refused_in_one_line(
    node: str, extra: list[str], parameter: str, reason: str
) -> None:
    cmd = [sys.executable, "-m", NODES[node].module, *extra, "--ros-args", "-r", "__ns:=/refused"]
    done = subprocess.run([*cmd, "-p", parameter], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert reason in done.stderr and "Traceback" not in done.stderr, done.stderr
    tried["parameters: refused names and arguments"] += 1


def test_whole_numbers_are_accepted_for_float_and_number_parameters(launch_module: Launcher, tmp_path: Path) -> None:
    """`-p lipschitz:=300 -p epsilon:=30` (integers on the command line) start a supervisor; it waits for a sim."""
    params = {"lipschitz": 300, "epsilon": 30, "run_dir": str(tmp_path / "run")}
    proc = launch_module("npp-supervisor", params, namespace="/accepts")
    deadline = time.monotonic() + 120
    while "waiting for the sim's plant description" not in launch_module.log(proc):
        launch_module.assert_alive(proc)
        assert time.monotonic() < deadline, launch_module.log(proc)
        time.sleep(0.2)
    launch_module.assert_alive(proc)
    assert launch_module.stop(proc) == 0, launch_module.log(proc)


# ----------------------------------------------------------------------------- run file for other dims
def test_supervisor_refuses_a_run_file_for_other_dimensions(graph: Graph, tmp_path: Path) -> None:
    """A run folder holding a file shaped for 12 states and 2 actions, for a sim running lqr_2_1 (4 and 1):
    the supervisor stops with the reason and touches nothing."""
    expert = LQRExpert("lqr_2_1", 0, horizon=HORIZON)
    config = build_config("lqr_2_1", 0, resolve_lipschitz("lqr_2_1", "analytic", expert), 50.0, horizon=HORIZON)
    path = tmp_path / "run" / "run.sqlite"
    RunStore.create(path, replace(config, state_dim=12, action_dim=2).metadata()).close()
    before = sha256(path)
    launch_module = graph.launch
    proc = launch_module("npp-supervisor", {"run_dir": str(path.parent), "epsilon": 50.0}, namespace="/bad")
    assert proc.wait(timeout=120) == 1
    log = launch_module.log(proc)
    assert "belongs to another run and was left untouched" in log and "state_dim: file has 12" in log, log
    assert sha256(path) == before
    tried["run files: other dimensions"] += 1
    graph.all_alive()
    assert sha256(graph.run_file) == graph.run_hash
