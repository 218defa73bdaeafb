"""The path policy: it follows the stored trajectory it chose, chooses again when the state leaves it, and starts
afresh with every rollout."""

from __future__ import annotations

import numpy as np
import pytest

from npp_ros.policy.bounds import NonparametricPolicy, PathEpisodeError
from npp_ros.policy.dataset import Dataset, Trajectory
from npp_ros.policy.feedback import ControlSpace

SPACE = ControlSpace.of(2, (), [-10.0], [10.0])
STEPS = 6


def crossing_paths() -> Dataset:
    """Path A along x (steps of 0.1); path B, valued a little higher, runs just beside A's later points, so the
    greedy choice hops from A to B half way while A's next point stays within one of A's steps of the best."""
    data = Dataset(2, 1)
    t = np.arange(STEPS, dtype=np.float64)
    a_states = np.stack([0.1 * t, np.zeros(STEPS)], axis=1)
    gains = np.tile(np.array([[[1.0, 2.0]]]), (STEPS, 1, 1))
    data.append(Trajectory(a_states, (0.5 + t)[:, None], 10.0 - 0.01 * t, gains=gains))
    b_states = a_states[3:] + np.array([0.0, 0.02])
    data.append(Trajectory(b_states, np.full((3, 1), -5.0), np.full(3, 10.5), gains=-gains[:3]))
    return data


def test_started_on_a_path_it_acts_with_that_paths_actions_where_the_greedy_choice_hops() -> None:
    data = crossing_paths()
    path = NonparametricPolicy(data, 10.0, control=SPACE, kind="path")
    greedy = NonparametricPolicy(data, 10.0, control=SPACE, kind="feedback")
    stored = data.trajectory(0)
    act = path.controller()
    actions = np.array([act(s) for s in stored.states])
    np.testing.assert_array_equal(actions, stored.actions)
    assert greedy.greedy_index(stored.states[3]) == STEPS  # B's first point: the per-step choice leaves A
    assert greedy.act(stored.states[3])[0] == pytest.approx(-5.0 + 2.0 * 0.02)  # B's action and gain


def test_pushed_off_its_path_it_chooses_again_on_v_lb() -> None:
    data = crossing_paths()
    path = NonparametricPolicy(data, 10.0, control=SPACE, kind="path")
    episode = path.episode()
    episode.act(data.states[0])
    pushed = np.array([0.4, 1.0])  # far from A's next point (0.1, 0): another point's bound is better by far more
    action, index = episode.act_at(pushed)
    assert index == path.greedy_index(pushed) != 1
    expected = data.actions[index] + data.gains[index] @ (pushed - data.states[index])
    np.testing.assert_allclose(action, expected, rtol=1e-12)


def test_past_its_paths_end_it_chooses_again() -> None:
    data = crossing_paths()
    path = NonparametricPolicy(data, 10.0, control=SPACE, kind="path")
    episode = path.episode()
    for s in data.states[: STEPS - 1]:
        episode.act(s)
    last = data.states[STEPS - 1]
    assert episode.act_at(last)[1] == STEPS - 1
    assert episode.act_at(last)[1] == path.greedy_index(last) != STEPS - 1  # A has no point after its last


def test_each_rollout_starts_afresh_and_a_batch_follows_each_row_as_alone() -> None:
    data = crossing_paths()
    path = NonparametricPolicy(data, 10.0, control=SPACE, kind="path")
    stored = data.states[:STEPS]
    first = path.episode()
    for s in stored[:3]:
        first.act(s)
    second = path.episode()  # a new rollout: its first step is the greedy choice, whatever the first one follows
    assert second.act_at(stored[3])[1] == STEPS
    assert first.act_at(stored[3])[1] == 3  # the first one still follows A: no episode sees another's path
    with pytest.raises(ValueError, match="take a new controller"):
        first.act(stored[:2])  # a batch of 2 while it follows 1 episode
    with pytest.raises(PathEpisodeError, match=r"take policy.controller\(\)"):
        path.act(stored[0])  # outside an episode: the policy object holds no path to continue
    rng = np.random.default_rng(0)
    starts = stored[:4] + rng.normal(0, 0.03, size=(4, 2))
    batch = path.controller()
    rows = [batch(starts)] + [batch(starts + 0.1 * k) for k in (1, 2)]
    for k in range(len(starts)):
        single = path.controller()
        alone = [single(starts[k] + 0.1 * j) for j in range(3)]
        np.testing.assert_array_equal(np.array(alone), np.array([r[k] for r in rows]))


def test_the_path_policy_needs_the_control_space_and_greedy_kinds_have_no_memory() -> None:
    data = crossing_paths()
    with pytest.raises(ValueError, match="path policy needs the task's control space"):
        NonparametricPolicy(data, 10.0, kind="path")
    greedy = NonparametricPolicy(data, 10.0, control=SPACE)
    assert greedy.kind == "feedback"
    first = greedy.act(data.states[3])
    greedy.act(data.states[:3])  # another batch size: no episode to follow
    np.testing.assert_array_equal(greedy.controller()(data.states[3]), first)
