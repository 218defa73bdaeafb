"""Lipschitz bounds on V* and Q*, the surrogate gap, and the greedy nonparametric policy.

V_lb(s) = max_i Q_i - L|s - s_i|        (1)    V_ub(s) = min_j Q_j + L|s - s_j|        (3)
Q_lb(s, a) = max_i Q_i - L(|s - s_i| + |a - a_i|)   (2), Q_ub mirrored (4).

The policy chooses i*, the maximiser of (1); ties go to the smallest index (Remark 3.2), which is
what ``np.argmax`` returns. It acts with a_{i*} (the paper's open-loop policy) or, given the task's
:class:`~npp_ros.policy.feedback.ControlSpace`, with the expert's feedback law at i*
(npp_ros.policy.feedback), or follows the stored trajectory it chose (npp_ros.policy.path, the one
kind with memory within an episode). A task's invariant state entries are left out of every distance
(their difference is 0). Distances are accumulated coordinate by
coordinate in a fixed order, so a single query and the same state inside a batch give the same
floating-point numbers, bit for bit.

V_lb and V_ub (and so the gap and the policy) go through :class:`npp_ros.policy.kdtree.BoundIndex`, an
exact branch-and-bound kd-tree that returns the same values and indices as the brute force here,
bit for bit, ties included; ``index=False`` keeps the plain brute force (the reference). Q_lb and
Q_ub, which add an action term, stay brute force.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from npp_ros.policy.dataset import Dataset, DatasetError, FloatArray
from npp_ros.policy.feedback import FEEDBACK_KINDS, ControlSpace, PolicyKind, check_policy_kind, feedback_actions
from npp_ros.policy.path import follow, trajectory_slack
from npp_ros.policy.vectors import bounded

# Upper limit on the (queries x points) block evaluated at once, to bound memory.
_BLOCK_ELEMENTS = 1 << 22


class EmptyDatasetError(DatasetError):
    """The policy has no data: it never invents an action."""


class PathEpisodeError(RuntimeError):
    """The path policy was asked to act outside an episode: its memory (the path it follows) is an episode's."""


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


class MeasuredData:
    """The dataset as the policy's distance sees it: the invariant entries left out (their difference is 0), each
    other entry times its weight (npp_ros.policy.feedback.ControlSpace.weights).

    Duck-types the parts of :class:`Dataset` the search reads (states, values, size, version); its states are a
    copy, brought up to date when the dataset grows.
    """

    def __init__(self, dataset: Dataset, measured: tuple[int, ...], weights: FloatArray | None = None) -> None:
        self.dataset = dataset
        self.measured = list(measured)
        self.weights = weights
        self.state_dim = len(measured)
        self._states = np.empty((0, self.state_dim))

    def queries(self, states: FloatArray) -> FloatArray:
        """States (rows) as this metric sees them, as its stored states are."""
        picked = states[:, self.measured]
        return np.ascontiguousarray(picked if self.weights is None else picked * self.weights)

    def __len__(self) -> int:
        return len(self.dataset)

    @property
    def version(self) -> int:
        return self.dataset.version

    @property
    def values(self) -> FloatArray:
        return self.dataset.values

    @property
    def states(self) -> FloatArray:
        size = len(self.dataset)
        if self._states.shape[0] != size:
            new = self.queries(self.dataset.states[self._states.shape[0] : size])
            self._states = np.ascontiguousarray(np.concatenate([self._states, new]))
        return self._states


class NonparametricPolicy:
    """Bounds and greedy actions over a live :class:`Dataset`, exact.

    ``index`` (default on) answers V_lb / V_ub with the kd-tree index; ``compress`` (default on)
    lets that index skip points that can never attain a bound (the dataset keeps them). Both
    return exactly what the brute force returns. ``control`` None acts open loop (the paper's
    policy); a task's ControlSpace makes it act with the expert's feedback gain at the chosen point, unless
    ``kind`` says otherwise (open-loop with a control space: stored actions, the space's invariant entries
    left out of the distance; path: npp_ros.policy.path).

    The path policy remembers, per batch row, the point it acted at last: :meth:`controller` (or :meth:`reset`)
    starts a new episode. The greedy kinds have no memory; for them both are no-ops.
    """

    def __init__(
        self,
        dataset: Dataset,
        lipschitz: float,
        *,
        index: bool = True,
        compress: bool = True,
        control: ControlSpace | None = None,
        kind: PolicyKind | None = None,
    ) -> None:
        if not np.isfinite(lipschitz) or lipschitz <= 0:
            raise ValueError(f"the Lipschitz constant must be finite and > 0, got {lipschitz!r}")
        if control is not None and control.state_dim != dataset.state_dim:
            raise ValueError(f"the control space is of {control.state_dim}-D states, the data of {dataset.state_dim}-D")
        if control is not None and len(control.action_low) != dataset.action_dim:
            actuators = len(control.action_low)
            raise ValueError(f"the control space has {actuators} actuators, the data {dataset.action_dim}")
        kind = check_policy_kind(kind or ("open-loop" if control is None else "feedback"))
        if kind in FEEDBACK_KINDS and control is None:
            raise ValueError(f"the {kind} policy needs the task's control space (its angles and actuator range)")
        self.dataset = dataset
        self.lipschitz = float(lipschitz)
        self.control = control
        self.kind: PolicyKind = kind
        # What every distance is measured on: the data itself, or its copy without the invariant entries and with
        # each entry times its weight.
        self.measured = (
            MeasuredData(dataset, control.measured, control.metric_weights)
            if control is not None and (control.invariant or control.weights)
            else None
        )
        self.metric: Dataset | MeasuredData = dataset if self.measured is None else self.measured
        # numba (the index's kernels) loads with the first policy, not with every process that imports this module
        from npp_ros.policy.kdtree import BoundIndex

        self.index = BoundIndex(self.metric, self.lipschitz, compress=compress) if index else None  # type: ignore[arg-type]
        self._slack = np.zeros(0)  # path: r of each stored trajectory (npp_ros.policy.path)

    # ----------------------------------------------------------------- episodes
    def episode(self) -> NonparametricPolicy | PathEpisode:
        """What acts over one new episode from s0 (or a batch in lockstep), with ``act`` and ``act_at``: the policy
        itself where it has no memory; for the path policy a :class:`PathEpisode`, which holds that episode's path,
        its own, so that two episodes never share one."""
        return PathEpisode(self) if self.kind == "path" else self

    def controller(self) -> Callable[[ArrayLike], FloatArray]:
        """The policy's action for one new rollout from s0 (or a batch in lockstep): its episode's ``act``."""
        return self.episode().act

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
        if self.measured is not None:
            queries = self.measured.queries(queries)
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
            dist = pairwise_distances(self.metric.states, queries[lo:hi])
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
        return self._lower_nonempty(batch).index

    def _lower_nonempty(self, batch: FloatArray) -> BoundQuery:
        if len(self.dataset) == 0:
            raise EmptyDatasetError("the dataset is empty: the policy has no action to give")
        return self._search(batch, None, lower=True)

    def _follow(self, batch: FloatArray, found: BoundQuery, cursor: NDArray[np.int64] | None) -> NDArray[np.int64]:
        """The path policy's point for each row (npp_ros.policy.path), after ``cursor`` (the points its episode
        acted at last; None at the episode's first step)."""
        if cursor is None:
            cursor = np.full(len(batch), -1, dtype=np.int64)
        elif len(cursor) != len(batch):
            raise ValueError(
                f"the path policy follows {len(cursor)} episodes, asked for {len(batch)} states: take a new "
                "controller() when another rollout starts"
            )
        offsets = np.asarray(self.dataset.trajectory_offsets, dtype=np.int64)
        states = self.metric.states
        known = len(self._slack)
        if known < self.dataset.num_trajectories:
            self._slack = np.concatenate([self._slack, trajectory_slack(states, offsets, known)])
        queries = batch if self.measured is None else self.measured.queries(batch)
        return follow(
            cursor, found.index, found.value, queries, states, self.dataset.values, self.lipschitz, offsets, self._slack
        )

    def act(self, states: ArrayLike) -> FloatArray:
        """pi(s): a_{i*} (open loop, always an action from the dataset, Remark 3.2), or the feedback law at i*. The
        path policy acts within an episode only: through :meth:`controller`, one per episode."""
        return self.act_at(states)[0]

    def act_at(self, states: ArrayLike) -> tuple[FloatArray, int | NDArray[np.int64]]:
        """pi(s) and i*, the chosen point (a robot checks its coverage there without another search)."""
        if self.kind == "path":
            raise PathEpisodeError(
                "the path policy follows the trajectory it chose over one episode, so it acts within an episode only: "
                "take policy.controller() (or policy.episode()) at each episode's start and call it at every step"
            )
        return self._act_at(states, None)[:2]

    def _act_at(
        self, states: ArrayLike, cursor: NDArray[np.int64] | None
    ) -> tuple[FloatArray, int | NDArray[np.int64], NDArray[np.int64]]:
        """pi(s), i*, and the chosen points as a path episode's next cursor."""
        batch, single = self._states(states)
        found = self._lower_nonempty(batch)
        index = found.index if self.kind != "path" else self._follow(batch, found, cursor)
        if self.kind == "open-loop":
            actions = self.dataset.actions[index]
        else:
            assert self.control is not None
            actions = feedback_actions(self.dataset, index, batch, self.control)
        if single:
            return actions[0].copy(), int(index[0]), index
        return actions.copy(), index, index


class PathEpisode:
    """One episode of the path policy (or a batch of episodes in lockstep): the points of its path it acted at last,
    which no other episode sees. ``NonparametricPolicy.controller()`` makes one per rollout."""

    def __init__(self, policy: NonparametricPolicy) -> None:
        self.policy = policy
        self._cursor: NDArray[np.int64] | None = None  # None: the episode's first step, a greedy choice on V_lb

    def act(self, states: ArrayLike) -> FloatArray:
        return self.act_at(states)[0]

    def act_at(self, states: ArrayLike) -> tuple[FloatArray, int | NDArray[np.int64]]:
        """This episode's next action and the point it follows."""
        actions, index, self._cursor = self.policy._act_at(states, self._cursor)
        return actions, index
