"""How far a robot's state lies from the certified policy's data, against a radius the run's own checks calibrate.

The certificate speaks of initial states drawn from rho; a state far from every data point is one the run
never checked near. npp-deploy reports (or stops at) a state outside the radius.
"""

from __future__ import annotations

import math

import numpy as np

from npp_ros.deployment.gate import Deployment
from npp_ros.policy.dataset import FloatArray


class Coverage:
    """How far a state lies from the certified policy's data (Euclidean, in the stored state space)."""

    def __init__(self, data_states: FloatArray, radius: float) -> None:
        from scipy.spatial import cKDTree  # on first use, not at npp-deploy's start

        self._tree = cKDTree(np.asarray(data_states, dtype=np.float64))
        self.radius = float(radius)

    @classmethod
    def of_deployment(cls, deployment: Deployment, radius: float = 0.0) -> Coverage:
        """``radius`` 0: the farthest a checked s0 lay from the policy's data (see :meth:`farthest_start`)."""
        coverage = cls(deployment.policy.dataset.states, math.inf)
        coverage.radius = radius if radius > 0 else coverage.farthest_start(deployment.checked_starts)
        return coverage

    def farthest_start(self, starts: FloatArray) -> float:
        """The largest distance from the data to an s0 ~ rho that the run checked and did not add to the policy's
        data (a certified run's streak is made of them): fresh draws from rho came that far from the data.
        Infinite when there is none (a run that never certified): then nothing calibrates a radius."""
        if len(starts) == 0:
            return math.inf
        return float(self._tree.query(starts)[0].max())

    def distance(self, state: FloatArray) -> float:
        return float(self._tree.query(state)[0])

    def covers(self, state: FloatArray, near: FloatArray | None = None) -> tuple[bool, float]:
        """Whether the state lies within the radius of the data, and a distance that decides it.

        ``near``: a data point (the one the policy picked). Within the radius of it the state is covered
        and no search is needed (the distance then is to ``near``, an upper bound on the nearest);
        only a state farther than that pays for the nearest-neighbour search, which can take
        milliseconds at 10^6 points in 12-D.
        """
        if near is not None:
            distance = float(np.sqrt(np.sum((state - near) ** 2)))
            if distance <= self.radius:
                return True, distance
        distance = self.distance(state)
        return distance <= self.radius, distance
