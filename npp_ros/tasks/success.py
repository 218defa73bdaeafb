"""When a task is done: a success criterion over the final stored states of an episode.

A certificate is relative to its expert: it says the policy does about as well as the expert, never that the
expert does the task. So every run measures both on the task's own criterion (npp_ros.run.loop): the expert on
its answers' stored states, the policy on its own rollouts from s0, and the certificate states the counts.

A :class:`SuccessCriterion` looks at the last ``steps`` stored states of an episode (or the last ``share`` of
them) and holds when its predicate holds on that block. An episode shorter than the criterion's ``steps`` is
judged on all the states it has: a criterion never looks past the start of an episode, so at a short horizon
it asks more of the whole episode, never less. The predicates here are small picklable classes (a task travels
to expert worker processes by name, but a criterion may be sent whole).

This module imports no other module of npp_ros.tasks: the Task contract (npp_ros.tasks.task) names it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from npp_ros.policy.dataset import FloatArray
from npp_ros.policy.feedback import wrap_angle


@dataclass(frozen=True)
class SuccessCriterion:
    """What "the task was done" means for one episode, in words and as a predicate over its final stored states.

    ``description`` says what holds ("the pole within 8 degrees of upright"); ``holds`` is that predicate over
    the final states (rows of stored states, oldest first); ``steps`` is how many final states it looks at, or
    ``share`` the part of the episode (at least one state); ``seconds`` is what ``steps`` is in the plant's
    time, for the words only.
    """

    description: str
    holds: Callable[[FloatArray], bool]
    steps: int = 0
    share: float = 0.0
    seconds: float | None = None

    def __post_init__(self) -> None:
        if not self.description:
            raise ValueError("a success criterion needs a description in words")
        if (self.steps > 0) == (self.share > 0):
            raise ValueError(f"a success criterion looks at a number of final steps or a share of the episode, "
                             f"exactly one of them; got steps {self.steps!r}, share {self.share!r}")  # fmt: skip
        if self.steps < 0 or not (0 <= self.share <= 1) or not math.isfinite(self.share):
            raise ValueError(f"steps must be >= 1 or share in (0, 1], got steps {self.steps!r}, share {self.share!r}")

    def window(self, length: int) -> int:
        """How many final states of an episode of ``length`` stored states it looks at (all of a shorter one)."""
        if length <= 0:
            return 0
        if self.steps:
            return min(length, self.steps)
        return max(1, min(length, math.ceil(self.share * length - 1e-9)))

    def met(self, states: ArrayLike) -> bool:
        """Whether an episode whose stored states are ``states`` (one row per step) met the criterion."""
        rows = np.asarray(states, dtype=np.float64)
        if rows.ndim != 2 or len(rows) == 0:
            return False
        return bool(self.holds(rows[len(rows) - self.window(len(rows)) :]))

    def describe(self) -> str:
        """The criterion in words, with the part of the episode it looks at."""
        if self.share:
            return f"{self.description} over the last {self.share:.0%} of the episode"
        seconds = f" ({self.seconds:g} s)" if self.seconds is not None else ""
        return f"{self.description} over the last {self.steps} steps{seconds}"


def steps_for(seconds: float, dt: float) -> int:
    """The control steps that make ``seconds`` at a control step of ``dt`` seconds (at least one)."""
    return max(1, round(seconds / dt))


@dataclass(frozen=True)
class UprightAngles:
    """Every link within ``degrees`` of upright (angle 0) in every state looked at.

    Each link is a tuple of state entries whose sum is its absolute angle: ``((0,),)`` a pendulum's pole,
    ``((0,), (0, 1))`` the acrobot's two links (the elbow angle is relative to the upper link).
    """

    links: tuple[tuple[int, ...], ...]
    degrees: float

    def __call__(self, states: FloatArray) -> bool:
        for link in self.links:
            angle = wrap_angle(np.sum(states[:, list(link)], axis=1))
            if np.degrees(np.max(np.abs(angle))) > self.degrees:
                return False
        return True


@dataclass(frozen=True)
class WithinBand:
    """The given state entries within [low, high] in every state looked at."""

    entries: tuple[int, ...]
    low: float
    high: float

    def __call__(self, states: FloatArray) -> bool:
        values = states[:, list(self.entries)]
        return bool(np.all((values >= self.low) & (values <= self.high)))
