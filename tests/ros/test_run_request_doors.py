"""Every door to a run takes every setting of the run request: npp-learn's and npp-run's options, npp-experiment's
(under its own names where it runs values side by side), the supervisor's and the expert's parameters,
npp_ros.learn's keywords and GraphClient.start's, each by the request's one help text. Nothing starts a run."""

from __future__ import annotations

import argparse
from dataclasses import replace
from typing import Any

import pytest
from rclpy.parameter import Parameter

import npp_ros
from npp_ros.cli import experiment, learn
from npp_ros.cli.args import flag, run_request
from npp_ros.experiment.arms import arm_request
from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.run.request import EXPERT_FIELDS, FIELD_NAMES, PLANT_FIELDS, RunRequest, request_fields
from npp_ros_graph.client import npp_run_argv
from npp_ros_graph.graph import npp_run_options
from npp_ros_graph.graph.description import request_parameters, run_options
from npp_ros_graph.nodes.expert import PARAMETERS as EXPERT_PARAMETERS
from npp_ros_graph.nodes.sim import PARAMETERS as SIM_PARAMETERS
from npp_ros_graph.nodes.supervisor.node import PARAMETERS as SUPERVISOR_PARAMETERS
from npp_ros_graph.nodes.supervisor.node import SupervisorSettings

# One value per field, none of them its default: a door that drops one is caught.
GIVEN: dict[str, Any] = {
    "task": "pendulum_swingup", "seed": 3, "epsilon": 12.5, "lipschitz": "data", "certify": "oracle",
    "rule": "mixture", "policy": "open-loop", "policy_lipschitz": "select", "condition": "i", "p": 0.8,
    "delta": 0.05, "horizon": 200,
    "gamma": 1.0, "explore": 0.5, "uncertainty": 1.0, "expert_model": "nominal", "max_episodes": 7, "time_budget": 30.0,
    "expert_stop": "time", "values": "return-to-go", "max_iterations": 4,
}  # fmt: skip
# npp-experiment runs these side by side, under its own option names; every other field under the request's.
EXPERIMENT_NAMES = {
    "task": "--tasks", "seed": "--seeds", "rule": "--rules", "policy": "--policies", "expert_model": "--expert-models"
}  # fmt: skip


def argv_of(request: RunRequest, names: tuple[str, ...] = FIELD_NAMES) -> list[str]:
    argv: list[str] = []
    for name in names:
        value = getattr(request, name)
        argv += [flag(name), str(value.value if isinstance(value, LipschitzConstant) else value)]
    return argv


def test_every_field_has_one_help_text_and_the_given_values_are_a_request() -> None:
    assert set(GIVEN) == set(FIELD_NAMES)
    request = RunRequest(**GIVEN)
    assert set(request.changed()) == set(GIVEN) - {"condition", "gamma"}  # those two are their defaults here
    for field, setting in request_fields():
        assert setting.text(), field.name


@pytest.mark.parametrize("parser", [learn.parser, npp_run_options.parser], ids=["npp-learn", "npp-run"])
def test_every_field_is_an_option_with_the_requests_help(parser: Any) -> None:
    ap: argparse.ArgumentParser = parser()
    request = RunRequest(**GIVEN)
    assert run_request(ap.parse_args(argv_of(request))) == request
    helps = {action.dest: action.help for action in ap._actions}
    for field, setting in request_fields():
        assert helps[field.name] == setting.text(), field.name


def test_npp_experiment_takes_every_field_with_the_requests_help_and_makes_the_same_request() -> None:
    ap = experiment.parser()
    by_flag = {option: action for action in ap._actions for option in action.option_strings}
    for field, setting in request_fields():
        action = by_flag[EXPERIMENT_NAMES.get(field.name, flag(field.name))]
        if field.name not in ("task", "seed"):
            assert setting.text() in (action.help or ""), field.name
    args = ap.parse_args(["--tasks", "pendulum_swingup", "--seeds", "3", "--epsilon", "12.5", "--lipschitz", "data",
                          "--certify", "oracle", "--rules", "mixture", "--policies", "open-loop", "--p", "0.8",
                          "--delta", "0.05", "--horizon", "200", "--explore", "0.5", "--max-episodes", "7",
                          "--time-budget", "30", "--expert-stop", "time", "--policy-lipschitz", "select",
                          "--condition", "i", "--gamma", "1", "--uncertainty", "1", "--expert-models", "nominal",
                          "--values", "return-to-go", "--max-iterations", "4"])  # fmt: skip
    settings, arms = experiment.plan(args)
    assert (settings.p, settings.delta, settings.horizon, settings.time_budget, settings.stop) == (
        0.8, 0.05, 200, 30.0, "time"
    )  # fmt: skip
    optimizer = (settings.condition, settings.gamma, settings.values, settings.max_iterations)
    assert optimizer == ("i", 1.0, "return-to-go", 4)
    assert [(a.lipschitz, a.certify, a.rule, a.policy, a.explore, a.policy_lipschitz, a.uncertainty, a.expert_model)
            for a in arms] == [("data", "oracle", "mixture", "open-loop", 0.5, "select", 1.0, "nominal")]  # fmt: skip
    assert arm_request(arms[0], 3, settings) == RunRequest(**GIVEN)  # what npp-learn is asked for the same run


def test_npp_run_passes_every_field_to_the_graph() -> None:
    """The plant's fields to the sim, the expert's options to the expert, every other field to the supervisor, whose
    parameters read them back into the same request (the plant's fields it learns from the sim)."""
    request = RunRequest(**GIVEN)
    params = request_parameters(request, "runs/x")
    assert params["sim"] == {name: GIVEN[name] for name in PLANT_FIELDS}
    assert set(params["expert"]) == set(EXPERT_FIELDS)
    assert set(params["supervisor"]) - {"run_dir"} == set(FIELD_NAMES) - set(PLANT_FIELDS)
    declared = {p.name for p in SUPERVISOR_PARAMETERS}
    assert set(FIELD_NAMES) - set(PLANT_FIELDS) <= declared
    assert set(EXPERT_FIELDS) <= {p.name for p in EXPERT_PARAMETERS}
    assert set(PLANT_FIELDS) <= {p.name for p in SIM_PARAMETERS}
    read = {}
    for param in SUPERVISOR_PARAMETERS:
        value = params["supervisor"].get(param.name, param.default)
        if isinstance(param.default, str) and not isinstance(value, str):
            value = str(value)  # what a text parameter takes a number for (declare_settings)
        read[param.name] = value if param.read is None else param.read(value)
    settings = SupervisorSettings.from_parameters(**read)
    plant = {name: GIVEN[name] for name in PLANT_FIELDS}
    assert replace(settings.request, **plant) == request


def test_the_task_decides_is_task_on_every_node() -> None:
    params = request_parameters(RunRequest(horizon=50), "runs/x")
    for role in ("expert", "supervisor"):
        for name, value in params[role].items():
            if name in FIELD_NAMES and getattr(RunRequest(), name) is None:
                assert value == "task", (role, name)
    assert Parameter("epsilon", value=params["supervisor"]["epsilon"]).value == "task"


def test_npp_learn_takes_every_field_as_a_keyword_and_refuses_a_typo_before_any_work(tmp_path) -> None:
    with pytest.raises(TypeError, match=r"unknown run setting epsilonn"):
        npp_ros.learn("lqr_2_1", epsilonn=3, run_dir=tmp_path / "run")
    with pytest.raises(ValueError, match=r"p must lie in \(0, 1\), got 1.5"):  # every field is taken and checked
        settings = {name: value for name, value in GIVEN.items() if name != "task"}
        npp_ros.learn("lqr_2_1", **{**settings, "p": 1.5}, run_dir=tmp_path / "run")
    with pytest.raises(ValueError, match=r"p must lie in \(0, 1\), got 1.5"):  # or a whole request
        npp_ros.learn(RunRequest(), p=1.5, run_dir=tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_graph_client_start_gives_npp_run_every_field(tmp_path) -> None:
    """The argv GraphClient.start hands npp-run, from a request's fields, parses back into the same request."""
    request = RunRequest(**GIVEN)
    options = {k: v for k, v in run_options(request).items() if k not in ("task", "seed")}
    argv = npp_run_argv(request.task, request.seed, tmp_path, None, options)
    args = npp_run_options.parser().parse_args(argv[argv.index("--task") :])
    assert run_request(args) == request
