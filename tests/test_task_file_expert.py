"""A task file's [expert] planner: receding-horizon windows before iLQR, chosen by keys, deterministic."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from npp_ros.tasks.registry import get_task
from npp_ros.tasks.task_file.loader import TaskFileError
from npp_ros.tasks.task_file.schema import EXPERT_KEYS
from npp_ros.trajopt.receding import PLANNER_KEYS, PlannerSettings

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


@pytest.fixture
def acrobot_dir(tmp_path: Path) -> Path:
    """A copy of the acrobot example, to edit."""
    for name in ("acrobot.xml", "task.toml"):
        shutil.copy(EXAMPLES / "acrobot" / name, tmp_path / name)
    return tmp_path


def with_expert(task_dir: Path, expert: str) -> Path:
    """The task file with its [expert] table's keys replaced by ``expert`` (its [[expert.terms]] kept)."""
    path = task_dir / "task.toml"
    head, rest = path.read_text().split("[expert]", 1)
    terms = rest[rest.index("[[expert.terms]]") :] if "[[expert.terms]]" in rest else rest[rest.index("[success]") :]
    path.write_text(f"{head}[expert]\n{expert}\n{terms}")
    return path


def test_every_planner_key_is_an_expert_key() -> None:
    assert set(PLANNER_KEYS) <= EXPERT_KEYS


def test_a_planners_settings_are_described_as_a_file_writes_them() -> None:
    """What npp-bench prints beside an expert's figures: the planner and only the keys it uses."""
    assert PlannerSettings("receding", window=200, commit=10, restarts=1).describe() == (
        'planner = "receding": window 200, commit 10, window_iterations 5, restarts 1'
    )
    assert "samples 32, knots 10, noise 0.3" in PlannerSettings("sampling").describe()


def test_a_file_without_a_planner_keeps_one_ilqr_from_zero() -> None:
    expert = get_task(str(EXAMPLES / "two_link_arm" / "task.toml")).make_expert(0, 20)
    assert expert.settings == PlannerSettings() and expert.settings.planner == "ilqr"
    assert expert.planner is None


@pytest.mark.parametrize(
    ("expert", "expected"),
    [
        ('planner = "mpc"', "expert.planner: must be one of ilqr, receding, sampling, got 'mpc'"),
        ('planner = "receding"\nwindow = 0', "expert.window: must be an integer >= 1, got 0"),
        ('planner = "receding"\nwindow = 50\ncommit = 60', "expert.commit: must be at most window (50), got 60"),
        ('planner = "sampling"\nnoise = -1.0', "expert.noise: must be a finite number > 0, got -1.0"),
        ('planner = "sampling"\nsamples = 1', "expert.samples: must be an integer >= 2, got 1"),
        ('planner = "receding"\nsamples = 16', 'expert.samples: applies to planner = "sampling", not "receding"'),
        ("window = 100", 'expert.window: applies to planner = "receding" or "sampling", not "ilqr"'),
        ('planner = "sampling"\nhorizon = 10', "expert.horizon: unknown key"),
    ],
)
def test_a_bad_planner_key_is_refused_in_one_line_naming_it(acrobot_dir: Path, expert: str, expected: str) -> None:
    path = with_expert(acrobot_dir, expert)
    with pytest.raises(TaskFileError) as caught:
        get_task(str(path))
    message = str(caught.value)
    assert "\n" not in message and expected in message, message


def example_with(task_dir: Path, example: str, model: str, expert: str) -> Path:
    """A copy of an example with its [expert] keys replaced by ``expert``."""
    for name in (model, "task.toml"):
        shutil.copy(EXAMPLES / example / name, task_dir / name)
    return with_expert(task_dir, expert)


def test_receding_windows_swing_the_pendulum_up_where_one_ilqr_does_not(tmp_path: Path) -> None:
    """From a fixed s0 at H = 300 (6 s): the planner's answer holds the pole up over the last second,
    the file's plain iLQR from u = 0 does not, and the planner's return is higher."""
    answers = {}
    for planner in ("receding", "ilqr"):
        folder = tmp_path / planner
        folder.mkdir()
        expert_keys = 'planner = "receding"' if planner == "receding" else ""
        task = get_task(str(example_with(folder, "pendulum", "pendulum.xml", expert_keys)))
        assert task.success is not None
        trajectory = task.make_expert(0, 300).trajectory(task.initial_state(0, 0))
        answers[planner] = (trajectory.expert_return, task.success.met(trajectory.states))
    assert answers["receding"][1] and not answers["ilqr"][1], answers
    assert answers["receding"][0] > answers["ilqr"][0] + 100, answers


@pytest.mark.parametrize(
    "expert",
    [
        'planner = "receding"\nwindow = 30\ncommit = 10\nwindow_iterations = 2\nrestarts = 1',
        'planner = "sampling"\nwindow = 30\ncommit = 10\nsamples = 8\nwindow_iterations = 1\nrestarts = 1',
    ],
)
def test_a_planned_answer_is_the_same_bit_for_bit_and_carries_gains(acrobot_dir: Path, expert: str) -> None:
    """Two requests from one s0, by two experts of the run's seed: identical arrays, and the gains of the
    last iLQR pass over the answer (the feedback policy's)."""
    task = get_task(str(with_expert(acrobot_dir, expert + "\nmax_iterations = 2")))
    s0 = task.initial_state(0, 0)
    first = task.make_expert(0, 40)
    answers = [first.trajectory(s0), first.trajectory(s0), task.make_expert(0, 40).trajectory(s0)]
    assert first.plans_made == 4  # the file states [success], which 40 steps never meet: every restart is tried
    for other in answers[1:]:
        for field in ("states", "actions", "values", "gains"):
            assert np.array_equal(getattr(answers[0], field), getattr(other, field)), field
    gains = answers[0].gains
    assert gains is not None and gains.shape == (40, 1, 4) and np.isfinite(gains).all()


def without_energy_term(path: Path) -> Path:
    """The task file at ``path`` with its [[expert.terms]] energy term taken out."""
    text = path.read_text()
    start = text.index("[[expert.terms]]\nenergy")
    path.write_text(text[:start] + text[text.index("\n[success]") + 1 :])
    return path


@pytest.mark.long
def test_the_energy_term_swings_the_acrobot_up_where_the_same_windows_without_it_do_not(acrobot_dir: Path) -> None:
    """The example's receding windows, one plan and two polishing iterations, from the s0 of episode 3 at
    H = 700 (7 s): with its energy term the answer holds both links up over the last second; the same
    file without the term answers a swing that never rises (the windows settle, pumping nothing)."""
    keys = 'planner = "receding"\nwindow = 200\ncommit = 10\nwindow_iterations = 5\nrestarts = 0\nmax_iterations = 2'
    answers = {}
    for variant in ("energy", "no energy"):
        folder = acrobot_dir / variant.replace(" ", "_")
        folder.mkdir()
        shutil.copy(acrobot_dir / "acrobot.xml", folder / "acrobot.xml")
        shutil.copy(acrobot_dir / "task.toml", folder / "task.toml")
        path = with_expert(folder, keys)
        task = get_task(str(path if variant == "energy" else without_energy_term(path)))
        assert task.success is not None
        trajectory = task.make_expert(0, 700).trajectory(task.initial_state(0, 3))
        answers[variant] = (trajectory.expert_return, task.success.met(trajectory.states))
    assert answers["energy"][1] and not answers["no energy"][1], answers
    assert answers["energy"][0] > answers["no energy"][0] + 100, answers
