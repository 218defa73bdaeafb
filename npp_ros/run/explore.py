"""Ask the expert where the policy goes: one more trajectory from where the policy's own rollout leaves the data.

A failed check sends s0 to the expert (Algorithm 1). On an unstable or chaotic plant the policy then leaves the
new path too, somewhere the data say nothing of, and more demonstrations from s0 only add more paths it leaves.
With a radius r > 0 the run also asks the expert from the first state of the policy's rollout from s0 whose
nearest stored state is farther than r (DAgger's idea, asked where the learner goes, once per failed check), and
stores that trajectory too. Every such call counts as an expert call in the run's figures.

The rollout is the policy's own, re-run on a local copy of the plant (:class:`PolicyReplay`): the plant is
deterministic (an assumption every certificate states), so it is the rollout the check measured, and the graph's
supervisor finds the same state as the in-process loop. The same replay gives the loop the states of the policy's
rollout for the task's success criterion (npp_ros.tasks.success); in process it is also the rollout the episode
driver runs, so an episode rolls the policy out once whatever asks for its states.
"""

from __future__ import annotations

import numpy as np

from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import FloatArray
from npp_ros.tasks.registry import Plant
from npp_ros.tasks.rollout import Rollout, rollout
from npp_ros.tasks.uncertainty import Robot

EXPLORE_HELP = (
    "after a failed check, also ask the expert from the first state of the policy's own rollout farther than this "
    "from every stored state (one more expert call, counted); 0: only s0, as the paper"
)


def check_radius(radius: float) -> float:
    if not (np.isfinite(radius) and radius >= 0):
        raise ValueError(f"the exploration radius must be finite and >= 0 (0: off), got {radius!r}")
    return float(radius)


class PolicyReplay:
    """The policy's own rollout from s0 on a local copy of the plant, kept until another rollout is asked for.

    Asked again for the same s0 and the same policy (the same object over the same data), it answers with the
    rollout it ran: the episode driver, the explorer and the success check of one episode share one rollout.
    """

    def __init__(self, plant: Plant, horizon: int) -> None:
        self.plant = plant
        self.horizon = int(horizon)
        self._policy: NonparametricPolicy | None = None
        self._key: tuple[bytes, int, Robot | None] | None = None
        self._last: Rollout | None = None

    def rollout(self, initial_state: FloatArray, policy: NonparametricPolicy, robot: Robot | None = None) -> Rollout:
        key = (np.asarray(initial_state, dtype=np.float64).tobytes(), len(policy.dataset), robot)
        if self._last is None or self._policy is not policy or self._key != key:
            self._last = rollout(self.plant, policy.controller(), initial_state, self.horizon, robot)
            self._policy, self._key = policy, key
        return self._last


class RolloutExplorer:
    """Finds the first state of the policy's rollout from s0 farther than ``radius`` from every stored state."""

    def __init__(self, replay: PolicyReplay, radius: float) -> None:
        self.replay = replay
        self.radius = check_radius(radius)

    def state_to_ask(
        self, initial_state: FloatArray, policy: NonparametricPolicy, robot: Robot | None = None
    ) -> FloatArray | None:
        """The state to ask the expert from, or None (no data yet, or the rollout never leaves the data)."""
        if len(policy.dataset) == 0 or self.radius == 0:
            return None
        states = self.replay.rollout(initial_state, policy, robot).states
        from scipy.spatial import cKDTree  # here, not at the top: every node imports this module, few explore

        distance, _ = cKDTree(policy.dataset.states).query(states)
        far = np.flatnonzero(distance > self.radius)
        return None if len(far) == 0 else states[far[0]].copy()
