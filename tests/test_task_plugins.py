"""Plug-in tasks: registered by entry point, listed with their origin, a broken one named with its error; npp_ros's
own tasks are the registry's, each listed once."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from importlib.metadata import EntryPoint
from pathlib import Path

import numpy as np
import pytest
from plugin_env import with_plugin_path

from npp_ros.tasks import registry as task_registry
from npp_ros.tasks import sources
from npp_ros.tasks.registry import REGISTRY, TASK_NAMES, UnknownTaskError, describe_tasks, get_task, task_names
from npp_ros.tasks.sources import ENTRY_POINT_GROUP, TaskLoadError

ORIGIN = "plug-in npp-demo-tasks 0.1.0"


@pytest.fixture
def plugin_on_path(demo_plugin: Path) -> Iterator[Path]:
    """The demo plug-in visible to this process, as if installed; forgotten again afterwards."""
    sys.path.insert(0, str(demo_plugin))
    task_registry.refresh()
    try:
        yield demo_plugin
    finally:
        sys.path.remove(str(demo_plugin))
        for module in [m for m in sys.modules if m.startswith("npp_demo_tasks")]:
            del sys.modules[module]
        task_registry.refresh()


def test_plugin_tasks_join_the_built_in_ones(plugin_on_path: Path) -> None:
    assert set(task_names()) == {*TASK_NAMES, "demo_pendulum", "demo_broken"}
    task = get_task("demo_pendulum")
    assert task.name == "demo_pendulum" and task.state_dim == 2
    plant = task.make_plant(0)
    assert plant.task == "demo_pendulum"
    assert plant.model_sha256() == get_task("pendulum_swingup").make_plant(0).model_sha256()
    plant.reset(task.initial_state(0, 0))
    assert np.isfinite(plant.step([0.5]))


def test_a_broken_plugin_is_named_with_its_error_and_the_others_still_work(plugin_on_path: Path) -> None:
    with pytest.raises(TaskLoadError) as caught:
        get_task("demo_broken")
    message = str(caught.value)
    for fragment in ("'demo_broken'", ORIGIN, "npp_demo_tasks.broken:TASK", "ModuleNotFoundError",
                     "npp_demo_tasks_missing_dependency"):  # fmt: skip
        assert fragment in message, message
    assert "\n" not in message
    assert get_task("demo_pendulum").name == "demo_pendulum"
    assert get_task("lqr_2_1").experts == ("optimal", "detuned")


def test_a_plugin_cannot_replace_a_built_in_task(plugin_on_path: Path) -> None:
    assert type(get_task("lqr_2_1")).__name__ == "LQRTask"
    assert any("'lqr_2_1'" in p and "ignored" in p and ORIGIN in p for p in task_registry.registration_problems())


def test_the_listing_says_where_each_task_comes_from(plugin_on_path: Path) -> None:
    lines = describe_tasks().splitlines()
    row = {line.split()[0]: line for line in lines[1:] if line.startswith("  ") and not line.startswith("  ignored")}
    assert "built-in" in row["lqr_2_1"] and "npp_ros.tasks.builtin.lqr:LQR_2_1" in row["lqr_2_1"]
    assert ORIGIN in row["demo_pendulum"] and "DOES NOT LOAD" not in row["demo_pendulum"]
    assert ORIGIN in row["demo_broken"] and "DOES NOT LOAD: ModuleNotFoundError" in row["demo_broken"]
    assert any(line.startswith("  ignored: task 'lqr_2_1'") for line in lines)


def test_unknown_names_list_every_task(plugin_on_path: Path) -> None:
    known = r"unknown task 'nope'; known tasks: acrobot_swingup, cartpole_swingup, demo_broken, demo_pendulum, lqr_2_1"
    with pytest.raises(UnknownTaskError, match=known):
        get_task("nope")


def _run(args: list[str], env: dict[str, str], cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(args, env=env, cwd=cwd, capture_output=True, text=True, timeout=600)


def test_command_lines_take_plugin_tasks(demo_plugin: Path, tmp_path: Path) -> None:
    env = with_plugin_path(demo_plugin)
    bin_dir = Path(sys.executable).parent
    listing = _run([str(bin_dir / "npp-learn"), "--list-tasks"], env, tmp_path)
    assert listing.returncode == 0, listing.stderr
    assert ORIGIN in listing.stdout and "demo_pendulum" in listing.stdout and "built-in" in listing.stdout

    broken = _run([str(bin_dir / "npp-learn"), "--task", "demo_broken"], env, tmp_path)
    assert broken.returncode == 2
    assert "argument --task: task 'demo_broken'" in broken.stderr and "ModuleNotFoundError" in broken.stderr
    assert "Traceback" not in broken.stderr

    sim_help = _run([str(bin_dir / "npp-sim"), "--help"], env, tmp_path)
    assert sim_help.returncode == 0 and ORIGIN in sim_help.stdout and "demo_broken" in sim_help.stdout

    learned = _run(
        [str(bin_dir / "npp-learn"), "--task", "demo_pendulum", "--horizon", "30", "--epsilon", "5",
         "--max-episodes", "2", "--time-budget", "0.5", "--evaluate", "0", "--run-dir", str(tmp_path / "run")],
        env, tmp_path,
    )  # fmt: skip
    assert learned.returncode in (0, 1), learned.stderr
    assert "npp-learn: demo_pendulum seed 0" in learned.stderr
    assert (tmp_path / "run" / "run.sqlite").exists()


def test_every_task_of_npp_ros_is_built_in_and_listed_once() -> None:
    """The acrobot is in REGISTRY like the others; npp_ros's own entry point for it, where the installed
    package still declares one, is the same task and neither a second one nor an ignored plug-in."""
    assert "acrobot_swingup" in TASK_NAMES
    assert TASK_NAMES == tuple(sorted(REGISTRY))
    origins = {name: source.origin for name, source in task_registry.registered().items()}
    assert {name: origins[name] for name in TASK_NAMES} == dict.fromkeys(TASK_NAMES, "built-in")
    assert not any("npp_ros" in problem for problem in task_registry.registration_problems())
    rows = [line.split()[0] for line in describe_tasks(check=False).splitlines()[1:] if line.startswith("  ") and
            not line.startswith(("  ignored", "  any path"))]  # fmt: skip
    assert sorted(rows) == rows and set(TASK_NAMES) <= set(rows) and len(rows) == len(set(rows))
    assert all(name in task_registry.unknown("nope") for name in TASK_NAMES)


def test_an_entry_point_that_repeats_a_built_in_task_is_that_task(monkeypatch: pytest.MonkeyPatch) -> None:
    """The same name and target is one task, listed once; the same name with another target is ignored, said so."""
    entries = [EntryPoint("acrobot_swingup", REGISTRY["acrobot_swingup"], ENTRY_POINT_GROUP),
               EntryPoint("lqr_2_1", "elsewhere:LQR", ENTRY_POINT_GROUP)]  # fmt: skip
    monkeypatch.setattr(sources.importlib.metadata, "entry_points", lambda group: entries)
    found, problems = sources.merge(REGISTRY)
    assert set(found) == set(REGISTRY) and all(source.built_in for source in found.values())
    assert found["acrobot_swingup"].target == REGISTRY["acrobot_swingup"]
    assert problems == ("task 'lqr_2_1' of plug-in is ignored: the built-in task has that name",)


def test_the_acrobot_plant_is_what_its_task_declares() -> None:
    task = get_task("acrobot_swingup")
    plant = task.make_plant(0)
    assert (plant.task, plant.state_dim, plant.action_dim, plant.actuated_joint_names) == (
        "acrobot_swingup",
        4,
        1,
        ["elbow"],
    )
    s0 = task.initial_state(0, 0)
    assert s0.shape == (4,) and (s0[2:] == 0).all()
    plant.reset(s0)
    assert 0.0 <= plant.step([1.0]) <= 1.0
