"""A task file's run defaults as a user meets them: epsilon refused naming the key and the flag on every path, the
file's L labelled a user's, L = 'data' fixed from the first expert answers and kept on resume, and npp-experiment
taking the horizon (and the rest) from the file."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from npp_ros.certificate.choices import DATA_ANSWERS, DATA_FACTOR
from npp_ros.cli import bench, experiment, learn
from npp_ros.experiment.arms import default_arms
from npp_ros.policy.dataset import Dataset
from npp_ros.run.request import RunRequest, resolve_run
from npp_ros.run.setup import build_config, build_loop, data_slope, resolve_lipschitz
from npp_ros.tasks.registry import ExpertOptions, get_task
from npp_ros.tasks.task_file.loader import TaskFileError, load_task_file

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "two_link_arm"
HORIZON = 10
QUICK = ExpertOptions(time_budget=60.0, max_iterations=2)  # a few iterations: the answers, not their quality


def task_file(tmp_path: Path, *drop: str, add: str = "") -> str:
    """The example's task with the top-level keys ``drop`` removed and ``add`` appended to its top level."""
    shutil.copy(EXAMPLE / "arm.xml", tmp_path / "arm.xml")
    lines = (EXAMPLE / "task.toml").read_text().splitlines()
    kept = [line for line in lines if line.split("=")[0].strip() not in drop]
    first_table = next(i for i, line in enumerate(kept) if line.startswith("["))
    kept.insert(first_table, add)
    (tmp_path / "task.toml").write_text("\n".join(kept) + "\n")
    return get_task(str(tmp_path / "task.toml")).name


def test_a_file_without_epsilon_is_refused_naming_the_key_and_the_flag(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    name = task_file(tmp_path, "epsilon")
    words = r"the task file gives no epsilon: add `epsilon = \.\.\.` to it or pass --epsilon"
    with pytest.raises(ValueError, match=words):
        get_task(name).epsilon(None)
    assert learn.main(["--task", name, "--run-dir", str(tmp_path / "run"), "--evaluate", "0"]) == 2
    assert "npp-learn: the task file gives no epsilon: add `epsilon = ...` to it or pass --epsilon" in (
        capsys.readouterr().err
    )
    assert experiment.main(["--tasks", name, "--out", str(tmp_path / "exp")]) == 2
    assert "npp-experiment: the task file gives no epsilon: add" in capsys.readouterr().err
    assert get_task(name).epsilon(3.0) == 3.0  # the flag gives it


def test_a_task_files_lipschitz_is_a_users_choice_labelled_user(tmp_path: Path) -> None:
    task = get_task(task_file(tmp_path))
    assert task.paper_lipschitz is None and task.default_lipschitz_choice() == 200.0
    expert = task.make_expert(0, HORIZON, QUICK)
    constant = resolve_lipschitz(task.name, None, expert)
    assert (constant.value, constant.source) == (200.0, "user")
    assert "the task file's key lipschitz" in constant.detail
    assert resolve_lipschitz(task.name, "35", expert).source == "user"
    config = build_config(task.name, 0, constant, 20.0, horizon=HORIZON)
    assert config.metadata().lipschitz_source == "user"
    assert expert.requests == 0  # a number asks the expert nothing


def test_a_bad_lipschitz_value_is_refused_naming_the_key(tmp_path: Path) -> None:
    task_file(tmp_path)
    path = tmp_path / "task.toml"
    path.write_text(path.read_text().replace("lipschitz = 200.0", 'lipschitz = "big"'))
    with pytest.raises(TaskFileError, match=r'lipschitz: must be a number > 0 or "data", got \'big\''):
        load_task_file(str(path))


def test_data_lipschitz_is_fixed_from_the_first_answers_and_read_back_on_resume(tmp_path: Path) -> None:
    name = task_file(tmp_path, "lipschitz")
    task = get_task(name)
    assert task.default_lipschitz_choice() == "data"  # a file without the key
    run_file = tmp_path / "run" / "run.sqlite"
    expert = task.make_expert(0, HORIZON, QUICK)
    constant = resolve_lipschitz(name, None, expert, seed=0, horizon=HORIZON, run_file=run_file)
    assert constant.source == "data" and expert.requests == DATA_ANSWERS

    again = task.make_expert(0, HORIZON, QUICK)  # the rule, by hand: the same answers, the same numbers
    answers = Dataset(task.state_dim, task.action_dim)
    for episode in range(DATA_ANSWERS):
        answers.append(again.trajectory(task.initial_state(0, episode), HORIZON))
    stored = data_slope(answers, continued=True)
    assert stored is not None and constant.value == DATA_FACTOR * max(stored.slope, again.slope_floor())
    assert stored.describe() in constant.detail  # the pair it came from, for the user to read

    config = build_config(name, 0, constant, 20.0, horizon=HORIZON)
    loop = build_loop(config, expert, store_path=run_file)
    loop.run(1)
    loop.store.close()  # type: ignore[union-attr]

    fresh = task.make_expert(0, HORIZON, QUICK)
    resumed = resolve_lipschitz(name, "data", fresh, seed=0, horizon=HORIZON, run_file=run_file)
    assert (resumed.value, resumed.source, fresh.requests) == (constant.value, "data", 0)  # read, not measured
    assert "read back from the run file" in resumed.detail
    build_loop(build_config(name, 0, resumed, 20.0, horizon=HORIZON), fresh, store_path=run_file).store.close()  # type: ignore[union-attr]


def test_npp_experiment_takes_the_horizon_and_l_from_the_task_file(tmp_path: Path) -> None:
    name = task_file(tmp_path)
    args = experiment.parser().parse_args(["--tasks", name])
    settings, arms = experiment.plan(args)
    assert settings.horizon == 200 and settings.epsilon_for(name) == 20.0
    assert [(arm.lipschitz, arm.certify) for arm in arms] == [("200", "oracle")]
    mixed = experiment.parser().parse_args(["--tasks", name, "lqr_2_1"])
    with pytest.raises(
        ValueError, match=r"the tasks' own horizons differ \(.*-task 200, lqr_2_1 1000\): pass --horizon"
    ):
        experiment.plan(mixed)
    assert (
        experiment.plan(experiment.parser().parse_args(["--tasks", name, "lqr_2_1", "--horizon", "50"]))[0].horizon
        == 50
    )
    assert [arm.lipschitz for arm in default_arms(["lqr_2_1"], None, ["optimal"])] == ["paper", "analytic"]
    assert [arm.lipschitz for arm in default_arms([task_file(tmp_path, "lipschitz")], None, None)] == ["data"]


def test_a_task_with_no_l_of_its_own_is_refused_naming_the_flag() -> None:
    with pytest.raises(ValueError, match=r"cartpole_swingup has no analytic, paper or own L: pass --lipschitz"):
        get_task("cartpole_swingup").default_lipschitz_choice()


@pytest.mark.parametrize("command", [learn.parser, experiment.parser])
def test_help_says_where_task_file_values_come_from(command: object) -> None:
    text = " ".join(command().format_help().split())  # type: ignore[operator]
    for key in ("key horizon", "key epsilon", "key lipschitz", "key certify", "[expert] time_budget"):
        assert key in text, key


def test_npp_bench_help_says_which_task_file_values_it_uses(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        bench.parse_args(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert (
        "a task file's [expert] keys" in text
        and "default: each task's own (1000 for the built-in tasks, a task file's key horizon)" in text
    )


def test_a_task_files_policy_is_a_runs_default_and_the_command_line_overrides_it(tmp_path: Path) -> None:
    name = task_file(tmp_path, add='policy = "path"')
    assert get_task(name).default_policy == "path"
    request = RunRequest(task=name, horizon=HORIZON, max_iterations=2)
    assert request.policy is None  # the task decides
    assert resolve_run(request).config.spec.policy == "path"
    assert resolve_run(RunRequest.of(request, policy="feedback")).config.spec.policy == "feedback"
    for folder in ("plain", "bad"):
        (tmp_path / folder).mkdir()
    assert get_task(task_file(tmp_path / "plain")).default_policy == "feedback"  # a file without the key
    with pytest.raises(TaskFileError, match="policy: must be one of open-loop, feedback, path, got 'paths'"):
        task_file(tmp_path / "bad", add='policy = "paths"')
