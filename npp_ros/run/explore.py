"""Ask the expert where the policy goes: one more trajectory from where the policy's own rollout leaves the data.

A failed check sends s0 to the expert (Algorithm 1). On an unstable or chaotic plant the policy then leaves the
new path too, somewhere the data say nothing of, and more demonstrations from s0 only add more paths it leaves.
With a radius r > 0 the run also asks the expert from the first state of the policy's rollout from s0 whose
nearest stored state is farther than r (DAgger's idea, asked where the learner goes, once per failed check), and
stores that trajectory too. Every such call counts as an expert call in the run's figures.

The rollout is the policy's own, re-run on a local copy of the plant: the plant is deterministic (an assumption
every certificate states), so it is the rollout the check measured, and the graph's supervisor finds the same
state as the in-process loop.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import FloatArray
from npp_ros.tasks.registry import Plant
from npp_ros.tasks.rollout import rollout

EXPLORE_HELP = (
    "after a failed check, also ask the expert from the first state of the policy's own rollout farther than this "
    "from every stored state (one more expert call, counted); 0: only s0, as the paper"
)


def check_radius(radius: float) -> float:
    if not (np.isfinite(radius) and radius >= 0):
        raise ValueError(f"the exploration radius must be finite and >= 0 (0: off), got {radius!r}")
    return float(radius)


class RolloutExplorer:
    """Finds the first state of the policy's rollout from s0 farther than ``radius`` from every stored state."""

    def __init__(self, plant: Plant, horizon: int, radius: float) -> None:
        self.plant = plant
        self.horizon = int(horizon)
        self.radius = check_radius(radius)

    def state_to_ask(self, initial_state: FloatArray, policy: NonparametricPolicy) -> FloatArray | None:
        """The state to ask the expert from, or None (no data yet, or the rollout never leaves the data)."""
        if len(policy.dataset) == 0 or self.radius == 0:
            return None
        states = rollout(self.plant, policy.act, initial_state, self.horizon).states
        distance, _ = cKDTree(policy.dataset.states).query(states)
        far = np.flatnonzero(distance > self.radius)
        return None if len(far) == 0 else states[far[0]].copy()
