"""Invariant coordinates: a task may declare joints whose position changes neither dynamics nor reward; the policy's
distance and feedback ignore them, and the loader refuses a declaration the model contradicts."""

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
from npp_ros.tasks.task_file.loader import TaskFileError, load_task_file

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "rotary_pendulum"


def rotary_data() -> Dataset:
    """Two stored points of a (arm, pole, arm rate, pole rate) state with gains on every entry."""
    data = Dataset(4, 1)
    states = np.array([[0.0, 3.0, 0.0, 0.0], [2.0, 0.5, 0.0, 1.0]])
    gains = np.array([[[0.7, 1.0, 0.2, 0.3]], [[0.7, -1.0, 0.1, 0.4]]])
    data.append(Trajectory(states, np.array([[0.1], [-0.2]]), np.array([5.0, 9.0]), gains=gains))
    return data


@pytest.mark.parametrize("kind", ["open-loop", "feedback", "path"])
def test_a_shifted_invariant_angle_gives_the_same_action_and_bounds(kind: str) -> None:
    space = ControlSpace.of(4, (0, 1), [-1.0], [1.0], invariant=(0,))
    policy = NonparametricPolicy(rotary_data(), 3.0, control=space, kind=kind)  # type: ignore[arg-type]
    rng = np.random.default_rng(1)
    for _ in range(20):
        s = rng.uniform(-3, 3, size=4)
        shifted = s.copy()
        shifted[0] = rng.uniform(-np.pi, np.pi)
        np.testing.assert_array_equal(policy.controller()(s), policy.controller()(shifted))
        assert policy.v_lb(s) == policy.v_lb(shifted) and policy.v_ub(s) == policy.v_ub(shifted)
    # Without the declaration the arm angle counts: the same two states are answered differently somewhere.
    plain = NonparametricPolicy(rotary_data(), 3.0, control=ControlSpace.of(4, (0, 1), [-1.0], [1.0]), kind="feedback")
    assert plain.act([0.0, 1.0, 0.0, 0.0])[0] != plain.act([2.5, 1.0, 0.0, 0.0])[0]


def test_the_rotary_pendulum_declares_its_arm_and_the_run_uses_it() -> None:
    task = get_task(str(EXAMPLE / "task.toml"))
    assert task.invariant_entries() == (0,)
    assert task_control_space(str(EXAMPLE / "task.toml"), 0).invariant == (0,)


def test_a_false_invariance_is_refused_naming_the_joint(tmp_path: Path) -> None:
    for name in ("task.toml", "rotary_pendulum.xml"):
        shutil.copy(EXAMPLE / name, tmp_path / name)
    path = tmp_path / "task.toml"
    path.write_text(path.read_text().replace('invariant = ["arm"]', 'invariant = ["pole"]'))
    with pytest.raises(TaskFileError, match=r"state\.invariant: joint 'pole' is not invariant: shifting") as caught:
        load_task_file(str(path))
    assert "\n" not in str(caught.value)
