"""Whether an expert's answer is what the certificate may rest on: checked against the supervisor's own plant.

An expert may be any process (README, "Experts from any process"), so the supervisor trusts no
answer it has not checked. It replays the answer's actions from s0 on its own copy of the plant
and refuses, with the reason, an answer that

- has the wrong dimensions (state or action entries, steps other than the horizon asked for);
- holds a value that is not finite (NaN as ``expert_return`` means "not known", and is allowed);
- does not start at s0, or whose states are not where its actions lead on this plant;
- reports a return other than the replayed return of its actions;
- holds values that contradict the rewards along its own trajectory. The value convention
  (README, "Value convention"): ``values[t]`` is the expert's H-step value of s_t, a
  window of H rewards from s_t, which the stationary lqr values H - J*(s_t) also are. So
  (a) Q_0 lies within [R - tail(s0), R], R the replayed H-step return and tail(s0) >= V_H(s0) - V(s0)
  the task's bound (0 where Q_0 is the return itself), and (b) the reward leaving the window,
  r_t - (Q_t - Q_{t+1}) = r_{t+H}, lies in the task's reward range, where the task states one.

Tolerances are for rounding only: an expert whose own model of the plant differs passes no check.
The check lives with the tasks because what a right answer is follows from the task alone: its plant, its
reward range and the value convention every expert fills in (task.py). In one process the task's own expert
answers, and nothing checks it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from npp_ros.policy.dataset import FloatArray, Trajectory
from npp_ros.tasks.registry import Plant

RELATIVE_TOLERANCE = 1e-6  # of the magnitudes compared: rounding, never a modelling difference


class AnswerError(ValueError):
    """An expert answer the certificate cannot rest on; the message says which check it fails."""


def _close(a: FloatArray, b: FloatArray, scale: float) -> FloatArray:
    """Entrywise agreement within the tolerance; angles may differ by whole turns (wrapped at the seam)."""
    diff = np.abs(a - b)
    turns = np.abs(diff - 2 * math.pi * np.round(diff / (2 * math.pi)))
    return np.minimum(diff, turns) <= RELATIVE_TOLERANCE * scale


@dataclass
class AnswerCheck:
    """The supervisor's checks of an expert answer for one plant and horizon (module docstring)."""

    plant: Plant
    horizon: int
    tail: Callable[[FloatArray], float] | None = None  # tail(s0) >= V_H(s0) - V(s0); None: values are returns
    reward_range: tuple[float, float] | None = None  # where the task states one

    def __call__(self, answer: Trajectory, initial_state: FloatArray) -> None:
        """Raise AnswerError naming the first check ``answer`` fails for a request from ``initial_state``."""
        n, m = self.plant.state_dim, self.plant.action_dim
        states, actions, values = answer.states, answer.actions, answer.values
        if states.shape[1] != n or actions.shape[1] != m:
            raise AnswerError(
                f"wrong dimensions: {states.shape[1]} state and {actions.shape[1]} action entries per step, "
                f"the plant has {n} and {m}"
            )
        if len(values) != self.horizon:
            raise AnswerError(f"wrong length: {len(values)} steps, the request asked for {self.horizon}")
        if answer.expert_return is not None and not math.isfinite(answer.expert_return):
            raise AnswerError(f"expert_return is {answer.expert_return}; it must be finite (or NaN: not known)")
        start = self.plant.reset(initial_state)
        scale = 1.0 + float(np.max(np.abs(states)))
        if not _close(states[0], start, scale).all():
            raise AnswerError(f"it does not start at the requested state: states[0] = {states[0]}, asked {start}")
        rewards = np.empty(self.horizon)
        for t in range(self.horizon):
            if t and not _close(states[t], self.plant.state(), scale).all():
                raise AnswerError(
                    f"states[{t}] = {states[t]} is not where its actions lead on this plant ({self.plant.state()})"
                )
            rewards[t] = self.plant.step(actions[t])
        self._check_values(answer, rewards, initial_state)

    def _check_values(self, answer: Trajectory, rewards: FloatArray, initial_state: FloatArray) -> None:
        values = answer.values
        replayed = float(rewards.sum())
        slack = RELATIVE_TOLERANCE * (1.0 + float(np.max(np.abs(values))) + float(np.sum(np.abs(rewards))))
        if answer.expert_return is not None and abs(answer.expert_return - replayed) > slack:
            raise AnswerError(
                f"expert_return {answer.expert_return:.9g} is not its trajectory's return {replayed:.9g} "
                "(its actions replayed on this plant)"
            )
        tail = 0.0 if self.tail is None else float(self.tail(initial_state))
        if not replayed - tail - slack <= values[0] <= replayed + slack:
            raise AnswerError(
                f"values[0] = {values[0]:.9g} contradicts its own trajectory: its actions earn {replayed:.9g} over "
                f"{self.horizon} steps, so the H-step value at s0 lies in [{replayed - tail:.9g}, {replayed:.9g}]"
            )
        if self.reward_range is None or len(values) < 2:
            return
        low, high = self.reward_range
        leaving = rewards[:-1] - (values[:-1] - values[1:])  # r_{t+H}, the reward that leaves the window
        outside = np.flatnonzero((leaving < low - slack) | (leaving > high + slack))
        if len(outside):
            t = int(outside[0])
            raise AnswerError(
                f"values[{t}] - values[{t + 1}] = {values[t] - values[t + 1]:.9g} contradicts the reward "
                f"{rewards[t]:.9g} of step {t}: the reward leaving the H-step window would be {leaving[t]:.9g}, "
                f"outside the task's range [{low:g}, {high:g}] ({len(outside)} steps like it)"
            )
