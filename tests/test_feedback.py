"""The feedback policy: the same chosen point as the paper's policy, the expert's gain applied at it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import Dataset, DatasetError, Trajectory
from npp_ros.policy.feedback import ControlSpace, wrap_angle
from npp_ros.tasks.builtin.lqr import LQRExpert
from npp_ros.tasks.registry import control_space, get_task

SPACE = ControlSpace.of(2, (0,), [-1.0], [1.0])  # a pendulum's: angle wrapped, torque in [-1, 1]


def one_point(state: list[float], action: float, gain: list[float] | None) -> Dataset:
    data = Dataset(2, 1)
    gains = None if gain is None else np.array([[gain]])
    data.append(Trajectory(np.array([state]), np.array([[action]]), np.array([10.0]), gains=gains))
    return data


def test_the_action_is_the_stored_one_plus_the_gain_times_the_wrapped_difference() -> None:
    data = one_point([3.0, 0.0], 0.1, [0.5, 0.2])
    policy = NonparametricPolicy(data, 1.0, control=SPACE)
    # -3.0 is 0.283 rad past the seam from 3.0, not 6 rad away.
    s = np.array([-3.0, 0.4])
    expected = 0.1 + 0.5 * (2 * math.pi - 6.0) + 0.2 * 0.4
    assert policy.act(s)[0] == pytest.approx(expected, rel=1e-12)
    assert policy.kind == "feedback"
    assert NonparametricPolicy(data, 1.0).act(s)[0] == 0.1  # the paper's policy replays the action


def test_the_action_is_clamped_to_the_actuator_range() -> None:
    policy = NonparametricPolicy(one_point([0.0, 0.0], 0.5, [10.0, 0.0]), 1.0, control=SPACE)
    assert policy.act([1.0, 0.0])[0] == 1.0 and policy.act([-1.0, 0.0])[0] == -1.0


def test_a_point_without_gains_acts_open_loop_and_batches_equal_single_queries() -> None:
    data = one_point([0.0, 0.0], 0.3, None)
    data.append(Trajectory(np.array([[1.0, 1.0]]), np.array([[-0.2]]), np.array([10.0]), gains=np.ones((1, 1, 2))))
    policy = NonparametricPolicy(data, 1.0, control=SPACE)
    states = np.random.default_rng(0).uniform(-3, 3, size=(50, 2))
    batch = policy.act(states)
    index = policy.greedy_index(states)
    for k, s in enumerate(states):
        np.testing.assert_array_equal(policy.act(s), batch[k])
        if index[k] == 0:
            assert batch[k][0] == 0.3
    np.testing.assert_array_equal(index, NonparametricPolicy(data, 1.0).greedy_index(states))


def test_wrong_gains_are_refused_with_their_shape() -> None:
    data = Dataset(2, 1)
    with pytest.raises(DatasetError, match="gains must hold one 1 x 2 matrix"):
        data.append(Trajectory(np.zeros((3, 2)), np.zeros((3, 1)), np.zeros(3), gains=np.zeros((3, 2, 1))))
    with pytest.raises(DatasetError, match="gains\\[1, 0, 1\\] is nan"):
        bad = np.zeros((3, 1, 2))
        bad[1, 0, 1] = np.nan
        data.append(Trajectory(np.zeros((3, 2)), np.zeros((3, 1)), np.zeros(3), gains=bad))


def test_on_lqr_the_feedback_policy_is_the_experts_own_law_everywhere() -> None:
    expert = LQRExpert("lqr_2_1", 0, horizon=20)
    data = Dataset(4, 1)
    data.append(expert.trajectory(np.array([1.0, 0.5, 0.0, 0.0])))
    policy = NonparametricPolicy(data, 263.0, control=control_space(expert.plant))
    for s in np.random.default_rng(1).normal(size=(20, 4)):
        np.testing.assert_allclose(policy.act(s), expert.action(s), rtol=1e-9, atol=1e-12)


def test_every_built_in_task_says_which_entries_are_angles() -> None:
    angles = {name: control_space(get_task(name).make_plant(0)).angles for name in
              ("lqr_2_1", "pendulum_swingup", "cartpole_swingup", "acrobot_swingup")}  # fmt: skip
    assert angles == {"lqr_2_1": (), "pendulum_swingup": (0,), "cartpole_swingup": (1,), "acrobot_swingup": (0, 1)}
    assert wrap_angle(np.pi) == np.pi and wrap_angle(-np.pi) == np.pi
