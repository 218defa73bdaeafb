"""Checks of expert answers against the closed form, shared by the expert, load and bad-input tests."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np
from npp_interfaces.srv import ExpertTrajectory
from rclpy.client import Client

from npp_ros.tasks.builtin.lqr import LQRExpert

if TYPE_CHECKING:
    from tests.ros.conftest import RosClient

TIMEOUT = 60.0


def request(state: list[float] | np.ndarray, horizon: int = 0) -> ExpertTrajectory.Request:
    return ExpertTrajectory.Request(state=[float(x) for x in state], horizon=horizon)


def wait_until_modelling(client: RosClient, expert: Client, timeout: float = TIMEOUT) -> None:
    """The service exists before the plant description arrives: poll until the expert has it."""
    deadline = time.monotonic() + timeout
    while True:
        answer = client.call(expert, request([]), timeout)
        if "no plant description" not in answer.message:
            return
        if time.monotonic() > deadline:
            raise TimeoutError(f"expert never received the plant description: {answer.message}")
        time.sleep(0.1)


def unpack(answer: ExpertTrajectory.Response) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n, m = answer.state_dim, answer.action_dim
    states = np.asarray(answer.states).reshape(-1, n)
    actions = np.asarray(answer.actions).reshape(-1, m)
    return states, actions, np.asarray(answer.values)


def check_good(answer: ExpertTrajectory.Response, expert: LQRExpert, s0: np.ndarray, steps: int) -> None:
    assert answer.success, answer.message
    assert (answer.state_dim, answer.action_dim) == (expert.plant.state_dim, expert.plant.action_dim)
    states, actions, values = unpack(answer)
    assert states.shape == (steps, expert.plant.state_dim) and values.shape == (steps,)
    np.testing.assert_array_equal(states[0], s0)
    np.testing.assert_allclose(values, expert.value(states), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(actions, states @ -expert.K.T, rtol=1e-9, atol=1e-12)
    predicted = states[:-1] @ expert.A.T + actions[:-1] @ expert.B.T
    np.testing.assert_allclose(states[1:], predicted, rtol=0, atol=1e-9)
