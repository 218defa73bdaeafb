from __future__ import annotations

import numpy as np
import pytest

from npp_ros.policy.dataset import Dataset, DatasetError, Trajectory


def make(steps: int = 3, n: int = 2, m: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.arange(steps * n, dtype=float).reshape(steps, n), np.ones((steps, m)), np.linspace(1, 0, steps)


def test_append_keeps_trajectory_boundaries_and_grows() -> None:
    data = Dataset(2, 1, capacity=1)
    for k in range(5):
        s, a, q = make(steps=k + 1)
        assert data.append_arrays(s, a, q) == k
    assert len(data) == 15
    assert data.num_trajectories == 5
    assert data.trajectory_offsets == (0, 1, 3, 6, 10, 15)
    third = data.trajectory(2)
    np.testing.assert_array_equal(third.states, make(steps=3)[0])
    np.testing.assert_array_equal(data.trajectory(-1).values, make(steps=5)[2])
    assert data.version == 5


@pytest.mark.parametrize(
    ("field", "mutate", "expected"),
    [
        ("states", lambda s, a, q: (s[:, :1], a, q), "states has 1 columns, the dataset's state_dim is 2"),
        ("actions", lambda s, a, q: (s, np.ones((3, 2)), q), "actions has 2 columns, the dataset's action_dim is 1"),
        ("values", lambda s, a, q: (s, a, q[:2]), "values has 2 entries but states has 3 rows"),
        ("actions", lambda s, a, q: (s, a[:1], q), "actions has 1 rows but states has 3"),
        ("states", lambda s, a, q: (s.ravel(), a, q), "states must be 2-D"),
        ("states", lambda s, a, q: (s[:0], a[:0], q[:0]), "states is empty"),
        ("values", lambda s, a, q: (s, a, np.array([1.0, np.nan, 0.0])), "values[1] is nan"),
        ("states", lambda s, a, q: (np.where(np.arange(6).reshape(3, 2) == 3, np.inf, s), a, q), "states[1, 1] is inf"),
        ("actions", lambda s, a, q: (s, [["x"], ["y"], ["z"]], q), "actions is not a numeric array"),
    ],
)
def test_bad_appends_name_the_field_and_index_and_change_nothing(field, mutate, expected) -> None:
    data = Dataset(2, 1)
    data.append_arrays(*make())
    before = (data.states.copy(), data.version)
    with pytest.raises(DatasetError) as err:
        data.append_arrays(*mutate(*make()))
    assert expected in str(err.value)
    assert field in str(err.value)
    assert "trajectory 1" in str(err.value)
    np.testing.assert_array_equal(data.states, before[0])
    assert data.version == before[1] and data.num_trajectories == 1


def test_validated_copies_so_callers_cannot_mutate_stored_data() -> None:
    s, a, q = make()
    traj = Trajectory.validated(s, a, q)
    s[0, 0] = 99.0
    assert traj.states[0, 0] == 0.0


def test_dimensions_must_be_positive() -> None:
    with pytest.raises(DatasetError, match="positive"):
        Dataset(0, 1)
