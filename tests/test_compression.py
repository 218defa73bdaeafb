"""Compression leaves V_lb, V_ub, the gap and the policy's actions exactly as they were."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.compression import compression_report, index_report, kept_masks
from npp_ros.policy.dataset import Dataset
from npp_ros.tasks.builtin.lqr import PAPER_LIPSCHITZ, LQRExpert, sample_initial_state


def assert_policies_identical(compressed: NonparametricPolicy, full: NonparametricPolicy, states: np.ndarray) -> None:
    for name in ("v_lb", "v_ub", "gap", "greedy_index", "act"):
        np.testing.assert_array_equal(getattr(compressed, name)(states), getattr(full, name)(states), err_msg=name)
    for k in range(0, len(states), max(1, len(states) // 7)):  # single queries too
        assert compressed.v_lb(states[k]) == full.v_lb(states[k])
        assert compressed.v_ub(states[k]) == full.v_ub(states[k])
        assert compressed.greedy_index(states[k]) == full.greedy_index(states[k])


@pytest.mark.parametrize("task", ["lqr_2_1", "lqr_6_2"])
def test_lqr_data_with_the_papers_lipschitz_compresses_and_keeps_every_bound_and_action(task: str) -> None:
    expert = LQRExpert(task, 0)
    rng = np.random.default_rng(5)
    data = Dataset(expert.plant.state_dim, expert.plant.actuators)
    L = PAPER_LIPSCHITZ[task]  # not a bound on V* here: many points are dominated
    compressed = NonparametricPolicy(data, L)
    full = NonparametricPolicy(data, L, index=False)
    assert compressed.index is not None
    compressed.index.tail_limit = 700  # index (and compress) while the data grows
    for _ in range(4):
        data.append(expert.trajectory(sample_initial_state(task, rng)))
        near = expert.trajectory(sample_initial_state(task, rng)).states[::25]
        states = np.concatenate([
            near, near + 1e-3 * rng.normal(size=near.shape), data.states[::53],
            rng.normal(scale=2.0, size=(40, data.state_dim)), 100.0 * rng.normal(size=(5, data.state_dim)),
        ])  # fmt: skip
        assert_policies_identical(compressed, full, states)
    live = index_report(compressed.index)
    assert live.kept_upper < live.points  # the comparison above really ran on compressed trees
    whole = compression_report(data, L)
    assert whole.kept_lower <= live.kept_lower and whole.kept_upper <= live.kept_upper
    assert whole.kept_either <= whole.points


def test_equal_domination_keeps_the_point_that_wins_the_tie() -> None:
    # s = 0 (Q = 0, index 0) and s = 1 (Q = 1, index 1), L = 1: Q_1 - L|s_0 - s_1| = Q_0 exactly.
    # At s = 0 both score 0 and index 0 wins the tie, so it must stay.
    data = Dataset(1, 1)
    data.append_arrays([[0.0], [1.0]], [[10.0], [20.0]], [0.0, 1.0])
    lower, _ = kept_masks(data, 1.0)
    assert lower.tolist() == [True, True]
    policy = NonparametricPolicy(data, 1.0)
    assert policy.index is not None
    policy.index.tail_limit = 1
    assert policy.greedy_index([0.0]) == 0 and policy.act([0.0])[0] == 10.0


def test_strict_domination_removes_the_point_from_the_search_only() -> None:
    data = Dataset(1, 1)
    data.append_arrays([[0.0], [1.0], [5.0]], [[1.0], [2.0], [3.0]], [0.0, 2.0, -9.0])
    lower, upper = kept_masks(data, 1.0)
    assert lower.tolist() == [False, True, False]  # 1 beats 0 (2 - 1 > 0) and 2 (2 - 4 > -9)
    assert upper.tolist() == [False, False, True]  # V_ub: -9 + 5 < 0 and -9 + 4 < 2: only 2 is needed
    assert len(data) == 3  # the dataset keeps everything
    report = compression_report(data, 1.0)
    assert (report.kept_lower, report.kept_upper, report.kept_either) == (1, 1, 2)


def test_near_equal_domination_within_rounding_is_not_trusted() -> None:
    # Q_1 - L d exceeds Q_0 by far less than the rounding margin: kept, though mathematically dominated.
    data = Dataset(1, 1)
    data.append_arrays([[0.0], [1.0]], [[0.0], [0.0]], [0.0, 1.0 + 1e-15])
    lower, _ = kept_masks(data, 1.0)
    assert lower.tolist() == [True, True]


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    dim=st.integers(1, 5),
    trajectories=st.integers(1, 6),
    lipschitz=st.sampled_from([0.05, 0.5, 1.0, 4.0]),
    grid=st.booleans(),
)
def test_randomised_trajectories_compress_without_changing_any_answer(
    seed: int, dim: int, trajectories: int, lipschitz: float, grid: bool
) -> None:
    rng = np.random.default_rng(seed)
    data = Dataset(dim, 2)
    compressed = NonparametricPolicy(data, lipschitz)
    full = NonparametricPolicy(data, lipschitz, index=False)
    assert compressed.index is not None
    compressed.index.tail_limit = 40
    for _ in range(trajectories):
        steps = int(rng.integers(20, 120))
        # a random walk with a value that rises along it, like a trajectory converging to a goal
        walk = np.cumsum(rng.normal(scale=0.3, size=(steps, dim)), axis=0) + rng.normal(size=dim)
        values = np.cumsum(np.abs(rng.normal(size=steps)))
        if grid:
            walk, values = np.round(walk), np.round(values)
        data.append_arrays(walk, rng.normal(size=(steps, 2)), values)
        states = np.concatenate([walk + rng.normal(scale=0.1, size=walk.shape), rng.normal(scale=3, size=(20, dim))])
        assert_policies_identical(compressed, full, states)
