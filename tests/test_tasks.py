"""The task registry: every task's plant matches what it declares, and choices a task cannot honour are refused."""

from __future__ import annotations

import numpy as np
import pytest

from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.run.setup import build_config, build_loop, initial_state_fn, resolve_lipschitz
from npp_ros.tasks.builtin import lqr
from npp_ros.tasks.registry import TASK_NAMES, ExpertOptions, UnknownTaskError, by_task, episode_rng, get_task


def test_registry_names_the_five_tasks() -> None:
    assert TASK_NAMES == ("acrobot_swingup", "cartpole_swingup", "lqr_2_1", "lqr_6_2", "pendulum_swingup")
    with pytest.raises(UnknownTaskError, match=r"unknown task 'pendulum'; known tasks: acrobot_swingup, cartpole"):
        get_task("pendulum")


def test_help_texts_list_every_built_in_task() -> None:
    """by_task, behind every command's help, covers each built-in task (the acrobot too) in the registry's order."""
    listed = by_task("default_certify")
    assert [entry.split()[1] for entry in listed.split(", ")] == list(TASK_NAMES)
    assert "oracle acrobot_swingup" in listed


@pytest.mark.parametrize("name", TASK_NAMES)
def test_each_plant_has_the_declared_dimensions_and_rho(name: str) -> None:
    task = get_task(name)
    plant = task.make_plant(0)
    assert (plant.task, plant.state_dim, plant.action_dim) == (name, task.state_dim, task.action_dim)
    s0 = task.initial_state(3, 7)
    assert s0.shape == (task.state_dim,)
    np.testing.assert_array_equal(s0, initial_state_fn(name, 3)(7))  # one stream per (seed, episode)
    np.testing.assert_array_equal(plant.reset(s0), plant.state())


@pytest.mark.parametrize("name", ["lqr_2_1", "lqr_6_2"])
def test_lqr_entries_keep_the_lqr_modules_numbers(name: str) -> None:
    task = get_task(name)
    np.testing.assert_array_equal(task.initial_state(0, 5), lqr.sample_initial_state(name, episode_rng(0, 5)))
    assert (task.default_certify, task.default_lipschitz_choice(), task.epsilon(None)) == (
        "rollout",
        "analytic",
        lqr.PAPER_EPSILON[name],
    )


def test_lipschitz_choices_a_task_cannot_resolve_are_refused() -> None:
    pendulum = get_task("pendulum_swingup")
    expert = pendulum.make_expert(0, 50, ExpertOptions(time_budget=30.0, max_iterations=2))
    assert pendulum.default_lipschitz_choice() == "paper"
    assert resolve_lipschitz("pendulum_swingup", "paper", expert).value == 4300.0
    with pytest.raises(ValueError, match=r"'analytic' is not available for pendulum_swingup: its 0/1 reward"):
        resolve_lipschitz("pendulum_swingup", "analytic", expert)
    cartpole = get_task("cartpole_swingup")
    with pytest.raises(ValueError, match=r"no analytic, paper or own L: pass --lipschitz"):
        cartpole.default_lipschitz_choice()
    with pytest.raises(ValueError, match=r"the paper gives no epsilon for cartpole_swingup: pass --epsilon"):
        cartpole.epsilon(None)


def test_expert_options_a_task_cannot_honour_are_refused() -> None:
    with pytest.raises(ValueError, match=r"lqr_2_1 expert is closed form: time_budget do not apply"):
        get_task("lqr_2_1").make_expert(0, 50, ExpertOptions(time_budget=2.0))
    with pytest.raises(ValueError, match=r"gamma must be 1"):
        get_task("pendulum_swingup").make_expert(0, 50, ExpertOptions(gamma=0.9))
    with pytest.raises(ValueError, match=r"pendulum_swingup has no 'detuned' expert; it has ilqr"):
        get_task("pendulum_swingup").make_expert(0, 50, ExpertOptions(kind="detuned"))


def test_pendulum_defaults_to_oracle_and_rollout_needs_window_values() -> None:
    task = get_task("pendulum_swingup")
    assert task.default_certify == "oracle"
    options = ExpertOptions(time_budget=30.0, max_iterations=2, values="return-to-go")
    expert = task.make_expert(0, 50, options)
    lipschitz = resolve_lipschitz(task.name, "paper", expert)
    with pytest.raises(ValueError, match=r"certify=rollout needs an upper bound .* depend on the time left"):
        build_loop(build_config(task.name, 0, lipschitz, 10.0, horizon=50, certify="rollout"), expert)
    window = task.make_expert(0, 50, ExpertOptions(time_budget=30.0, max_iterations=2))
    assert window.values == "window"
    answer = window.trajectory(task.initial_state(0, 0))
    assert answer.expert_return == answer.values[0]  # the oracle mode's V^E(s0)


def test_a_run_records_the_fingerprint_of_its_plant() -> None:
    lipschitz = LipschitzConstant(50.0, "paper")
    fingerprints = {}
    for task in ("lqr_2_1", "pendulum_swingup"):
        config = build_config(task, 0, lipschitz, 50.0)
        assert config.metadata().plant_fingerprint == config.plant_fingerprint
        assert config.plant_fingerprint == get_task(task).make_plant(0).model_sha256()
        fingerprints[task] = config.plant_fingerprint
    assert len(set(fingerprints.values())) == 2
