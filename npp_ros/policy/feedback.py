"""Which action the policy takes at its chosen data point: the stored one, or the expert's feedback law there.

The first two policies choose the data point i* exactly as the paper does (the maximiser of V_lb,
npp_ros.policy.bounds) at every step. They differ only in the action at i*:

- ``open-loop`` (the paper): a = a_i*, the stored action, replayed whatever the state;
- ``feedback``: a = clamp(a_i* + K_i* (s - s_i*)), the expert's own local policy around its trajectory (iLQR's
  backward-pass gain, the LQR gain), as LQR-trees and trajectory libraries act. The difference s - s_i* is the
  task's own: entries that are angles are wrapped to (-pi, pi], so a state just across the +-pi seam is near,
  not 2 pi away. The action is clamped to the actuator range, as the plant would clamp it.

On an unstable plant a state a little off the stored path needs a correction that a stored action does not hold:
the feedback policy carries it. A point whose expert gave no gain has K = 0 and acts open loop.

The third, ``path`` (npp_ros.policy.path), acts as ``feedback`` does but remembers its choice within an episode: it
follows the stored trajectory it chose, time index by time index, while the state stays near it, and chooses again
on V_lb when it leaves.

A task may declare ``invariant`` state entries (positions that change neither dynamics nor reward, e.g. a rotary
pendulum's arm angle): every policy's distance and the feedback difference take those entries' difference as 0,
as if the state were shifted onto the stored point's position there.

A task may also weigh its state entries in the policy's distance (``weights``): each entry's difference times its
weight, so that a centimetre of a reach's target can count as much as a tenth of a radian of a joint. The weights
decide only which data point the policy chooses; the feedback difference s - s_i* is the task's own, unweighted.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np
from numpy.typing import ArrayLike, NDArray

from npp_ros.policy.dataset import Dataset, FloatArray

PolicyKind = Literal["open-loop", "feedback", "path"]
POLICY_KINDS: tuple[str, ...] = get_args(PolicyKind)
PAPER_POLICY: PolicyKind = "open-loop"
DEFAULT_POLICY: PolicyKind = "feedback"  # what a run uses unless it names one: the better measured (docs/results.md)
POLICY_HELP = (
    "how the policy acts at the data point it chooses on V_lb: open-loop (the paper's: the stored action), "
    "feedback (the stored action plus the expert's feedback gain times the state difference), or path (feedback "
    "along the stored trajectory it chose, followed step by step while the state stays near it); "
    f"default {DEFAULT_POLICY}"
)
FEEDBACK_KINDS: tuple[str, ...] = ("feedback", "path")  # the kinds that act with the expert's gains


def wrap_angle(angle: ArrayLike) -> FloatArray:
    """Map angles to (-pi, pi] (pi stays pi, -pi becomes pi)."""
    a = np.asarray(angle, dtype=np.float64)
    return np.pi - np.mod(np.pi - a, 2 * np.pi)


def check_policy_kind(kind: str) -> PolicyKind:
    if kind not in POLICY_KINDS:
        raise ValueError(f"the policy must be one of {', '.join(POLICY_KINDS)}, got {kind!r}")
    return kind  # type: ignore[return-value]


@dataclass(frozen=True)
class ControlSpace:
    """How a task's states differ and how far its actuators reach: what the feedback law needs of the plant.

    ``angles`` are the state entries stored wrapped to (-pi, pi]; ``action_low`` and ``action_high`` the
    actuator range (infinite where an actuator has no limit); ``invariant`` the state entries (positions) whose
    value changes neither the dynamics nor the reward: their difference is taken as 0.
    """

    state_dim: int
    angles: tuple[int, ...]
    action_low: tuple[float, ...]
    action_high: tuple[float, ...]
    invariant: tuple[int, ...] = ()
    weights: tuple[float, ...] = ()  # each entry's weight in the policy's distance; () = every entry 1

    def __post_init__(self) -> None:
        if any(not 0 <= i < self.state_dim for i in self.angles):
            raise ValueError(f"angle entries {self.angles} must lie in [0, {self.state_dim})")
        if any(not 0 <= i < self.state_dim for i in self.invariant):
            raise ValueError(f"invariant entries {self.invariant} must lie in [0, {self.state_dim})")
        if len(set(self.invariant)) == self.state_dim:
            raise ValueError("every state entry is invariant: the policy would have no distance to choose by")
        if self.weights and (len(self.weights) != self.state_dim or not all(
            math.isfinite(w) and w > 0 for w in self.weights
        )):  # fmt: skip
            raise ValueError(f"distance weights must be {self.state_dim} finite numbers > 0, got {self.weights}")
        if len(self.action_low) != len(self.action_high):
            raise ValueError("action_low and action_high must have one entry per actuator")
        low, high = np.asarray(self.action_low), np.asarray(self.action_high)
        if np.any(np.isnan(low)) or np.any(np.isnan(high)) or np.any(low > high):
            raise ValueError(f"the action range [{self.action_low}, {self.action_high}] is not a range")

    @classmethod
    def of(
        cls,
        state_dim: int,
        angles: Sequence[int],
        low: ArrayLike,
        high: ArrayLike,
        invariant: Sequence[int] = (),
        weights: Sequence[float] = (),
    ) -> ControlSpace:
        return cls(
            int(state_dim),
            tuple(int(i) for i in angles),
            tuple(float(x) for x in np.ravel(low)),
            tuple(float(x) for x in np.ravel(high)),
            tuple(sorted({int(i) for i in invariant})),
            tuple(float(w) for w in weights) if any(float(w) != 1.0 for w in weights) else (),
        )

    def weighted_by_spread(self, states: FloatArray) -> ControlSpace:
        """This space with distance weights read off stored ``states``: each measured entry's weight the inverse of
        its spread there (its standard deviation, angles' differences wrapped), so that each entry's typical variation
        counts alike; scaled so that their geometric mean is 1, which keeps an L's scale. An entry that does not vary
        in the data keeps weight 1 (its difference there is 0). What a task that states no weights might use."""
        rows = np.asarray(states, dtype=np.float64).reshape(-1, self.state_dim)
        center = rows.mean(axis=0)
        if self.angles:  # an angle's mean on the circle: values on both sides of the +-pi seam are near
            index = list(self.angles)
            center[index] = np.arctan2(np.sin(rows[:, index]).mean(axis=0), np.cos(rows[:, index]).mean(axis=0))
        spread = np.std(self.difference(rows, np.broadcast_to(center, rows.shape).copy()), axis=0)
        moving = [i for i in self.measured if spread[i] > 1e-12 * max(1.0, float(np.abs(rows[:, i]).max()))]
        weights = np.ones(self.state_dim)
        if moving:
            inverse = 1.0 / spread[moving]
            weights[moving] = inverse / math.exp(float(np.mean(np.log(inverse))))
        return ControlSpace.of(self.state_dim, self.angles, self.action_low, self.action_high, self.invariant, weights)

    @property
    def metric_weights(self) -> FloatArray | None:
        """The weights of the measured entries, in their order; None when every one is 1."""
        if not self.weights:
            return None
        return np.array([self.weights[i] for i in self.measured], dtype=np.float64)

    @property
    def measured(self) -> tuple[int, ...]:
        """The state entries the policy's distance measures: all but the invariant ones."""
        return tuple(i for i in range(self.state_dim) if i not in self.invariant)

    def difference(self, states: FloatArray, references: FloatArray) -> FloatArray:
        """s - s_ref with the angle entries wrapped and the invariant entries 0 (rows of equal shape)."""
        diff = states - references
        if self.angles:
            index = list(self.angles)
            diff[..., index] = wrap_angle(diff[..., index])
        if self.invariant:
            diff[..., list(self.invariant)] = 0.0
        return diff

    def clamp(self, actions: FloatArray) -> FloatArray:
        return np.clip(actions, self.action_low, self.action_high)


def feedback_actions(dataset: Dataset, index: NDArray[np.int64], states: FloatArray, space: ControlSpace) -> FloatArray:
    """clamp(a_i + K_i (s - s_i)) for each row of ``states`` (B, n) and its chosen point ``index`` (B,)."""
    diff = space.difference(states, dataset.states[index])
    correction = np.matmul(dataset.gains_at(index), diff[:, :, None])[:, :, 0]
    return space.clamp(dataset.actions[index] + correction)
