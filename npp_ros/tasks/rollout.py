"""The generic rollout every task uses: a controller driven on a plant for H steps, one s0 or many in lockstep.

It knows only the :class:`~npp_ros.tasks.registry.Plant` protocol, so a new task's plant rolls out here unchanged.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from npp_ros.policy.dataset import FloatArray
from npp_ros.tasks.registry import Plant, check_horizon
from npp_ros.tasks.uncertainty import Robot, RobotEffects, as_robot


def episode_return(rewards: ArrayLike) -> float:
    """An episode's return from its per-step rewards: the one summation every rollout uses (numpy's
    pairwise sum), so a return earned through the ROS graph equals the in-process one bit for bit."""
    return float(np.asarray(rewards, dtype=np.float64).sum())


@dataclass(frozen=True)
class Rollout:
    states: FloatArray  # (T, n): s_0 .. s_{T-1}
    actions: FloatArray  # (T, m)
    rewards: FloatArray  # (T,)

    @property
    def total_return(self) -> float:
        return episode_return(self.rewards)


def rollout(
    plant: Plant,
    controller: Callable[[FloatArray], ArrayLike],
    initial_state: ArrayLike,
    horizon: int,
    robot: Robot | None = None,
) -> Rollout:
    """Roll ``controller(state) -> action`` out on the plant for ``horizon`` steps; with a ``robot``
    (npp_ros.tasks.uncertainty), on the plant made into that robot, which is nominal again afterwards.

    The stored states and actions are the true states and the commanded actions; the controller reads the
    robot's noisy states and the plant applies its delayed commands (the same :class:`RobotEffects` as the sim).
    """
    horizon = check_horizon(horizon)
    states = np.empty((horizon, plant.state_dim))
    actions = np.empty((horizon, plant.action_dim))
    rewards = np.empty(horizon)
    effects = None if robot is None else RobotEffects(robot, plant.action_dim)
    with as_robot(plant, robot):
        x = plant.reset(initial_state)
        for t in range(horizon):
            u = controller(x if effects is None else effects.observe(x))
            states[t], actions[t] = x, u
            rewards[t] = plant.step(u if effects is None else effects.command(np.asarray(u, dtype=np.float64)))
            x = plant.state()
    return Rollout(states, actions, rewards)


def rollout_batch(
    plant: Plant, controller: Callable[[FloatArray], FloatArray], initial_states: ArrayLike, horizon: int
) -> list[Rollout]:
    """Rollouts from many s0 in lockstep, one plant clone each; ``controller`` maps (B, n) -> (B, m).

    Gives the same numbers as :func:`rollout` one s0 at a time when the controller answers a
    batch row exactly as it answers that state alone (the NPP policy does, bit for bit); it
    only saves the per-step Python overhead of asking the controller B times.
    """
    horizon = check_horizon(horizon)
    starts = np.asarray(initial_states, dtype=np.float64)
    plants = [plant.clone() for _ in range(len(starts))]
    count = len(plants)
    states = np.empty((count, horizon, plant.state_dim))
    actions = np.empty((count, horizon, plant.action_dim))
    rewards = np.empty((count, horizon))
    x = np.array([p.reset(s0) for p, s0 in zip(plants, starts, strict=True)])
    for t in range(horizon):
        u = np.asarray(controller(x), dtype=np.float64).reshape(count, plant.action_dim)
        states[:, t], actions[:, t] = x, u
        for k, p in enumerate(plants):
            rewards[k, t] = p.step(u[k])
            x[k] = p.state()
    return [Rollout(states[k], actions[k], rewards[k]) for k in range(count)]
