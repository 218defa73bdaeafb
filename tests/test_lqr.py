"""The real dm_control plants and the closed-form expert."""

from __future__ import annotations

import numpy as np
import pytest

from npp_ros.policy.dataset import DatasetError
from npp_ros.tasks.builtin.lqr import (
    LQRExpert,
    LQRPlant,
    UnknownTaskError,
    episode_rng,
    rollout,
    rollout_batch,
    sample_initial_state,
)


def test_plant_shapes_names_and_seeded_stiffness() -> None:
    plant = LQRPlant("lqr_6_2", seed=3)
    assert (plant.state_dim, plant.action_dim) == (12, 2)
    assert plant.joint_names == [f"joint_{k}" for k in range(6)]
    assert plant.actuated_joint_names == ["joint_0", "joint_1"]
    assert plant.dt == pytest.approx(0.03)
    assert plant.model_sha256() == LQRPlant("lqr_6_2", seed=3).model_sha256()
    assert plant.model_sha256() != LQRPlant("lqr_6_2", seed=4).model_sha256()


def test_reset_step_and_reward_follow_the_task() -> None:
    plant = LQRPlant("lqr_2_1", seed=0)
    x0 = np.array([1.0, -0.5, 0.2, 0.0])
    np.testing.assert_array_equal(plant.reset(x0), x0)
    np.testing.assert_array_equal(plant.state(), x0)
    reward = plant.step([0.3])
    q = plant.state()[:2]
    assert reward == pytest.approx(1 - 0.5 * q @ q - 0.05 * 0.09)
    a, b = plant.linearization()
    np.testing.assert_allclose(plant.state(), a @ x0 + b @ [0.3], atol=1e-12)


def test_initial_states_lie_on_the_position_sphere_and_are_reproducible() -> None:
    for episode in range(20):
        s0 = sample_initial_state("lqr_6_2", episode_rng(1, episode))
        assert np.linalg.norm(s0[:6]) == pytest.approx(np.sqrt(2))
        np.testing.assert_array_equal(s0[6:], 0.0)
        np.testing.assert_array_equal(s0, sample_initial_state("lqr_6_2", episode_rng(1, episode)))


def test_unknown_task_is_refused_by_name() -> None:
    with pytest.raises(UnknownTaskError, match=r"lqr_9_9.*known tasks: lqr_2_1, lqr_6_2"):
        LQRPlant("lqr_9_9", seed=0)


@pytest.mark.parametrize(
    ("state", "message"),
    [
        (np.zeros(3), r"has 3 entries, expected 4 \(qpos then qvel of 2 joints of lqr_2_1\)"),
        (np.zeros((2, 2)), r"got shape \(2, 2\)"),
        (np.array([0.0, np.nan, 0.0, 0.0]), r"requested state\[1\] = nan"),
        (np.array([np.inf, 0.0, 0.0, 0.0]), r"requested state\[0\] = inf"),
    ],
)
def test_expert_rejects_bad_states(expert_2_1: LQRExpert, state, message) -> None:
    with pytest.raises(DatasetError, match=message):
        expert_2_1.trajectory(state)


def test_expert_rejects_bad_horizon(expert_2_1: LQRExpert) -> None:
    with pytest.raises(ValueError, match="horizon"):
        expert_2_1.trajectory(np.ones(4), horizon=10**9)


def test_expert_trajectory_follows_the_plant_with_q_equal_v_star(expert_2_1: LQRExpert) -> None:
    s0 = sample_initial_state("lqr_2_1", episode_rng(0, 0))
    traj = expert_2_1.trajectory(s0, horizon=50)
    assert len(traj) == 50
    np.testing.assert_array_equal(traj.states[0], s0)
    np.testing.assert_allclose(
        traj.states[1:], traj.states[:-1] @ expert_2_1.A.T + traj.actions[:-1] @ expert_2_1.B.T, atol=1e-10
    )
    np.testing.assert_allclose(traj.values, expert_2_1.value(traj.states))
    np.testing.assert_allclose(traj.actions, -traj.states @ expert_2_1.K.T)


def test_expert_values_match_measured_returns_within_half_a_percent(expert_2_1: LQRExpert) -> None:
    plant = LQRPlant("lqr_2_1", seed=0)
    for episode in range(10):
        s0 = sample_initial_state("lqr_2_1", episode_rng(5, episode))
        measured = rollout(plant, expert_2_1.action, s0, 1000).total_return
        assert measured == pytest.approx(expert_2_1.value(s0), rel=0.005)


def test_lqr_6_2_values_match_once_the_slow_mode_has_decayed(expert_6_2: LQRExpert) -> None:
    # The optimal closed loop of lqr_6_2 has a mode with |lambda| ~ 0.999: after 1000 steps part of
    # the cost is still to come, so a 1000-step return exceeds V*(s0) (V* stays a lower bound).
    # Over a long rollout the accumulated cost matches J*(s0) = H - V*(s0).
    plant = LQRPlant("lqr_6_2", seed=0)
    for episode in range(3):
        s0 = sample_initial_state("lqr_6_2", episode_rng(5, episode))
        cost = (1.0 - rollout(plant, expert_6_2.action, s0, 12000).rewards).sum()
        assert cost == pytest.approx(expert_6_2.offset - expert_6_2.value(s0), rel=0.005)
        assert rollout(plant, expert_6_2.action, s0, 1000).total_return >= expert_6_2.value(s0)


def test_expert_is_optimal_against_perturbed_gains(expert_2_1: LQRExpert) -> None:
    plant = LQRPlant("lqr_2_1", seed=0)
    s0 = sample_initial_state("lqr_2_1", episode_rng(2, 0))
    best = rollout(plant, expert_2_1.action, s0, 1000).total_return
    rng = np.random.default_rng(0)
    for _ in range(5):
        gain = expert_2_1.K * (1 + 0.2 * rng.normal(size=expert_2_1.K.shape))
        assert rollout(plant, lambda x, g=gain: -g @ x, s0, 1000).total_return < best


def test_discounted_values_are_available(expert_2_1: LQRExpert) -> None:
    disc = LQRExpert("lqr_2_1", seed=0, gamma=0.99)
    s0 = sample_initial_state("lqr_2_1", episode_rng(0, 1))
    plant = LQRPlant("lqr_2_1", seed=0)
    rewards = rollout(plant, disc.action, s0, 3000).rewards
    assert (0.99 ** np.arange(3000)) @ rewards == pytest.approx(disc.value(s0), rel=0.005)
    with pytest.raises(ValueError, match="gamma"):
        LQRExpert("lqr_2_1", seed=0, gamma=1.5)


def test_analytic_lipschitz_bounds_the_slope_along_expert_trajectories(expert_2_1: LQRExpert) -> None:
    bound = expert_2_1.analytic_lipschitz()
    assert bound.source == "lqr-analytic"
    for episode in range(30):
        traj = expert_2_1.trajectory(sample_initial_state("lqr_2_1", episode_rng(8, episode)))
        assert np.max(expert_2_1.slope(traj.states)) <= bound.value
        # and it bounds actual value differences between any two states of the trajectory
        i, j = np.random.default_rng(episode).integers(0, 1000, size=(2, 50))
        diff = np.abs(traj.values[i] - traj.values[j])
        assert np.all(diff <= bound.value * np.linalg.norm(traj.states[i] - traj.states[j], axis=1) + 1e-9)
    assert bound.value > 50.0  # the paper's L is below the true slope on lqr_2_1


def test_batched_rollouts_equal_one_at_a_time(expert_2_1: LQRExpert) -> None:
    """rollout_batch steps plant clones in lockstep; the numbers must not change."""
    plant = LQRPlant("lqr_2_1", 0)
    starts = np.array([sample_initial_state("lqr_2_1", episode_rng(5, k)) for k in range(4)])
    batch = rollout_batch(plant, lambda xs: np.array([expert_2_1.action(x) for x in xs]), starts, 300)
    for s0, run in zip(starts, batch, strict=True):
        alone = rollout(plant, expert_2_1.action, s0, 300)
        assert np.array_equal(run.rewards, alone.rewards) and np.array_equal(run.states, alone.states)
