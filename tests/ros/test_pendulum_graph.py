"""The pendulum swing-up through the same graph: the iLQR expert served, and the run equal to the in-process one.

The expert stops by convergence or its iteration cap (a generous time budget), so a request's numbers
do not depend on the machine's speed and the graph must repeat the in-process run number for number.
"""

from __future__ import annotations

import math
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest
from expert_checks import TIMEOUT, request, unpack, wait_until_modelling
from npp_interfaces.srv import ExpertTrajectory
from reference import decisions

from npp_ros.run.setup import build_config, build_loop, resolve_lipschitz
from npp_ros.run.store import RunStore
from npp_ros.tasks.registry import ExpertOptions, get_task
from npp_ros_graph.transport.topics import EXPERT_SERVICE

if TYPE_CHECKING:
    from tests.ros.conftest import Launcher, RosClient

TASK = "pendulum_swingup"
HORIZON = 100
EPSILON = 30.0
EPISODES = 12
BUDGET = 120.0  # seconds per request: never reached, so iterations decide (deterministic)
ITERATIONS = 10
EXPLORE = 0.3  # failed checks also ask where the policy left the data: the supervisor does it as npp-learn does


def test_pendulum_graph_gives_the_in_process_dataset_and_decisions(tmp_path: Path, ros_domain: int) -> None:
    run_dir = tmp_path / "graph"
    command = [
        sys.executable, "-m", "npp_ros_graph.tools.run", "--task", TASK, "--horizon", str(HORIZON),
        "--epsilon", str(EPSILON), "--max-episodes", str(EPISODES), "--run-dir", str(run_dir),
        "--time-budget", str(BUDGET), "--max-iterations", str(ITERATIONS), "--explore", str(EXPLORE),
    ]  # fmt: skip
    run = subprocess.run(command, capture_output=True, text=True, timeout=900)
    logs = "\n".join(f"== {p.name}\n{p.read_text()[-3000:]}" for p in sorted((run_dir / "logs").glob("*.log")))
    assert run.returncode in (0, 1), f"{run.stderr[-3000:]}\n{logs}"  # 1: not certified within the budget
    with RunStore.open(run_dir / "run.sqlite") as store:
        graph_data = store.load_dataset()
        graph_rows = store.episodes()
        metadata = store.metadata
    assert len(graph_rows) == EPISODES, logs
    assert (metadata.certify, metadata.lipschitz_source, metadata.lipschitz) == ("oracle", "paper", 4300.0)
    assert all(row.oracle_called for row in graph_rows)  # oracle mode asks the expert every episode
    assert metadata.explore == EXPLORE and graph_data.num_trajectories == sum(r.trajectories_stored for r in graph_rows)

    task = get_task(TASK)
    expert = task.make_expert(0, HORIZON, ExpertOptions(time_budget=BUDGET, max_iterations=ITERATIONS))
    lipschitz = resolve_lipschitz(TASK, "paper", expert)
    loop = build_loop(build_config(TASK, 0, lipschitz, EPSILON, horizon=HORIZON, explore=EXPLORE), expert)
    local = loop.run(max_episodes=EPISODES)
    assert decisions(graph_rows) == decisions(local.rows)
    assert [r.explored for r in graph_rows] == [r.explored for r in local.rows]
    assert any(r.explored for r in local.rows), "no check asked where the policy went: the test shows nothing"
    assert [(r.checked_gap, r.policy_return) for r in graph_rows] == [
        (r.checked_gap, r.policy_return) for r in local.rows
    ]
    np.testing.assert_array_equal(graph_data.states, loop.dataset.states)
    np.testing.assert_array_equal(graph_data.actions, loop.dataset.actions)
    np.testing.assert_array_equal(graph_data.values, loop.dataset.values)
    assert np.all(np.abs(graph_data.states[:, 0]) <= math.pi)  # the stored angle is wrapped


@pytest.fixture(scope="module")
def pendulum_expert(launch_module: Launcher, ros_client_module: Callable[..., RosClient]) -> tuple[RosClient, Any]:
    """A pendulum sim (H = 100) and the expert it describes, with one queue slot to show 'busy:'."""
    launch_module("npp-sim", {"task": TASK, "seed": 0, "horizon": HORIZON})
    launch_module("npp-expert", {"max_queue": 1, "time_budget": BUDGET, "max_iterations": ITERATIONS})
    client = ros_client_module("pendulum_expert_client")
    service = client.client(ExpertTrajectory, EXPERT_SERVICE, TIMEOUT)
    wait_until_modelling(client, service)
    return client, service


@pytest.mark.parametrize(
    ("state", "fragments"),
    [
        ([0.1], ["1 entries", "expected 2"]),
        ([0.1, 0.2, 0.3], ["3 entries", "expected 2"]),
        ([math.nan, 0.0], ["finite", "state[0] = nan"]),
        ([0.5, math.inf], ["finite", "state[1] = inf"]),
        ([], ["empty", "expected 2"]),
    ],
)
def test_bad_requests_to_the_optimizer_get_precise_errors(
    pendulum_expert: tuple[RosClient, Any], state: list[float], fragments: list[str]
) -> None:
    client, service = pendulum_expert
    # One attempt, however long it takes: a second one sent while the first computes would meet max_queue 1.
    answer = client.call(service, request(state, 0), TIMEOUT, attempt_timeout=TIMEOUT)
    assert not answer.success
    for fragment in fragments:
        assert fragment in answer.message, answer.message
    good = client.call(service, request([3.0, 0.0], 0), TIMEOUT, attempt_timeout=TIMEOUT)  # the node keeps serving
    assert good.success, good.message
    states, _, values = unpack(good)
    expert = get_task(TASK).make_expert(0, HORIZON, ExpertOptions(time_budget=BUDGET, max_iterations=ITERATIONS))
    want = expert.trajectory(np.array([3.0, 0.0]))
    np.testing.assert_array_equal(states, want.states)
    np.testing.assert_array_equal(values, want.values)
    assert good.expert_return == want.expert_return == want.values[0]


def test_a_long_request_leaves_the_service_answering_busy(pendulum_expert: tuple[RosClient, Any]) -> None:
    """While the worker optimises one request, further ones beyond max_queue get 'busy:' at once."""
    client, service = pendulum_expert
    long = request([2.0, 0.0], 5000)  # 5,000 steps: seconds of iLQR
    futures = [service.call_async(long) for _ in range(3)]
    answers = [client.wait_for(f, timeout=600.0, label="expert answer") for f in futures]
    busy = [a for a in answers if not a.success]
    assert any(a.success for a in answers)
    assert busy and all(a.message.startswith("busy:") and "max_queue 1" in a.message for a in busy)


def test_an_answer_cut_by_the_time_budget_is_named_in_the_log(
    launch: Launcher, ros_client: Callable[..., RosClient]
) -> None:
    """A budget no request can meet: the node still answers, and says the answer depends on the machine."""
    namespace = "/budget"
    launch("npp-sim", {"task": TASK, "seed": 0, "horizon": HORIZON}, namespace=namespace)
    expert = launch("npp-expert", {"time_budget": 1e-6, "max_iterations": ITERATIONS}, namespace=namespace)
    client = ros_client("budget_client", namespace=namespace)
    service = client.client(ExpertTrajectory, EXPERT_SERVICE, TIMEOUT)
    wait_until_modelling(client, service)
    answer = client.call(service, request([3.0, 0.0], 0), TIMEOUT)
    assert answer.success, answer.message
    deadline = time.monotonic() + TIMEOUT
    while "stopped at the time budget" not in launch.log(expert) and time.monotonic() < deadline:
        time.sleep(0.2)
    log = launch.log(expert)
    assert "the request from [3. 0.] stopped at the time budget (1e-06 s) before converging" in log, log
    assert "its answer depends on this machine's speed (1 such requests so far" in log
