"""The expert dataset D of (s, a, Q) triplets, kept trajectory by trajectory.

Trajectory boundaries matter: Definition 3.3 (consistency) needs every stored state's successor
to be in D too, which holds trajectory-wise, and the store persists whole trajectories.

Each point may also carry its expert's local feedback gain K (action_dim x state_dim): the expert's
own policy near its trajectory is u = a_t + K_t (s - s_t) (iLQR's backward pass, the LQR gain). The
bounds never read it; the feedback policy (npp_ros.policy.feedback) acts with it. A trajectory whose
expert gave none stores zero gains, so the feedback policy replays its actions open loop.
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
    # The expert's feedback gain at each step, (T, action_dim, state_dim); None when the expert gives none.
    gains: FloatArray | None = None

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
        gains: ArrayLike | None = None,
    ) -> Trajectory:
        """Check shapes, finiteness and dimensions; return float64 copies (gains: None, or one per step)."""
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
        return cls(s, a, q, gains=None if gains is None else _checked_gains(gains, s, a, label))


def _checked_gains(gains: ArrayLike, states: FloatArray, actions: FloatArray, label: str) -> FloatArray:
    """Gains of shape (steps, action_dim, state_dim), finite; a flat row-major array of that size is reshaped."""
    k = _as_float_array(gains, f"{label}: gains")
    steps, n, m = states.shape[0], states.shape[1], actions.shape[1]
    if k.ndim == 1 and k.size == steps * m * n:
        k = k.reshape(steps, m, n)
    if k.shape != (steps, m, n):
        raise DatasetError(
            f"{label}: gains must hold one {m} x {n} matrix (action_dim x state_dim) per step, {steps * m * n} "
            f"numbers in all; got shape {k.shape}"
        )
    _require_finite(k, f"{label}: gains")
    return k


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
        self._gains: FloatArray | None = None  # allocated with the first trajectory that has gains
        self._size = 0
        self._offsets: list[int] = [0]
        self._with_gains: list[bool] = []  # per trajectory: did its expert give gains
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
    def gains(self) -> FloatArray:
        """The feedback gain of every point, (N, action_dim, state_dim); zero where the expert gave none."""
        if self._gains is None:
            return np.zeros((self._size, self.action_dim, self.state_dim))
        return self._gains[: self._size]

    def gains_at(self, index: ArrayLike) -> FloatArray:
        """The gains of the points ``index`` (zeros without allocating all of them when no expert gave any)."""
        rows = np.asarray(index)
        if self._gains is None:
            return np.zeros((*rows.shape, self.action_dim, self.state_dim))
        return self._gains[: self._size][rows]

    @property
    def trajectories_with_gains(self) -> int:
        return sum(self._with_gains)

    @property
    def trajectory_offsets(self) -> tuple[int, ...]:
        """Start index of each trajectory, then the total size."""
        return tuple(self._offsets)

    def trajectory(self, index: int) -> Trajectory:
        if not -self.num_trajectories <= index < self.num_trajectories:
            raise IndexError(f"trajectory {index} out of range; the dataset holds {self.num_trajectories}")
        index %= self.num_trajectories
        lo, hi = self._offsets[index], self._offsets[index + 1]
        gains = self.gains[lo:hi].copy() if self._with_gains[index] else None
        return Trajectory(self.states[lo:hi].copy(), self.actions[lo:hi].copy(), self.values[lo:hi].copy(), gains=gains)

    def prefix(self, trajectories: int) -> Dataset:
        """A copy holding the first ``trajectories`` trajectories: the data as it was after that many calls."""
        if not 0 <= trajectories <= self.num_trajectories:
            raise DatasetError(f"a prefix of {trajectories} trajectories; the dataset holds {self.num_trajectories}")
        out = Dataset(self.state_dim, self.action_dim, capacity=max(self.trajectory_offsets[trajectories], 1))
        for index in range(trajectories):
            out.append(self.trajectory(index))
        return out

    def validate(
        self, states: ArrayLike, actions: ArrayLike, values: ArrayLike, gains: ArrayLike | None = None
    ) -> Trajectory:
        """Validate a would-be trajectory against this dataset without appending it."""
        return Trajectory.validated(
            states,
            actions,
            values,
            state_dim=self.state_dim,
            action_dim=self.action_dim,
            label=f"trajectory {self.num_trajectories}",
            gains=gains,
        )

    def append(self, trajectory: Trajectory) -> int:
        """Append a whole trajectory after validating it; return its trajectory index."""
        checked = self.validate(trajectory.states, trajectory.actions, trajectory.values, trajectory.gains)
        steps = len(checked)
        self._reserve(self._size + steps)
        lo, hi = self._size, self._size + steps
        self._states[lo:hi] = checked.states
        self._actions[lo:hi] = checked.actions
        self._values[lo:hi] = checked.values
        if checked.gains is not None:
            if self._gains is None:
                self._gains = np.zeros((self._states.shape[0], self.action_dim, self.state_dim))
            self._gains[lo:hi] = checked.gains
        elif self._gains is not None:
            self._gains[lo:hi] = 0.0
        self._size = hi
        self._offsets.append(hi)
        self._with_gains.append(checked.gains is not None)
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
        for name in ("_states", "_actions", "_values", "_gains"):
            old = getattr(self, name)
            if old is None:
                continue
            new = np.empty((capacity, *old.shape[1:]))
            new[: self._size] = old[: self._size]
            setattr(self, name, new)
