"""A run's set-up for a task and seed: its L, its config, its s0 stream, its loop.

npp-learn, npp-experiment and the supervisor node all build their run here (the supervisor with
the ROS parts in place of direct calls): :func:`build_config`, :func:`initial_state_fn` and
:func:`value_basis`, so the same seed gives the same numbers in process and through the graph.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from npp_ros.bounds import NonparametricPolicy
from npp_ros.certification import CheckedQuantity, Condition, StoppingRule
from npp_ros.dataset import FloatArray
from npp_ros.lipschitz import LipschitzCheck, LipschitzConstant, check_lipschitz, estimate_global
from npp_ros.loop import NPPLoop, Observer, RunConfig
from npp_ros.lqr import (
    PAPER_LIPSCHITZ,
    LQRExpert,
    LQRPlant,
    check_task,
    episode_rng,
    initial_state_diameter,
    rollout,
    sample_initial_state,
)
from npp_ros.storage import RunStore
from npp_ros.values import ValueBasis

LIPSCHITZ_CHOICES = ("analytic", "paper")


def resolve_lipschitz(task: str, choice: str | float, expert: LQRExpert) -> LipschitzConstant:
    """'analytic' (default, a true bound), 'paper' (50 / 200, not a bound) or a number (user)."""
    if choice == "analytic":
        return expert.analytic_lipschitz()
    if choice == "paper":
        return LipschitzConstant(PAPER_LIPSCHITZ[task], "paper", "the paper's choice (Section 5); not a bound on V*")
    try:
        value = float(choice)
    except ValueError:
        known = ", ".join(LIPSCHITZ_CHOICES)
        raise ValueError(f"the Lipschitz choice must be one of {known} or a number, got {choice!r}") from None
    return LipschitzConstant(value, "user", "given on the command line")


def build_config(
    task: str,
    seed: int,
    lipschitz: LipschitzConstant,
    epsilon: float,
    *,
    condition: Condition = "i",
    p: float = 0.9,
    delta: float = 0.1,
    horizon: int = 1000,
    gamma: float = 1.0,
    certify: CheckedQuantity = "rollout",
    rule: StoppingRule = "sequential",
) -> RunConfig:
    bodies, actuators = check_task(task)
    return RunConfig(
        task=task, seed=seed, state_dim=2 * bodies, action_dim=actuators, lipschitz=lipschitz,
        epsilon=epsilon, condition=condition, p=p, delta=delta, horizon=horizon, gamma=gamma,
        diameter=initial_state_diameter(), certify=certify, rule=rule,
    )  # fmt: skip


def initial_state_fn(task: str, seed: int) -> Callable[[int], FloatArray]:
    """s0 for episode e: its own seeded stream, so a resumed run replays the same states."""
    return lambda episode: sample_initial_state(task, episode_rng(seed, episode))


class PolicyRollouts:
    """Episode driver: the greedy policy drives the plant for H steps; returns the return."""

    def __init__(self, plant: LQRPlant, horizon: int) -> None:
        self.plant = plant
        self.horizon = horizon

    def run_episode(self, episode: int, initial_state: FloatArray, policy: NonparametricPolicy) -> float | None:
        if len(policy.dataset) == 0:
            return None
        return rollout(self.plant, policy.act, initial_state, self.horizon).total_return


def build_loop(
    config: RunConfig,
    expert: LQRExpert,
    *,
    store_path: Path | None = None,
    rollouts: bool = False,
    observers: Sequence[Observer] = (),
) -> NPPLoop:
    """The loop for ``config`` with this expert; the sound modes always let the policy drive."""
    store = RunStore.open_or_create(store_path, config.metadata()) if store_path is not None else None
    drive = rollouts or config.certify != "surrogate"
    driver = PolicyRollouts(LQRPlant(config.task, config.seed), config.horizon) if drive else None
    return NPPLoop(
        config,
        expert,
        initial_state_fn(config.task, config.seed),
        store=store,
        driver=driver,
        observers=observers,
        expert_value=expert.value,
        basis=value_basis(expert, config.lipschitz.value),
    )


def value_basis(expert: LQRExpert, lipschitz: float) -> ValueBasis:
    """The expert's value basis with Theorem 3.4's condition checked for its plant and this L."""
    holds, text = expert.theorem_34_condition(lipschitz)
    return replace(expert.value_basis(), theorem_34_holds=holds, theorem_34=text)


def lipschitz_checks(loop: NPPLoop, expert: LQRExpert, rollout_slope: float = 0.0) -> list[LipschitzCheck]:
    """Compare the L in use with every slope this run can compute or estimate (warns on shortfalls)."""
    slopes = [(expert.analytic_lipschitz().value, "analytic (expert trajectories from S0)")]
    if len(loop.dataset):
        slopes.append((float(np.max(expert.slope(loop.dataset.states))), "exact |P x| over the dataset"))
    if len(loop.dataset) >= 2:
        slopes.append((estimate_global(loop.dataset), "data-estimated (global)"))
    if rollout_slope:
        slopes.append((rollout_slope, "exact |P x| over the evaluation rollouts"))
    return [check_lipschitz(loop.config.lipschitz.value, slope, source) for slope, source in slopes]
