"""finite_vector: the one rule for states and actions from outside, and its wording; the policy's queries
follow the same magnitude rule (distances must not overflow)."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from npp_ros.policy.bounds import NonparametricPolicy, pairwise_distances
from npp_ros.policy.dataset import Dataset, DatasetError, Trajectory
from npp_ros.policy.vectors import MAX_MAGNITUDE, VectorError, finite_vector


def test_a_good_vector_comes_back_as_float64() -> None:
    out = finite_vector([1, 2, 3, 4], 4)
    assert out.dtype == np.float64 and out.tolist() == [1.0, 2.0, 3.0, 4.0]


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ([], "state is empty; expected 4 entries (qpos then qvel)"),
        ([0.0, 1.0, 2.0], "state has 3 entries, expected 4 (qpos then qvel)"),
        ([[0.0, 1.0], [2.0, 3.0]], "state must be a flat vector of 4 entries (qpos then qvel), got shape (2, 2)"),
        ([0.0, math.nan, math.inf, 1.0], "state must be finite: state[1] = nan, state[2] = inf"),
        (["a", 1.0, 2.0, 3.0], "state is not a numeric vector"),
    ],
)
def test_a_bad_vector_is_refused_with_the_reason(values: object, message: str) -> None:
    with pytest.raises(VectorError) as info:
        finite_vector(values, 4, "state", "qpos then qvel")  # type: ignore[arg-type]
    assert message in str(info.value)
    assert isinstance(info.value, DatasetError) and isinstance(info.value, ValueError)


# ----------------------------------------------------------------------------- magnitude: distances must not overflow
def test_a_huge_finite_state_is_refused_with_the_limit() -> None:
    with pytest.raises(VectorError) as info:
        finite_vector([1e160, 0.0, 0.0, 0.0], 4)
    assert "state is too large to compare with the data: state[0] = 1e+160" in str(info.value)
    assert "within +-1e+150" in str(info.value)
    assert finite_vector([MAX_MAGNITUDE, -MAX_MAGNITUDE, 0.0, 0.0], 4)[0] == MAX_MAGNITUDE


def _policy() -> NonparametricPolicy:
    data = Dataset(2, 1)
    data.append(Trajectory(np.array([[0.0, 0.0], [1.0, 1.0]]), np.array([[-1.0], [2.0]]), np.array([0.0, -1.0])))
    return NonparametricPolicy(data, 1.0)


def test_the_overflow_as_it_was_met_distances_to_1e160_are_inf() -> None:
    """Why the limit: without it every distance is inf, and argmax over all -inf scores is index 0."""
    with np.errstate(over="ignore"):
        dist = pairwise_distances(np.array([[0.0, 0.0], [1.0, 1.0]]), np.array([[1e160, 0.0]]))
    assert np.isinf(dist).all()


@pytest.mark.parametrize("index", [True, False])
@pytest.mark.parametrize(("query", "where"), [([1e160, 0.0], "state[0]"), ([[0.5, 0.5], [1.0, -1e155]], "state[1, 1]")])
def test_the_policy_refuses_states_whose_bounds_cannot_be_computed(query: list[float], where: str, index: bool) -> None:
    policy = _policy()
    policy = NonparametricPolicy(policy.dataset, 1.0, index=index)
    for method in (policy.act, policy.v_lb, policy.v_ub, policy.gap, policy.greedy_index, policy.lower):
        with pytest.raises(VectorError, match=rf"too large to compare with the data: {re.escape(where)}"):
            method(query)
    with pytest.raises(VectorError, match="action"):
        policy.q_lb([0.0, 0.0], [1e200])


def test_the_largest_accepted_state_has_finite_bounds_and_the_right_action() -> None:
    policy = _policy()
    state = [MAX_MAGNITUDE, MAX_MAGNITUDE]
    assert math.isfinite(policy.v_lb(state)) and math.isfinite(policy.v_ub(state))  # type: ignore[arg-type]
    assert policy.act(state).tolist() in ([-1.0], [2.0])  # at this scale both points are equally far
    assert policy.act([0.9, 1.1]).tolist() == [2.0]
