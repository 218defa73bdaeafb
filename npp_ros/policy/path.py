"""The path policy: follow the stored trajectory chosen on V_lb, time index by time index, while the state stays near.

The greedy policies choose i* = argmax_i Q_i - L|s - s_i| afresh at every step. On a fast swing the maximiser hops
between stored trajectories whose feedback gains disagree, each correction undoing the last. The path policy keeps
its choice within an episode:

- at the episode's first step, and whenever it has no path to follow, it chooses i* on V_lb exactly as the greedy
  policy does;
- having acted at point i of a stored trajectory, it takes that trajectory's next point j = i + 1 at the next step,
  and keeps it while
      Q_j - L|s - s_j|  >=  V_lb(s) - L r,     r = PATH_SLACK x (max |s_{t+1} - s_t| along that trajectory),
  i.e. while no point's lower bound beats the path's by more than L r (the state has left the path, or another
  point is better by that margin); past the trajectory's last point, or when the rule fails, it chooses i* again;
- at the point it acts with that trajectory's feedback law, clamp(a_j + K_j (s - s_j)), as the feedback policy does.

r is in the units of the policy's distance (invariant entries left out), scaled by the trajectory's own step, so
the rule needs no per-task number. Everything is a function of the data and the states seen since the episode
began: the same (data, s0) gives the same rollout, in process and through the graph.

Where it is reset: :meth:`NonparametricPolicy.controller` (every rollout from s0: npp_ros.tasks.rollout's callers,
the replay, the held-out checks) and the policy node on the first state of each episode (the sim's state at time 0).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from npp_ros.policy.dataset import FloatArray

PATH_SLACK = 1.0
"""How many of its own longest steps a path's lower bound may trail V_lb(s) before the policy chooses again.

Measured on pendulum_swingup (docs/results.md): 0.5 and 1 follow well; 2 and more keep paths the state has left.
A median or mean step is no scale: a swing-up rests upright for most of its steps, which are then all but 0."""


def row_distances(points: FloatArray, queries: FloatArray) -> FloatArray:
    """|q_k - p_k| row by row, accumulated coordinate by coordinate in the order the V_lb search uses."""
    diff = queries[:, 0] - points[:, 0]
    acc = diff * diff
    for k in range(1, points.shape[1]):
        diff = queries[:, k] - points[:, k]
        acc += diff * diff
    return np.sqrt(acc)


def trajectory_slack(states: FloatArray, offsets: NDArray[np.int64], first: int) -> FloatArray:
    """r of trajectories ``first`` onward (PATH_SLACK x the longest distance between consecutive stored states)."""
    out = np.zeros(len(offsets) - 1 - first)
    for k in range(first, len(offsets) - 1):
        lo, hi = int(offsets[k]), int(offsets[k + 1])
        if hi - lo >= 2:
            out[k - first] = PATH_SLACK * float(np.max(row_distances(states[lo : hi - 1], states[lo + 1 : hi])))
    return out


def follow(
    cursor: NDArray[np.int64],
    greedy: NDArray[np.int64],
    best: FloatArray,
    queries: FloatArray,
    states: FloatArray,
    values: FloatArray,
    lipschitz: float,
    offsets: NDArray[np.int64],
    slack: FloatArray,
) -> NDArray[np.int64]:
    """The point each row acts at: its path's next point where the rule keeps it, else the greedy choice.

    ``cursor`` is the point each row acted at last (-1: none, the episode's first step); ``best`` and ``greedy``
    are V_lb at ``queries`` and its maximiser; ``states``, ``values`` the data in the policy's metric.
    """
    chosen = greedy.copy()
    rows = np.flatnonzero(cursor >= 0)
    if len(rows) == 0:
        return chosen
    trajectory = np.searchsorted(offsets, cursor[rows], side="right") - 1
    nxt = cursor[rows] + 1
    on = nxt < offsets[trajectory + 1]
    rows, nxt, trajectory = rows[on], nxt[on], trajectory[on]
    if len(rows) == 0:
        return chosen
    score = values[nxt] - lipschitz * row_distances(states[nxt], queries[rows])
    keep = score >= best[rows] - lipschitz * slack[trajectory]
    chosen[rows[keep]] = nxt[keep]
    return chosen
