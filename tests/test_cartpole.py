"""The cartpole swing-up plant (RK4) and its iLQR expert on the real dm_control task."""

from __future__ import annotations

import math

import numpy as np
import pytest

from npp_ros.tasks.builtin.cartpole import CartpoleExpert, CartpolePlant, represent, sample_initial_state


@pytest.fixture(scope="module")
def solutions() -> list:
    expert = CartpoleExpert(seed=0, time_budget=60.0, values="return-to-go")  # generous budget: results are tested
    rng = np.random.default_rng(7)
    return [(s0, expert.solve(s0)) for s0 in (sample_initial_state(rng) for _ in range(2))]


def test_plant_matches_dm_control_task() -> None:
    plant = CartpolePlant()
    from dm_control import suite

    env = suite.load("cartpole", "swingup")
    assert plant.dt == env.control_timestep() == pytest.approx(0.01)
    assert (plant.state_dim, plant.action_dim) == (4, 1)
    assert plant.joint_names == ["slider", "hinge_1"] and plant.actuated_joint_names == ["slider"]
    x0 = np.array([0.3, 2.0, -0.1, 0.5])
    plant.reset(x0)
    with env.physics.reset_context():
        env.physics.data.qpos[:] = x0[:2]
        env.physics.data.qvel[:] = x0[2:]
    for u in (0.5, -1.0, 0.2):
        reward = plant.step([u])
        env.physics.set_control([u])
        env.physics.step()
        assert reward == env.task.get_reward(env.physics)
        np.testing.assert_array_equal(plant.raw_state(), np.r_[env.physics.data.qpos, env.physics.data.qvel])


def test_initial_states_follow_dm_control_swingup() -> None:
    starts = np.array([sample_initial_state(np.random.default_rng(k)) for k in range(200)])
    assert np.all(np.abs(starts[:, 1] - math.pi) < 0.05) and np.all(np.abs(starts[:, [0, 2, 3]]) < 0.05)
    stored = represent(starts)
    assert np.all((stored[:, 1] > -math.pi) & (stored[:, 1] <= math.pi))


def test_expert_swings_up_holds_and_stays_on_the_rail(solutions: list) -> None:
    for s0, solution in solutions:
        raw = solution.raw_states
        assert np.all(np.cos(raw[-300:, 1]) >= math.cos(math.radians(8.0))), f"s0 = {s0}"
        assert np.all(np.abs(raw[:, 0]) < 1.8)
        assert np.all(np.abs(solution.trajectory.actions) <= 1.0)
        assert solution.expert_return > 800  # of at most 1000


def test_values_are_the_replayed_true_return_to_go(solutions: list) -> None:
    plant = CartpolePlant()
    for s0, solution in solutions:
        traj = solution.trajectory
        plant.reset(s0)
        rewards = np.array([plant.step(u) for u in traj.actions])
        np.testing.assert_array_equal(traj.values, np.cumsum(rewards[::-1])[::-1])
        np.testing.assert_array_equal(solution.raw_states, solution.optimization.states)  # the RK4 step is the plant's
        np.testing.assert_array_equal(traj.states, represent(solution.raw_states))
