"""npp-experiment takes every run setting, refuses what a run or its task would refuse before any worker starts
(one line, exit code 2, no folder made), names its arms apart by every setting they differ in, and checks a run on
a set of robots on fresh (s0, robot) draws, as npp-learn does."""

from __future__ import annotations

import csv
import shlex
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from npp_ros.cli import experiment, learn
from npp_ros.cli.args import run_request
from npp_ros.experiment.arms import Arm, ExperimentSettings, arm_request, default_arms, make_expert
from npp_ros.experiment.evaluation import compares_with_expert, held_out_asks_expert
from npp_ros.experiment.expert_requests import ExpertReturns
from npp_ros.experiment.report import held_out_verdict
from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import Dataset
from npp_ros.run.held_out import (
    EXPERIMENT_HELD_OUT_STREAM,
    HeldOutCheck,
    check_policy,
    held_out_robots,
    held_out_states,
)
from npp_ros.run.request import resolve_run
from npp_ros.run.setup import uncertainty_record
from npp_ros.tasks.registry import get_task

REPO = Path(__file__).resolve().parents[1]
NO_SUCCESS = str(REPO / "examples" / "two_link_arm" / "task.toml")  # a task file that states no success criterion


@pytest.mark.parametrize(
    ("argv", "reason"),
    [
        (["--epsilon", "-5", "--tasks", "lqr_2_1"], "epsilon must be finite and > 0, got -5.0"),
        (["--tasks", NO_SUCCESS, "--certify", "success"], "certify=success judges the policy's own rollout"),
        (["--tasks", "pendulum_swingup", "--uncertainty", "-0.5"], "the uncertainty factor must be finite and >= 0"),
        (["--tasks", "lqr_2_1", "--uncertainty", "1"], "lqr_2_1 declares nothing uncertain"),
        (["--tasks", "lqr_2_1", "--expert-models", "nominal"], "expert model nominal needs a set of robots"),
        (["--tasks", "lqr_2_1", "--max-iterations", "0"], "argument --max-iterations: must be an integer >= 1"),
        (["--tasks", "lqr_2_1", "--gamma", "0.9"], "npp-experiment's evaluations and held-out checks measure"),
        (["--tasks", "lqr_2_1", "--gamma", "1.5"], "gamma must lie in (0, 1], got 1.5"),
        (["--tasks", "lqr_2_1", "--condition", "ii"], "condition (ii) claims a mean gap"),
    ],
)
def test_a_refused_setting_is_one_line_before_any_worker_and_no_folder(
    argv: list[str], reason: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    try:
        code = experiment.main([*argv, "--seeds", "0", "--out", str(out)])
    except SystemExit as exit:  # argparse's own refusal of a malformed value
        code = exit.code
    err = capsys.readouterr().err
    assert code == 2, err
    assert reason in err and err.startswith(("npp-experiment: ", "usage: npp-experiment")), err
    assert "Traceback" not in err and "worker" not in err.lower()
    assert not out.exists()


def test_a_task_refusal_names_the_arm_and_seed() -> None:
    refused = r"^lqr_2_1-optimal-Lpaper-feedback-u1 seed 0: lqr_2_1 declares nothing uncertain"
    with pytest.raises(ValueError, match=refused):
        experiment.plan(experiment.parser().parse_args(["--tasks", "lqr_2_1", "--seeds", "0", "--uncertainty", "1"]))


def test_arms_differ_by_their_set_of_robots_and_expert_model_and_keep_the_exact_models_names() -> None:
    arms = default_arms(
        ["pendulum_swingup"], ["paper"], None, ["success"], ["mixture"], ["feedback"],
        uncertainty=(0.0, 1.0), expert_models=("robot", "nominal"),
    )  # fmt: skip
    assert [a.name for a in arms] == [
        "pendulum_swingup-ilqr-Lpaper-success-mixture-feedback",  # the exact model: the name it always had
        "pendulum_swingup-ilqr-Lpaper-success-mixture-feedback-u1",
        "pendulum_swingup-ilqr-Lpaper-success-mixture-feedback-u1-nominal-expert",
    ]  # the exact model with the nominal expert changes nothing: not an arm
    acts = [a.acts for a in arms]
    assert len(set(acts)) == 3 and "robots of uncertainty 1" in acts[1] and "nominal model" in acts[2]
    assert Arm("lqr_2_1", "optimal", "paper").name == "lqr_2_1-optimal-Lpaper"
    with pytest.raises(ValueError, match="expert model nominal needs a set of robots"):
        Arm("pendulum_swingup", "ilqr", "paper", expert_model="nominal")


def test_optimizer_options_reach_the_optimizer_experts_only() -> None:
    settings = ExperimentSettings(max_episodes={"lqr_2_1": 5, "pendulum_swingup": 5}, values="window", max_iterations=3)
    lqr = arm_request(Arm("lqr_2_1", "optimal", "analytic"), 0, settings)
    pendulum = arm_request(
        Arm("pendulum_swingup", "ilqr", "paper", "oracle", "sequential", uncertainty=0.5), 0, settings
    )
    assert (lqr.values, lqr.max_iterations) == (None, None)  # closed-form experts take no optimizer options
    assert (pendulum.values, pendulum.max_iterations, pendulum.uncertainty) == ("window", 3, 0.5)


def test_a_set_of_robots_is_checked_against_the_expert_and_a_success_claim_asks_it_nothing() -> None:
    on_a_set = Arm("pendulum_swingup", "ilqr", "paper", "success", "mixture", "feedback", uncertainty=1.0)
    assert not held_out_asks_expert(on_a_set, "success")
    oracle = replace(on_a_set, certify="oracle", rule="sequential")
    assert compares_with_expert(oracle, "oracle") and held_out_asks_expert(oracle, "oracle")
    success = HeldOutCheck(100, "the task's success criterion", 95, 0.95, 0.9, False, 0, np.nan, np.nan, 1.0)
    assert held_out_verdict(success, 0.9, 0.1) == "held (95.0% succeeded)"


@pytest.mark.parametrize("model", ["robot", "nominal"])
def test_the_held_out_answers_asked_ahead_on_robots_are_the_ones_npp_learns_check_asks(model: str) -> None:
    """The experiment asks the expert ahead, in chunks, on (s0, robot) pairs; the held-out check given them is the
    check that asks them itself (npp-learn's), for the expert planning on each robot or on the nominal model."""
    arm = Arm("pendulum_swingup", "ilqr", "5", "oracle", "sequential", uncertainty=0.5, expert_model=model)
    settings = ExperimentSettings(max_episodes={arm.task: 5}, horizon=150, time_budget=120.0, max_iterations=3)
    task, expert = get_task(arm.task), make_expert(arm, 0, settings)
    states = held_out_states(arm.task, 0, 3, EXPERIMENT_HELD_OUT_STREAM)
    robots = held_out_robots(uncertainty_record(arm.task, 0, arm.uncertainty, model), 0, len(states))
    assert robots is not None and len(set(robots)) == 3  # a fresh robot per s0
    asked = ExpertReturns(arm, 0, settings, states, expert, chunk=2, robots=robots).result()
    data = Dataset(task.state_dim, task.action_dim)
    data.append(expert.trajectory(states[0]))
    policy = NonparametricPolicy(data, 5.0)
    plant = task.make_plant(0)

    def check(returns: np.ndarray | None) -> HeldOutCheck:
        return check_policy(
            policy, task, plant, expert, states, settings.horizon, epsilon=10.0, p=0.9, delta=0.1,
            against_expert=True, expert_returns=returns, robots=robots, expert_model=model,
        )  # fmt: skip

    mine, learns = check(asked), check(None)
    same = {"wall_time": 0.0, "visited_slope": 0.0}  # the clock, and NaN: no value slope known in closed form
    assert replace(mine, **same) == replace(learns, **same)
    exact = ExpertReturns(replace(arm, uncertainty=0.0, expert_model="robot"), 0, settings, states, expert).result()
    assert not np.array_equal(asked, exact)  # the robots changed the answers


def readme_commands(path: Path) -> list[list[str]]:
    """The npp-experiment commands of a page's shell blocks (continuations joined, comments dropped)."""
    text = path.read_text().split("```bash\n", 1)[1].split("```", 1)[0].replace("\\\n", " ")
    lines = [line.split("#", 1)[0].split() for line in text.splitlines()]
    return [line[1:] for line in lines if line and line[0].endswith("npp-experiment")]


def test_the_robust_certificates_commands_make_the_runs_its_rows_were_made_by() -> None:
    """Each row of results/robust-certificates was one npp-learn run; the page's npp-experiment commands plan an arm
    whose run is the same run (RunConfig.identity: every setting that decides its answers) within the same budget."""
    folder = REPO / "results" / "robust-certificates"
    made = {}
    for row in csv.DictReader((folder / "results.csv").open()):
        if row["seed"] == "0":
            args = learn.parser().parse_args(shlex.split(row["command"])[1:])
            made[row["arm"]] = (resolve_run(run_request(args)).config.identity(), args.max_episodes)
    planned = {}
    for argv in readme_commands(folder / "README.md"):
        args = experiment.parser().parse_args([*argv, "--seeds", "0"])  # seed 0 is every row's
        settings, arms = experiment.plan(args)
        for arm in arms:
            run = resolve_run(arm_request(arm, 0, settings), kind=arm.expert, control_weight=settings.control_weight)
            planned[arm.name] = (run.config.identity(), settings.max_episodes[arm.task])
    for name, run in made.items():
        assert run in planned.values(), f"{name}: no npp-experiment arm makes its run"
