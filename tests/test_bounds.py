"""Bounds, gap and greedy policy: hand-checked cases, ties, batch = single, brute force."""

from __future__ import annotations

import numpy as np
import pytest

from npp_ros.policy.bounds import EmptyDatasetError, NonparametricPolicy
from npp_ros.policy.dataset import Dataset, DatasetError


def random_dataset(rng: np.random.Generator, size: int, state_dim: int = 3, action_dim: int = 2) -> Dataset:
    """Synthetic data on a coarse grid, so exact ties are frequent."""
    data = Dataset(state_dim, action_dim)
    states = rng.integers(-3, 4, size=(size, state_dim)).astype(float)
    actions = rng.integers(-2, 3, size=(size, action_dim)).astype(float)
    values = rng.integers(0, 5, size=size).astype(float)
    data.append_arrays(states, actions, values)
    return data


def brute_force(data: Dataset, L: float, s: np.ndarray) -> tuple[float, int, float, int]:
    """Reference: a plain Python loop over the dataset, smallest index on ties."""
    best_lo, arg_lo, best_hi, arg_hi = -np.inf, -1, np.inf, -1
    for i in range(len(data)):
        d = float(np.sqrt(sum((float(s[k]) - float(data.states[i, k])) ** 2 for k in range(data.state_dim))))
        lo, hi = data.values[i] - L * d, data.values[i] + L * d
        if lo > best_lo:
            best_lo, arg_lo = lo, i
        if hi < best_hi:
            best_hi, arg_hi = hi, i
    return best_lo, arg_lo, best_hi, arg_hi


def test_hand_checked_one_dimensional_case() -> None:
    # Points at s = 0 (Q = 10) and s = 4 (Q = 6), L = 2.
    data = Dataset(1, 1)
    data.append_arrays([[0.0], [4.0]], [[1.0], [-1.0]], [10.0, 6.0])
    pi = NonparametricPolicy(data, 2.0)
    # s = 1: lower = max(10 - 2, 6 - 6) = 8 (i = 0); upper = min(10 + 2, 6 + 6) = 12 (tie -> j = 0).
    assert pi.v_lb([1.0]) == 8.0
    assert pi.v_ub([1.0]) == 12.0
    assert pi.gap([1.0]) == 4.0
    assert pi.greedy_index([1.0]) == 0
    # s = 4: lower = max(10 - 8, 6) = 6 (i = 1): the policy takes the action stored at s = 4.
    assert pi.v_lb([4.0]) == 6.0
    np.testing.assert_array_equal(pi.act([4.0]), [-1.0])
    # Q bounds add the action distance: Q_lb(1, a = 0) = max(10 - 2(1 + 1), 6 - 2(3 + 1)) = 6.
    assert pi.q_lb([1.0], [0.0]) == 6.0
    assert pi.q_ub([1.0], [0.0]) == 14.0


def test_exact_tie_goes_to_the_smallest_index() -> None:
    # s = 2 is equidistant from both points with equal Q: both attain V_lb exactly.
    data = Dataset(1, 1)
    data.append_arrays([[0.0], [4.0], [4.0]], [[1.0], [2.0], [3.0]], [5.0, 5.0, 5.0])
    pi = NonparametricPolicy(data, 1.0)
    assert pi.greedy_index([2.0]) == 0
    assert pi.greedy_index([4.0]) == 1  # duplicates: the first copy wins
    np.testing.assert_array_equal(pi.act(np.array([[2.0], [4.0], [3.0]])), [[1.0], [2.0], [2.0]])


@pytest.mark.parametrize("seed", range(5))
def test_matches_brute_force_bit_for_bit_including_ties(seed: int) -> None:
    rng = np.random.default_rng(seed)
    data = random_dataset(rng, 300)
    pi = NonparametricPolicy(data, 1.0)  # integer grid + L = 1: many exact ties
    queries = rng.integers(-3, 4, size=(200, 3)).astype(float)
    lower, upper = pi.lower(queries), pi.upper(queries)
    ties = 0
    for k, s in enumerate(queries):
        lo, arg_lo, hi, arg_hi = brute_force(data, 1.0, s)
        assert lower.value[k] == lo and lower.index[k] == arg_lo
        assert upper.value[k] == hi and upper.index[k] == arg_hi
        scores = data.values - np.sqrt(((s - data.states) ** 2).sum(axis=1))
        ties += int(np.sum(scores == scores.max()) > 1)
    assert ties > 20  # the case really exercises the tie rule


def test_single_and_batch_queries_agree_bit_for_bit() -> None:
    rng = np.random.default_rng(7)
    data = Dataset(4, 1)
    data.append_arrays(rng.normal(size=(5000, 4)), rng.normal(size=(5000, 1)), rng.normal(size=5000))
    pi = NonparametricPolicy(data, 3.7)
    queries = rng.normal(size=(64, 4))
    batch = (pi.v_lb(queries), pi.v_ub(queries), pi.gap(queries), pi.greedy_index(queries))
    for k, s in enumerate(queries):
        assert pi.v_lb(s) == batch[0][k]
        assert pi.v_ub(s) == batch[1][k]
        assert pi.gap(s) == batch[2][k]
        assert pi.greedy_index(s) == batch[3][k]


def test_q_bounds_match_their_definition() -> None:
    rng = np.random.default_rng(3)
    data = random_dataset(rng, 50)
    pi = NonparametricPolicy(data, 0.5)
    for _ in range(20):
        s, a = rng.normal(size=3), rng.normal(size=2)
        ds = np.sqrt(((s - data.states) ** 2).sum(axis=1))
        da = np.sqrt(((a - data.actions) ** 2).sum(axis=1))
        assert pi.q_lb(s, a) == pytest.approx(np.max(data.values - 0.5 * (ds + da)), abs=1e-12)
        assert pi.q_ub(s, a) == pytest.approx(np.min(data.values + 0.5 * (ds + da)), abs=1e-12)
        # Remark 3.2: Q_lb(s, a) <= Q_lb(s, a_i*) = V_lb(s)
        assert pi.q_lb(s, a) <= pi.q_lb(s, pi.act(s)) == pytest.approx(pi.v_lb(s), abs=1e-12)


def test_policy_only_emits_dataset_actions() -> None:
    rng = np.random.default_rng(11)
    data = random_dataset(rng, 200)
    pi = NonparametricPolicy(data, 2.0)
    stored = {tuple(a) for a in data.actions}
    actions = pi.act(rng.normal(scale=4, size=(500, 3)))
    assert all(tuple(a) in stored for a in actions)


def test_empty_dataset_gives_infinite_gap_and_no_action() -> None:
    pi = NonparametricPolicy(Dataset(2, 1), 1.0)
    assert pi.v_lb([0.0, 0.0]) == -np.inf
    assert pi.v_ub([0.0, 0.0]) == np.inf
    assert pi.gap([0.0, 0.0]) == np.inf
    with pytest.raises(EmptyDatasetError, match="empty"):
        pi.act([0.0, 0.0])


@pytest.mark.parametrize(
    ("state", "message"),
    [
        ([0.0], r"shape \(2,\) or \(batch, 2\)"),
        ([0.0, np.nan], r"state\[1\] is nan"),
        ([[0.0, 1.0], [np.inf, 0]], r"state\[1, 0\]"),
    ],
)
def test_bad_query_states_are_refused(state, message) -> None:
    data = Dataset(2, 1)
    data.append_arrays([[0.0, 0.0]], [[0.0]], [1.0])
    with pytest.raises(DatasetError, match=message):
        NonparametricPolicy(data, 1.0).v_lb(state)


@pytest.mark.parametrize("bad", [0.0, -1.0, np.nan, np.inf])
def test_lipschitz_must_be_positive_and_finite(bad: float) -> None:
    with pytest.raises(ValueError, match="Lipschitz"):
        NonparametricPolicy(Dataset(1, 1), bad)


def test_gap_vanishes_on_data_and_bounds_are_ordered_for_consistent_data() -> None:
    rng = np.random.default_rng(5)
    data = Dataset(2, 1)
    # Values of a 1-Lipschitz function, so the dataset is consistent with L = 1.
    states = rng.normal(size=(100, 2))
    data.append_arrays(states, np.zeros((100, 1)), np.abs(states).sum(axis=1) / 2)
    pi = NonparametricPolicy(data, 1.0)
    np.testing.assert_allclose(pi.gap(states), 0.0, atol=1e-12)
    queries = rng.normal(size=(300, 2))
    assert np.all(pi.v_lb(queries) <= pi.v_ub(queries))
