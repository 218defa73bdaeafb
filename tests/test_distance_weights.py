"""Distance weights: a task weighs its state entries in the policy's distance. They change which data point the
policy chooses, exactly as brute force over the weighted states does, and nothing of the feedback law at it."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import Dataset, Trajectory
from npp_ros.policy.feedback import ControlSpace
from npp_ros.run.setup import task_control_space
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.task_file.loader import TaskFileError

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
WEIGHTS = (1.0, 10.0, 0.5, 2.0)


def random_data(rng: np.random.Generator, trajectories: int = 6, steps: int = 30) -> Dataset:
    data = Dataset(4, 1)
    for _ in range(trajectories):
        states = rng.normal(size=(steps, 4))
        gains = rng.normal(size=(steps, 1, 4))
        data.append(Trajectory(states, rng.normal(size=(steps, 1)), rng.uniform(0, 10, steps), gains=gains))
    return data


@pytest.mark.parametrize("index", [True, False])
@pytest.mark.parametrize("invariant", [(), (2,)])
def test_the_weighted_choice_is_brute_force_over_the_weighted_states(index: bool, invariant: tuple[int, ...]) -> None:
    rng = np.random.default_rng(4)
    data = random_data(rng)
    space = ControlSpace.of(4, (), [-5.0], [5.0], invariant=invariant, weights=WEIGHTS)
    policy = NonparametricPolicy(data, 3.0, control=space, kind="feedback", index=index)
    queries = rng.normal(size=(50, 4))
    scale = np.array(WEIGHTS) * np.array([0.0 if i in invariant else 1.0 for i in range(4)])
    distances = np.linalg.norm((data.states[None, :, :] - queries[:, None, :]) * scale, axis=2)
    lower = data.values[None, :] - 3.0 * distances
    upper = data.values[None, :] + 3.0 * distances
    found = policy.lower(queries)
    np.testing.assert_allclose(found.value, lower.max(axis=1), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(found.index, lower.argmax(axis=1))
    np.testing.assert_allclose(policy.upper(queries).value, upper.min(axis=1), rtol=0, atol=1e-12)


def test_weights_choose_the_point_and_the_feedback_law_stays_the_tasks() -> None:
    """Two points: nearer in the plain distance is the first, in the weighted one the second; the action at the
    chosen point is its stored action plus its gain times the unweighted difference."""
    data = Dataset(2, 1)
    gains = np.array([[[1.0, 2.0]], [[3.0, -1.0]]])
    data.append(Trajectory(np.array([[0.0, 0.0], [1.0, 1.0]]), np.array([[1.0], [-1.0]]), np.zeros(2), gains=gains))
    s = np.array([0.8, 0.3])
    plain = NonparametricPolicy(data, 1.0, control=ControlSpace.of(2, (), [-9.0], [9.0]), kind="feedback")
    weighted = NonparametricPolicy(
        data, 1.0, control=ControlSpace.of(2, (), [-9.0], [9.0], weights=(1.0, 10.0)), kind="feedback"
    )
    assert plain.lower(s[None]).index[0] == 1 and weighted.lower(s[None]).index[0] == 0
    np.testing.assert_allclose(weighted.act(s), [1.0 + 1.0 * 0.8 + 2.0 * 0.3])


def test_all_ones_is_the_plain_distance_and_bad_weights_are_refused() -> None:
    assert ControlSpace.of(3, (), [0.0], [1.0], weights=(1, 1, 1)).weights == ()
    for bad in ((1.0, 2.0), (1.0, 0.0, 1.0), (1.0, float("nan"), 1.0)):
        with pytest.raises(ValueError, match="distance weights must be 3 finite numbers > 0"):
            ControlSpace(3, (), (0.0,), (1.0,), weights=bad)


def test_the_panda_weighs_its_target_and_the_run_uses_it() -> None:
    space = task_control_space(str(EXAMPLES / "panda_reach" / "task.toml"), 0)
    assert space.weights[7:10] == (10.0, 10.0, 10.0) and set(space.weights[:7] + space.weights[10:]) == {1.0}


@pytest.mark.parametrize(
    ("table", "expected"),
    [
        ("shoulder = 2.0\nelbow = { position = 0.5, velocity = 3.0 }", None),
        ("wrist = 2.0", "state.weights.wrist: unknown joint 'wrist'"),
        ("shoulder = 0.0", "state.weights.shoulder: must be > 0"),
        ("shoulder = { angle = 2.0 }", "state.weights.shoulder.angle: unknown key"),
        ('shoulder = { velocity = "fast" }', "state.weights.shoulder.velocity: must be a finite number"),
    ],
)
def test_a_task_file_states_its_weights_by_joint(tmp_path: Path, table: str, expected: str | None) -> None:
    for name in ("task.toml", "arm.xml"):
        shutil.copy(EXAMPLES / "two_link_arm" / name, tmp_path / name)
    path = tmp_path / "task.toml"
    path.write_text(path.read_text().replace("\n[rho]", f"\n[state.weights]\n{table}\n\n[rho]", 1))
    if expected is not None:
        with pytest.raises(TaskFileError, match=expected):
            get_task(str(path))
        return
    assert task_control_space(str(path), 0).weights == (2.0, 0.5, 1.0, 3.0)


def test_weights_by_spread_make_each_moving_entry_count_alike_and_keep_the_scale() -> None:
    """Each measured entry weighs the inverse of its spread in the data (angle differences wrapped), the weights'
    geometric mean is 1; an entry that never moves and an invariant one keep weight 1."""
    rng = np.random.default_rng(3)
    states = np.column_stack([
        rng.normal(0.0, 0.1, 500),  # an entry with a spread of 0.1
        rng.normal(0.0, 2.0, 500),  # and one with 2
        np.full(500, 0.7),  # one that never moves
        rng.normal(0.0, 5.0, 500),  # an invariant one: not in the distance
        np.pi + rng.normal(0.0, 0.2, 500),  # an angle across the +-pi seam, stored wrapped
    ])  # fmt: skip
    states[:, 4] = np.pi - np.mod(np.pi - states[:, 4], 2 * np.pi)
    control = ControlSpace.of(5, [4], [-1.0], [1.0], invariant=[3])
    weights = np.array(control.weighted_by_spread(states).weights)
    moving = weights[[0, 1, 4]]
    assert np.exp(np.mean(np.log(moving))) == pytest.approx(1.0)
    assert weights[2] == weights[3] == 1.0
    spread = np.array([0.1, 2.0, 0.2])  # the angle's spread measured across the seam, not 2 pi wide
    assert moving * spread == pytest.approx(np.full(3, moving[0] * 0.1), rel=0.1)
