"""The expert node answers several optimizer requests at once in worker processes, each answer the
one-at-a-time answer bit for bit (the iteration cap stops the optimizer, not the clock)."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
from expert_checks import TIMEOUT, request, unpack, wait_until_modelling
from npp_interfaces.srv import ExpertTrajectory

from npp_ros.tasks.registry import ExpertOptions, episode_rng, get_task
from npp_ros_graph.transport.topics import EXPERT_SERVICE

if TYPE_CHECKING:
    from tests.ros.conftest import Launcher, RosClient

TASK, HORIZON = "pendulum_swingup", 80
OPTIONS = ExpertOptions(time_budget=120.0, max_iterations=5)


def test_requests_asked_at_once_get_the_one_at_a_time_answers(
    launch: Launcher, ros_client: Callable[..., RosClient]
) -> None:
    namespace = "/workers"
    launch("npp-sim", {"task": TASK, "seed": 0, "horizon": HORIZON}, namespace=namespace)
    expert_node = launch(
        "npp-expert", {"workers": 2, "time_budget": OPTIONS.time_budget, "max_iterations": OPTIONS.max_iterations},
        namespace=namespace,
    )  # fmt: skip
    client = ros_client("workers_client", namespace=namespace)
    service = client.client(ExpertTrajectory, EXPERT_SERVICE, TIMEOUT)
    wait_until_modelling(client, service)
    task = get_task(TASK)
    states = [task.sample_initial_state(episode_rng(5, k)) for k in range(4)]
    futures = [service.call_async(request(s0, 0)) for s0 in states]  # all four waiting at once
    answers = [client.wait_for(f, timeout=600.0, label="expert answer") for f in futures]
    alone = task.make_expert(0, HORIZON, OPTIONS)
    for s0, answer in zip(states, answers, strict=True):
        assert answer.success, answer.message
        want = alone.trajectory(s0)
        got_states, got_actions, got_values = unpack(answer)
        np.testing.assert_array_equal(got_states, want.states)
        np.testing.assert_array_equal(got_actions, want.actions)
        np.testing.assert_array_equal(got_values, want.values)
        assert answer.expert_return == want.expert_return
    deadline = time.monotonic() + TIMEOUT
    while launch.log(expert_node).count("computed a trajectory from s0") < 4 and time.monotonic() < deadline:
        time.sleep(0.2)
    log = launch.log(expert_node)
    assert "computing trajectories in 2 worker processes" in log
    assert log.count("computed a trajectory from s0") == 4  # one line per answer, as one at a time
