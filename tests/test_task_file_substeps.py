"""A task file's control_timestep as k model timesteps: the plant, the optimizer's dynamics and the reward agree.

The example arm's model steps 0.01 s; a control_timestep of 0.03 s holds each action for k = 3 MuJoCo
steps, as dm_control's n_sub_steps does. The expert's planned states must be the plant's stepped
states bit for bit, and the reward must see the physics after the third step. Also the file's
``[expert] stop``, which chooses what ends a request.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from npp_ros.tasks.registry import ExpertOptions
from npp_ros.tasks.task_file.loader import FileTask, TaskFileError, load_task_file

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "two_link_arm"
SUBSTEPS = 3
HORIZON = 30
S0 = np.array([0.4, -0.7, 1.5, -2.0])  # moving, so one MuJoCo step and three end in different places


def arm_task(tmp_path: Path, **replace: str) -> FileTask:
    """The example arm with its file's lines replaced (old text -> new text)."""
    for name in ("arm.xml", "task.toml"):
        shutil.copy(EXAMPLE / name, tmp_path / name)
    path = tmp_path / "task.toml"
    text = path.read_text()
    for old, new in replace.items():
        assert old in text, old
        text = text.replace(old, new, 1)
    path.write_text(text)
    return load_task_file(str(path))


@pytest.fixture
def substepped(tmp_path: Path) -> FileTask:
    return arm_task(tmp_path, **{"control_timestep = 0.01": f"control_timestep = {0.01 * SUBSTEPS:g}"})


def test_the_expert_plans_the_states_the_plant_steps_through(substepped: FileTask) -> None:
    """The optimizer's rollout of its answer (its own dynamics, k MuJoCo steps a control step) is the
    plant's run of the same actions, bit for bit, and both move k model timesteps a step."""
    plant = substepped.make_plant(0)
    assert plant.substeps == SUBSTEPS and plant.dt == pytest.approx(0.03)
    expert = substepped.make_expert(0, HORIZON, ExpertOptions(max_iterations=3))
    assert expert.optimizer.dynamics.substeps == SUBSTEPS
    solution = expert.solve(S0)
    plant.reset(S0)
    stepped = [plant.raw_state()]
    for action in solution.trajectory.actions:
        plant.step(action)
        stepped.append(plant.raw_state())
    planned = np.vstack([solution.optimization.states, solution.optimization.final_state])
    np.testing.assert_array_equal(planned, np.array(stepped))
    np.testing.assert_array_equal(solution.raw_states, np.array(stepped[:-1]))
    assert plant.physics.data.time == pytest.approx(HORIZON * 0.03)


def test_the_reward_sees_the_physics_after_the_last_substep(substepped: FileTask) -> None:
    plant = substepped.make_plant(0)
    action = np.array([0.5, -0.5])
    plant.reset(S0)
    reward = plant.step(action)
    twin = substepped.make_plant(0)
    twin.reset(S0)
    twin.physics.set_control(action)
    rewards = []
    for _ in range(SUBSTEPS):
        twin.physics.step()
        rewards.append(substepped.definition.reward.get_reward(twin.physics))
    assert reward == rewards[-1] and reward != rewards[0]


def test_the_batched_and_one_at_a_time_derivatives_agree_over_substeps(substepped: FileTask) -> None:
    """Centred differences of whole control steps: mujoco.batch and mujoco.rollout give the same numbers."""
    expert = substepped.make_expert(0, HORIZON, ExpertOptions(max_iterations=0))
    dynamics = expert.optimizer.dynamics
    assert "3 MuJoCo steps per control step" in dynamics.derivatives_by
    actions = np.random.default_rng(0).uniform(-1.0, 1.0, (HORIZON, 2))
    states, actions = dynamics.rollout(S0, HORIZON, actions=actions)
    a, b = dynamics.jacobians(states, actions)
    a_ref, b_ref = dynamics._rollout_jacobians(states, actions)
    np.testing.assert_array_equal(a, a_ref)
    np.testing.assert_array_equal(b, b_ref)
    step = dynamics.step(states[0], actions[0])  # and A_0 is the slope of that step
    moved = dynamics.step(states[0] + 1e-6 * np.eye(4)[2], actions[0])
    np.testing.assert_allclose((moved - step) / 1e-6, a[0][:, 2], rtol=1e-3, atol=1e-5)


def test_a_control_timestep_not_a_multiple_is_refused_in_one_line(tmp_path: Path) -> None:
    with pytest.raises(TaskFileError) as refused:
        arm_task(tmp_path, **{"control_timestep = 0.01": "control_timestep = 0.025"})
    line = str(refused.value)
    assert "\n" not in line and "control_timestep" in line
    assert "0.025 s is not a whole multiple of the model's timestep 0.01 s" in line


def test_the_files_expert_stop_is_the_experts(tmp_path: Path) -> None:
    timed = arm_task(tmp_path, **{'warm_start = "zero"': 'warm_start = "zero"\nstop = "time"'})
    expert = timed.make_expert(0, HORIZON, ExpertOptions(max_iterations=0))
    assert expert.stop == "time"
    assert timed.make_expert(0, HORIZON, ExpertOptions(max_iterations=0, stop="iterations")).stop == "iterations"


def test_an_unknown_expert_stop_is_refused_naming_the_key(tmp_path: Path) -> None:
    with pytest.raises(TaskFileError, match=r"expert\.stop.*must be one of iterations, time, got 'clock'"):
        arm_task(tmp_path, **{'warm_start = "zero"': 'warm_start = "zero"\nstop = "clock"'})
