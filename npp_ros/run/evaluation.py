"""The policy against fresh initial states: the rollouts behind npp-learn's and npp-experiment's checks.

``policy_rollouts`` steps N rollouts of the greedy policy in lockstep on plant clones (batched
policy queries, bit-identical to one-at-a-time rollouts) and records the largest value slope the
policy visited: npp-experiment's checkpoint evaluations are these rollouts, and a certificate's held-out check
(npp_ros.run.held_out, both commands') measures them against the value its claim speaks of.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike

from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import FloatArray
from npp_ros.tasks.registry import Plant
from npp_ros.tasks.rollout import rollout, rollout_batch
from npp_ros.tasks.success import SuccessCriterion
from npp_ros.tasks.uncertainty import Robot

CHUNK = 100  # rollouts stepped in lockstep
VIOLATION_TOLERANCE = 1e-9  # relative: a return below V_lb(s0) by more than rounding


def policy_rollouts(
    plant: Plant,
    policy: NonparametricPolicy,
    states: FloatArray,
    horizon: int,
    slope: Callable[[ArrayLike], FloatArray] | None,
    *,
    chunk: int = CHUNK,
    progress: Callable[[int, int], None] | None = None,
    robots: Sequence[Robot] | None = None,
    met: FloatArray | None = None,
    criterion: SuccessCriterion | None = None,
) -> tuple[FloatArray, FloatArray]:
    """The policy's H-step return from each s0, and the largest |grad V^expert| along each rollout
    (NaN where the expert's value slope is not known in closed form). With ``robots``, s0 k is rolled out on
    robot k (one at a time: each robot is its own model). With ``criterion``, ``met[k]`` is 1 where rollout k met it,
    else 0."""
    returns = np.empty(len(states))
    slopes = np.empty(len(states))
    if progress is not None:
        progress(0, len(states))  # the phase has begun: a chunk of long rollouts says nothing until it ends
    for lo in range(0, len(states), chunk):
        hi = min(lo + chunk, len(states))
        if robots is None:
            runs = rollout_batch(plant, policy.controller(), states[lo:hi], horizon)
        else:
            runs = [rollout(plant, policy.controller(), states[k], horizon, robots[k]) for k in range(lo, hi)]
        for k, run in enumerate(runs):
            returns[lo + k] = run.total_return
            slopes[lo + k] = math.nan if slope is None else float(np.max(slope(run.states)))
            if met is not None and criterion is not None:
                met[lo + k] = float(criterion.met(run.states))
        if progress is not None:
            progress(hi, len(states))
    return returns, slopes


def below_lower_bound(returns: FloatArray, lower: FloatArray) -> FloatArray:
    """Returns below V_lb(s0): impossible where Theorem 3.4 holds (and so a sign that it does not)."""
    return returns < lower - VIOLATION_TOLERANCE * np.maximum(1.0, np.abs(lower))
