"""Lipschitz bounds on V* and Q*, the surrogate gap, and the greedy nonparametric policy.

V_lb(s) = max_i Q_i - L|s - s_i|        (1)    V_ub(s) = min_j Q_j + L|s - s_j|        (3)
Q_lb(s, a) = max_i Q_i - L(|s - s_i| + |a - a_i|)   (2), Q_ub mirrored (4).

The policy chooses i*, the maximiser of (1); ties go to the smallest index (Remark 3.2), which is
what ``np.argmax`` returns. It acts with a_{i*} (the paper's open-loop policy) or, given the task's
:class:`~npp_ros.policy.feedback.ControlSpace`, with the expert's feedback law at i*
(npp_ros.policy.feedback). Distances are accumulated coordinate by
coordinate in a fixed order, so a single query and the same state inside a batch give the same
floating-point numbers, bit for bit.

V_lb and V_ub (and so the gap and the policy) go through :class:`npp_ros.policy.kdtree.BoundIndex`, an
exact branch-and-bound kd-tree that returns the same values and indices as the brute force here,
bit for bit, ties included; ``index=False`` keeps the plain brute force (the reference). Q_lb and
Q_ub, which add an action term, stay brute force.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from npp_ros.policy.dataset import Dataset, DatasetError, FloatArray
from npp_ros.policy.feedback import ControlSpace, PolicyKind, feedback_actions
from npp_ros.policy.kdtree import BoundIndex
from npp_ros.policy.vectors import bounded

# Upper limit on the (queries x points) block evaluated at once, to bound memory.
_BLOCK_ELEMENTS = 1 << 22


class EmptyDatasetError(DatasetError):
    """The policy has no data: it never invents an action."""


@dataclass(frozen=True)
class BoundQuery:
    """Result of one bound evaluation: the bound and the index that attains it."""

    value: FloatArray  # (B,)
    index: NDArray[np.int64]  # (B,), -1 when the dataset is empty


def pairwise_distances(points: FloatArray, queries: FloatArray) -> FloatArray:
    """Euclidean distances (B, N) with a fixed summation order (reproducible bit for bit)."""
    diff = queries[:, None, 0] - points[None, :, 0]
    acc = diff * diff
    for k in range(1, points.shape[1]):
        diff = queries[:, None, k] - points[None, :, k]
        acc += diff * diff
    return np.sqrt(acc)


class NonparametricPolicy:
    """Bounds and greedy actions over a live :class:`Dataset`, exact.

    ``index`` (default on) answers V_lb / V_ub with the kd-tree index; ``compress`` (default on)
    lets that index skip points that can never attain a bound (the dataset keeps them). Both
    return exactly what the brute force returns. ``control`` None acts open loop (the paper's
    policy); a task's ControlSpace makes it act with the expert's feedback gain at the chosen point.
    """

    def __init__(
        self,
        dataset: Dataset,
        lipschitz: float,
        *,
        index: bool = True,
        compress: bool = True,
        control: ControlSpace | None = None,
    ) -> None:
        if not np.isfinite(lipschitz) or lipschitz <= 0:
            raise ValueError(f"the Lipschitz constant must be finite and > 0, got {lipschitz!r}")
        if control is not None and control.state_dim != dataset.state_dim:
            raise ValueError(f"the control space is of {control.state_dim}-D states, the data of {dataset.state_dim}-D")
        if control is not None and len(control.action_low) != dataset.action_dim:
            actuators = len(control.action_low)
            raise ValueError(f"the control space has {actuators} actuators, the data {dataset.action_dim}")
        self.dataset = dataset
        self.lipschitz = float(lipschitz)
        self.control = control
        self.index = BoundIndex(dataset, self.lipschitz, compress=compress) if index else None

    @property
    def kind(self) -> PolicyKind:
        return "open-loop" if self.control is None else "feedback"

    # ----------------------------------------------------------------- validation
    def _states(self, states: ArrayLike) -> tuple[FloatArray, bool]:
        arr = np.asarray(states, dtype=np.float64)
        single = arr.ndim == 1
        batch = arr[None, :] if single else arr
        n = self.dataset.state_dim
        if batch.ndim != 2 or batch.shape[1] != n:
            raise DatasetError(f"state must have shape ({n},) or (batch, {n}); got {arr.shape}")
        if not np.isfinite(batch).all():
            row, col = (int(i) for i in np.argwhere(~np.isfinite(batch))[0])
            where = f"[{col}]" if single else f"[{row}, {col}]"
            raise DatasetError(f"state{where} is {float(batch[row, col])}; query states must be finite")
        bounded(arr, "state")  # the distances must not overflow: huge states are refused, not answered
        return batch, single

    def _actions(self, actions: ArrayLike, batch_size: int) -> FloatArray:
        arr = np.asarray(actions, dtype=np.float64)
        batch = arr[None, :] if arr.ndim == 1 else arr
        m = self.dataset.action_dim
        if batch.ndim != 2 or batch.shape != (batch_size, m):
            raise DatasetError(f"action must have shape ({m},) or ({batch_size}, {m}); got {arr.shape}")
        if not np.isfinite(batch).all():
            raise DatasetError("query actions must be finite")
        bounded(arr, "action")
        return batch

    # ----------------------------------------------------------------- core search
    def _search(self, queries: FloatArray, offsets: FloatArray | None, lower: bool) -> BoundQuery:
        """max_i (Q_i - L d_i) if lower else min_j (Q_j + L d_j); d may include an action term."""
        if offsets is None and self.index is not None:
            value, index = self.index.search(queries, lower)
            return BoundQuery(value, index)
        data = self.dataset
        count = queries.shape[0]
        if len(data) == 0:
            fill = -np.inf if lower else np.inf
            return BoundQuery(np.full(count, fill), np.full(count, -1, dtype=np.int64))
        values = np.empty(count)
        index = np.empty(count, dtype=np.int64)
        block = max(1, _BLOCK_ELEMENTS // len(data))
        q, L = data.values, self.lipschitz
        for lo in range(0, count, block):
            hi = min(lo + block, count)
            dist = pairwise_distances(data.states, queries[lo:hi])
            if offsets is not None:
                dist += offsets[lo:hi]
            scores = q - L * dist if lower else q + L * dist
            best = np.argmax(scores, axis=1) if lower else np.argmin(scores, axis=1)
            index[lo:hi] = best
            values[lo:hi] = np.take_along_axis(scores, best[:, None], axis=1)[:, 0]
        return BoundQuery(values, index)

    def _action_distances(self, actions: FloatArray) -> FloatArray:
        return pairwise_distances(self.dataset.actions, actions)

    @staticmethod
    def _out(result: FloatArray, single: bool) -> float | FloatArray:
        return float(result[0]) if single else result

    # ----------------------------------------------------------------- public API
    def lower(self, states: ArrayLike) -> BoundQuery:
        """V_lb with its maximiser, always batched."""
        batch, _ = self._states(states)
        return self._search(batch, None, lower=True)

    def upper(self, states: ArrayLike) -> BoundQuery:
        """V_ub with its minimiser, always batched."""
        batch, _ = self._states(states)
        return self._search(batch, None, lower=False)

    def v_lb(self, states: ArrayLike) -> float | FloatArray:
        batch, single = self._states(states)
        return self._out(self._search(batch, None, lower=True).value, single)

    def v_ub(self, states: ArrayLike) -> float | FloatArray:
        batch, single = self._states(states)
        return self._out(self._search(batch, None, lower=False).value, single)

    def q_lb(self, states: ArrayLike, actions: ArrayLike) -> float | FloatArray:
        batch, single = self._states(states)
        acts = self._actions(actions, len(batch))
        offsets = self._action_distances(acts) if len(self.dataset) else None
        return self._out(self._search(batch, offsets, lower=True).value, single)

    def q_ub(self, states: ArrayLike, actions: ArrayLike) -> float | FloatArray:
        batch, single = self._states(states)
        acts = self._actions(actions, len(batch))
        offsets = self._action_distances(acts) if len(self.dataset) else None
        return self._out(self._search(batch, offsets, lower=False).value, single)

    def gap(self, states: ArrayLike) -> float | FloatArray:
        """Surrogate gap V_ub - V_lb (5); +inf on an empty dataset."""
        batch, single = self._states(states)
        lo = self._search(batch, None, lower=True).value
        hi = self._search(batch, None, lower=False).value
        return self._out(hi - lo, single)

    def greedy_index(self, states: ArrayLike) -> int | NDArray[np.int64]:
        batch, single = self._states(states)
        index = self._greedy(batch)
        return int(index[0]) if single else index

    def _greedy(self, batch: FloatArray) -> NDArray[np.int64]:
        if len(self.dataset) == 0:
            raise EmptyDatasetError("the dataset is empty: the policy has no action to give")
        return self._search(batch, None, lower=True).index

    def act(self, states: ArrayLike) -> FloatArray:
        """pi(s): a_{i*} (open loop, always an action from the dataset, Remark 3.2), or the feedback law at i*."""
        return self.act_at(states)[0]

    def act_at(self, states: ArrayLike) -> tuple[FloatArray, int | NDArray[np.int64]]:
        """pi(s) and i*, the chosen point (a robot checks its coverage there without another search)."""
        batch, single = self._states(states)
        index = self._greedy(batch)
        if self.control is None:
            actions = self.dataset.actions[index]
        else:
            actions = feedback_actions(self.dataset, index, batch, self.control)
        return (actions[0].copy(), int(index[0])) if single else (actions.copy(), index)
