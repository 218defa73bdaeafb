"""The expert dataset D of (s, a, Q) triplets, kept trajectory by trajectory.

Trajectory boundaries matter: Definition 3.3 (consistency) needs every stored state's successor
to be in D too, which holds trajectory-wise, and the store persists whole trajectories.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


class DatasetError(ValueError):
    """A trajectory or query that does not fit the dataset; the message names field and index."""


@dataclass(frozen=True)
class Trajectory:
    """One expert trajectory: row t is (s_t, a_t, Q_t)."""

    states: FloatArray  # (T, state_dim)
    actions: FloatArray  # (T, action_dim)
    values: FloatArray  # (T,)
    # The trajectory's own return over its T steps under the task's reward, when the expert says
    # (V^E(s_0) of the oracle certification mode). Not part of the dataset: stored values are Q.
    expert_return: float | None = None

    def __len__(self) -> int:
        return int(self.values.shape[0])

    @classmethod
    def validated(
        cls,
        states: ArrayLike,
        actions: ArrayLike,
        values: ArrayLike,
        *,
        state_dim: int | None = None,
        action_dim: int | None = None,
        label: str = "trajectory",
    ) -> Trajectory:
        """Check shapes, finiteness and dimensions; return float64 copies."""
        s = _as_float_array(states, f"{label}: states")
        a = _as_float_array(actions, f"{label}: actions")
        q = _as_float_array(values, f"{label}: values")
        if s.ndim != 2:
            raise DatasetError(f"{label}: states must be 2-D (steps, state_dim), got shape {s.shape}")
        if a.ndim != 2:
            raise DatasetError(f"{label}: actions must be 2-D (steps, action_dim), got shape {a.shape}")
        if q.ndim != 1:
            raise DatasetError(f"{label}: values must be 1-D (steps,), got shape {q.shape}")
        steps = s.shape[0]
        if steps == 0:
            raise DatasetError(f"{label}: states is empty; a trajectory needs at least one step")
        if a.shape[0] != steps:
            raise DatasetError(f"{label}: actions has {a.shape[0]} rows but states has {steps}")
        if q.shape[0] != steps:
            raise DatasetError(f"{label}: values has {q.shape[0]} entries but states has {steps} rows")
        if s.shape[1] == 0:
            raise DatasetError(f"{label}: states has zero columns")
        if a.shape[1] == 0:
            raise DatasetError(f"{label}: actions has zero columns")
        if state_dim is not None and s.shape[1] != state_dim:
            raise DatasetError(f"{label}: states has {s.shape[1]} columns, the dataset's state_dim is {state_dim}")
        if action_dim is not None and a.shape[1] != action_dim:
            raise DatasetError(f"{label}: actions has {a.shape[1]} columns, the dataset's action_dim is {action_dim}")
        for name, arr in (("states", s), ("actions", a), ("values", q)):
            _require_finite(arr, f"{label}: {name}")
        return cls(s, a, q)


def _as_float_array(data: ArrayLike, what: str) -> FloatArray:
    try:
        return np.array(data, dtype=np.float64, copy=True)
    except (TypeError, ValueError) as exc:
        raise DatasetError(f"{what} is not a numeric array: {exc}") from exc


def _require_finite(arr: FloatArray, what: str) -> None:
    bad = ~np.isfinite(arr)
    if bad.any():
        where = tuple(int(i) for i in np.argwhere(bad)[0])
        index = ", ".join(str(i) for i in where)
        raise DatasetError(f"{what}[{index}] is {float(arr[where])}; every entry must be finite")


class Dataset:
    """Growing arrays of expert triplets with trajectory offsets.

    Appends amortise to O(1) by capacity doubling; the public arrays are views of the filled
    part, so bound queries never copy. ``version`` changes on every append, which lets
    accelerated query structures know when to rebuild.
    """

    def __init__(self, state_dim: int, action_dim: int, capacity: int = 1024) -> None:
        if state_dim <= 0 or action_dim <= 0:
            raise DatasetError(f"state_dim and action_dim must be positive, got {state_dim}, {action_dim}")
        self.state_dim = int(state_dim)
        self.action_dim = int(action_dim)
        capacity = max(int(capacity), 1)
        self._states = np.empty((capacity, self.state_dim))
        self._actions = np.empty((capacity, self.action_dim))
        self._values = np.empty(capacity)
        self._size = 0
        self._offsets: list[int] = [0]
        self.version = 0

    def __len__(self) -> int:
        return self._size

    @property
    def num_trajectories(self) -> int:
        return len(self._offsets) - 1

    @property
    def states(self) -> FloatArray:
        return self._states[: self._size]

    @property
    def actions(self) -> FloatArray:
        return self._actions[: self._size]

    @property
    def values(self) -> FloatArray:
        return self._values[: self._size]

    @property
    def trajectory_offsets(self) -> tuple[int, ...]:
        """Start index of each trajectory, then the total size."""
        return tuple(self._offsets)

    def trajectory(self, index: int) -> Trajectory:
        if not -self.num_trajectories <= index < self.num_trajectories:
            raise IndexError(f"trajectory {index} out of range; the dataset holds {self.num_trajectories}")
        index %= self.num_trajectories
        lo, hi = self._offsets[index], self._offsets[index + 1]
        return Trajectory(self.states[lo:hi].copy(), self.actions[lo:hi].copy(), self.values[lo:hi].copy())

    def prefix(self, trajectories: int) -> Dataset:
        """A copy holding the first ``trajectories`` trajectories: the data as it was after that many calls."""
        if not 0 <= trajectories <= self.num_trajectories:
            raise DatasetError(f"a prefix of {trajectories} trajectories; the dataset holds {self.num_trajectories}")
        out = Dataset(self.state_dim, self.action_dim, capacity=max(self.trajectory_offsets[trajectories], 1))
        for index in range(trajectories):
            out.append(self.trajectory(index))
        return out

    def validate(self, states: ArrayLike, actions: ArrayLike, values: ArrayLike) -> Trajectory:
        """Validate a would-be trajectory against this dataset without appending it."""
        return Trajectory.validated(
            states,
            actions,
            values,
            state_dim=self.state_dim,
            action_dim=self.action_dim,
            label=f"trajectory {self.num_trajectories}",
        )

    def append(self, trajectory: Trajectory) -> int:
        """Append a whole trajectory after validating it; return its trajectory index."""
        checked = self.validate(trajectory.states, trajectory.actions, trajectory.values)
        steps = len(checked)
        self._reserve(self._size + steps)
        lo, hi = self._size, self._size + steps
        self._states[lo:hi] = checked.states
        self._actions[lo:hi] = checked.actions
        self._values[lo:hi] = checked.values
        self._size = hi
        self._offsets.append(hi)
        self.version += 1
        return self.num_trajectories - 1

    def append_arrays(self, states: ArrayLike, actions: ArrayLike, values: ArrayLike) -> int:
        return self.append(self.validate(states, actions, values))

    def _reserve(self, needed: int) -> None:
        capacity = self._states.shape[0]
        if needed <= capacity:
            return
        while capacity < needed:
            capacity *= 2
        for name in ("_states", "_actions", "_values"):
            old = getattr(self, name)
            new = np.empty((capacity, *old.shape[1:]))
            new[: self._size] = old[: self._size]
            setattr(self, name, new)
