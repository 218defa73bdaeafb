"""The paper's results, measured on the real lqr_2_1 plant with a valid L."""

from __future__ import annotations

import numpy as np
import pytest

from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import Dataset
from npp_ros.tasks.builtin.lqr import LQRExpert, LQRPlant, episode_rng, sample_initial_state
from npp_ros.tasks.rollout import rollout


def test_theorem_3_4_greedy_return_is_at_least_v_lb(expert_2_1: LQRExpert, expert_dataset_2_1: Dataset) -> None:
    L = expert_2_1.analytic_lipschitz().value
    policy = NonparametricPolicy(expert_dataset_2_1, L)
    plant = LQRPlant("lqr_2_1", seed=0)
    margins = []
    for episode in range(40):
        s0 = sample_initial_state("lqr_2_1", episode_rng(1234, episode))
        measured = rollout(plant, policy.act, s0, 1000).total_return
        margins.append(measured - policy.v_lb(s0))
    assert min(margins) >= 0.0, f"returns below V_lb: {sorted(margins)[:3]}"


def test_paper_lipschitz_breaks_theorem_3_4_on_lqr_2_1(expert_2_1: LQRExpert, expert_dataset_2_1: Dataset) -> None:
    # Shown, not hidden: with L = 50 (the paper's), V_lb exceeds the policy's true return.
    policy = NonparametricPolicy(expert_dataset_2_1, 50.0)
    plant = LQRPlant("lqr_2_1", seed=0)
    violations = 0
    for episode in range(20):
        s0 = sample_initial_state("lqr_2_1", episode_rng(1234, episode))
        violations += rollout(plant, policy.act, s0, 1000).total_return < policy.v_lb(s0)
    assert violations > 0


def test_theorem_3_5_v_lb_never_decreases_as_trajectories_are_added(expert_2_1: LQRExpert) -> None:
    L = expert_2_1.analytic_lipschitz().value
    data = Dataset(4, 1)
    policy = NonparametricPolicy(data, L)
    rng = np.random.default_rng(0)
    probes = np.vstack([sample_initial_state("lqr_2_1", rng) for _ in range(200)] + [rng.normal(size=(200, 4))])
    previous = policy.v_lb(probes)
    for episode in range(15):
        data.append(expert_2_1.trajectory(sample_initial_state("lqr_2_1", episode_rng(77, episode))))
        current = policy.v_lb(probes)
        assert np.all(current >= previous)
        previous = current


def test_theorem_3_5_new_states_are_served_optimally(expert_2_1: LQRExpert) -> None:
    # On states of the newly added trajectory the new policy is the expert: V^pi'(s') = V*(s').
    L = expert_2_1.analytic_lipschitz().value
    data = Dataset(4, 1)
    data.append(expert_2_1.trajectory(sample_initial_state("lqr_2_1", episode_rng(3, 0))))
    s_new = sample_initial_state("lqr_2_1", episode_rng(3, 1))
    data.append(expert_2_1.trajectory(s_new))
    policy = NonparametricPolicy(data, L)
    plant = LQRPlant("lqr_2_1", seed=0)
    measured = rollout(plant, policy.act, s_new, 1000).total_return
    expert_return = rollout(plant, expert_2_1.action, s_new, 1000).total_return
    assert measured == pytest.approx(expert_return, abs=1e-6)


def test_proposition_3_7_true_gap_is_below_surrogate_gap(expert_2_1: LQRExpert, expert_dataset_2_1: Dataset) -> None:
    L = expert_2_1.analytic_lipschitz().value
    policy = NonparametricPolicy(expert_dataset_2_1, L)
    plant = LQRPlant("lqr_2_1", seed=0)
    rng = np.random.default_rng(21)
    for _ in range(30):
        s0 = sample_initial_state("lqr_2_1", rng)
        true_gap = expert_2_1.value(s0) - rollout(plant, policy.act, s0, 1000).total_return
        assert true_gap <= policy.gap(s0)


def test_remark_3_2_actions_along_rollouts_come_from_the_dataset(
    expert_2_1: LQRExpert, expert_dataset_2_1: Dataset
) -> None:
    policy = NonparametricPolicy(expert_dataset_2_1, expert_2_1.analytic_lipschitz().value)
    plant = LQRPlant("lqr_2_1", seed=0)
    run = rollout(plant, policy.act, sample_initial_state("lqr_2_1", episode_rng(4, 4)), 300)
    stored = {a.tobytes() for a in expert_dataset_2_1.actions}
    assert all(a.tobytes() in stored for a in run.actions)
