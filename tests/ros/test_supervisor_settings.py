"""The supervisor's parameters as the node reads them (declare_settings on a real rclpy node, no graph): a value
the task decides is `task` on the ROS side and None in the core, and the parameters are checked at start by the
code the run's spec is built with, with nothing standing in for what the task decides."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
import rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter

from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.run.setup import build_config, resolve_lipschitz
from npp_ros.tasks.registry import get_task
from npp_ros_graph.nodes.supervisor.node import PARAMETERS, SupervisorSettings
from npp_ros_graph.transport.parameters import StartupError, declare_settings, task_or_number_value

CONDITION_II_ROLLOUT = r"condition \(ii\) cannot certify with certify=rollout"


@pytest.fixture
def settings_of() -> Iterator[Any]:
    context = rclpy.Context()
    rclpy.init(context=context)

    def settings(**given: Any) -> SupervisorSettings:
        overrides = [Parameter(name, value=value) for name, value in given.items()]
        node = Node("npp_supervisor_settings", context=context, parameter_overrides=overrides)
        try:
            return declare_settings(node, PARAMETERS, SupervisorSettings)
        finally:
            node.destroy_node()

    yield settings
    rclpy.shutdown(context=context)


def test_epsilon_certify_and_rule_are_the_tasks_until_given(settings_of) -> None:
    default = settings_of()
    assert (default.epsilon, default.certify, default.rule) == (None, None, None)
    assert settings_of(epsilon=30).epsilon == 30.0  # a whole number on the command line
    assert settings_of(epsilon=12.5, certify="oracle", rule="mixture").epsilon == 12.5
    assert settings_of(epsilon="task").epsilon is None
    for value in (None, 7.25):  # what npp-run passes for its --epsilon
        assert settings_of(epsilon=task_or_number_value(value)).epsilon == value


def test_lipschitz_is_read_once_into_the_cores_type(settings_of) -> None:
    """task -> None (the task decides), a named choice as it is, a number as a user's L; anything else refused."""
    assert settings_of().lipschitz is None and settings_of(lipschitz="task").lipschitz is None
    assert settings_of(lipschitz="data").lipschitz == "data"
    user = settings_of(lipschitz="250").lipschitz
    assert isinstance(user, LipschitzConstant) and (user.value, user.source) == (250.0, "user")
    refusal = r"parameter lipschitz must be one of: task, analytic, paper, data, a number > 0, got 'steep'"
    with pytest.raises(StartupError, match=refusal):
        settings_of(lipschitz="steep")


def test_a_bad_epsilon_is_refused_at_start_with_the_specs_own_reason(settings_of) -> None:
    with pytest.raises(StartupError, match=r"parameter epsilon must be one of: task, a number > 0, got 'many'"):
        settings_of(epsilon="many")
    for value in (-1.0, 0.0):  # 0 is no sentinel: "the task's" is spelled task
        with pytest.raises(StartupError, match=rf"epsilon must be finite and > 0, got {value}"):
            settings_of(epsilon=value)


def test_what_the_task_decides_is_checked_when_the_spec_is_built_by_the_same_code(settings_of) -> None:
    """condition (ii) with certify=rollout is refused at start; with certify left to the task it starts, and the
    run's own spec refuses it in the same words once the task (lqr_2_1: rollout) is known."""
    with pytest.raises(StartupError, match=CONDITION_II_ROLLOUT):
        settings_of(condition="ii", certify="rollout")
    settings = settings_of(condition="ii")
    expert = get_task("lqr_2_1").make_expert(0, 10)
    lipschitz = resolve_lipschitz("lqr_2_1", "analytic", expert)
    with pytest.raises(ValueError, match=CONDITION_II_ROLLOUT):
        build_config("lqr_2_1", 0, lipschitz, 50.0, condition=settings.condition, certify=settings.certify)
