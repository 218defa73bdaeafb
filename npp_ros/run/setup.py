"""A run's set-up for a task and seed: its L, its config, its s0 stream, its loop.

Everything task-specific comes from the task registry (npp_ros.tasks.registry): plant, expert, rho, L choices.

npp-learn, npp-experiment and the supervisor node all build their run here (the supervisor with
the ROS parts in place of direct calls): :func:`build_config`, :func:`initial_state_fn` and
:func:`value_basis`, so the same seed gives the same numbers in process and through the graph.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from npp_ros.certificate.certifier import DEFAULT_RULES, CertificationSpec, CheckedQuantity, Condition, StoppingRule
from npp_ros.certificate.values import ValueBasis
from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import Dataset, FloatArray
from npp_ros.policy.feedback import DEFAULT_POLICY, ControlSpace, PolicyKind, check_policy_kind
from npp_ros.policy.lipschitz import LipschitzCheck, LipschitzConstant, check_lipschitz, estimate_global
from npp_ros.run.explore import RolloutExplorer, check_radius
from npp_ros.run.loop import EpisodeDriver, NPPLoop, Observer, Oracle, RunConfig, make_policy
from npp_ros.run.records import RunMetadata
from npp_ros.run.store import RunStore
from npp_ros.tasks.registry import Expert, MeasuresValueSlope, Plant, control_space, get_task
from npp_ros.tasks.rollout import rollout


def resolve_lipschitz(task: str, choice: str | float, expert: Expert) -> LipschitzConstant:
    """'analytic' (a true bound, where the expert computes one), 'paper' (the paper's, not a bound) or a number."""
    return get_task(task).resolve_lipschitz(choice, expert)


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
    certify: CheckedQuantity | None = None,
    rule: StoppingRule | None = None,
    policy: PolicyKind = DEFAULT_POLICY,
    explore: float = 0.0,
) -> RunConfig:
    """The run's config; ``certify`` None is the task's default (rollout on lqr, oracle for optimizer experts),
    ``rule`` None the default rule of that checked quantity (DEFAULT_RULES), ``policy`` how the policy acts,
    ``explore`` > 0 the radius beyond which a failed check also asks where the policy went (npp_ros.run.explore).

    Refuses a bad combination (ValueError) when the run is defined, not episodes later.
    """
    definition = get_task(task)
    certify = certify or definition.default_certify
    spec = CertificationSpec(
        condition, epsilon, p, delta, lipschitz, definition.initial_state_diameter,
        certify=certify, rule=rule or DEFAULT_RULES[certify], policy=check_policy_kind(policy),
    )  # fmt: skip
    return RunConfig(
        task, seed, definition.state_dim, definition.action_dim, spec,
        horizon=horizon, gamma=gamma, plant_fingerprint=plant_fingerprint(task, seed), explore=check_radius(explore),
    )  # fmt: skip


def spec_of(metadata: RunMetadata, diameter: float | None) -> CertificationSpec:
    """The spec a run file records (its metadata), read back: what the deployment gate and a reader check against.
    Raises ValueError or TypeError when the recorded values are no spec (a hand-edited file)."""
    lipschitz = LipschitzConstant(float(metadata.lipschitz), str(metadata.lipschitz_source))
    return CertificationSpec(
        metadata.condition, metadata.epsilon, metadata.p, metadata.delta, lipschitz, diameter,  # type: ignore[arg-type]
        certify=metadata.certify, rule=metadata.rule, policy=metadata.policy,  # type: ignore[arg-type]
    )  # fmt: skip


@functools.lru_cache(maxsize=64)
def plant_fingerprint(task: str, seed: int) -> str:
    """The fingerprint of the task's plant for this seed: what a run file records of its data's plant."""
    return get_task(task).make_plant(seed).model_sha256()


@functools.lru_cache(maxsize=64)
def task_control_space(task: str, seed: int) -> ControlSpace:
    """How the task's states differ and how far its actuators reach, for this seed's plant (the feedback policy)."""
    return control_space(get_task(task).make_plant(seed))


def policy_for(data: Dataset, spec: CertificationSpec, task: str, seed: int) -> NonparametricPolicy:
    """The policy ``spec`` names over ``data`` for this task's plant: what a run's checks, its evaluations and a
    robot act with."""
    control = task_control_space(task, seed) if spec.policy == "feedback" else None
    return make_policy(data, spec, control)


def initial_state_fn(task: str, seed: int) -> Callable[[int], FloatArray]:
    """s0 for episode e: its own seeded stream, so a resumed run replays the same states."""
    spec = get_task(task)
    return lambda episode: spec.initial_state(seed, episode)


class PolicyRollouts:
    """Episode driver: the greedy policy drives the plant for H steps; returns the return."""

    def __init__(self, plant: Plant, horizon: int) -> None:
        self.plant = plant
        self.horizon = horizon

    def run_episode(self, episode: int, initial_state: FloatArray, policy: NonparametricPolicy) -> float | None:
        if len(policy.dataset) == 0:
            return None
        return rollout(self.plant, policy.act, initial_state, self.horizon).total_return


def build_loop(
    config: RunConfig,
    expert: Expert,
    *,
    store_path: Path | None = None,
    store: RunStore | None = None,
    rollouts: bool = False,
    observers: Sequence[Observer] = (),
    oracle: Oracle | None = None,
    driver: EpisodeDriver | None = None,
) -> NPPLoop:
    """The loop for ``config`` with this expert: every front end builds its run here, so a loop option is added once.

    In one process (npp-learn, npp-experiment) the expert answers directly and the policy drives a local copy of
    the plant (the sound modes always let it drive; ``rollouts`` in surrogate mode too). The supervisor node gives
    its own ``oracle`` (the expert service) and ``driver`` (the sim, or None when it does not let the policy
    drive) and the ``store`` it opened; the expert is then still the task's, for L, V(s0) and the value basis.
    """
    if store is None and store_path is not None:
        store = RunStore.open_or_create(store_path, config.metadata())
    task = get_task(config.task)
    if oracle is None:
        drive = rollouts or config.spec.certify != "surrogate"
        driver = PolicyRollouts(task.make_plant(config.seed), config.horizon) if drive else None
    return NPPLoop(
        config,
        oracle or expert,
        initial_state_fn(config.task, config.seed),
        store=store,
        driver=driver,
        observers=observers,
        expert_value=task.expert_value(expert),
        basis=value_basis(expert, config.spec.lipschitz.value),
        control=task_control_space(config.task, config.seed) if config.spec.policy == "feedback" else None,
        explorer=RolloutExplorer(task.make_plant(config.seed), config.horizon, config.explore)
        if config.explore
        else None,
    )


def value_basis(expert: Expert, lipschitz: float) -> ValueBasis:
    """The expert's value basis with Theorem 3.4's condition checked for its plant and this L."""
    holds, text = expert.theorem_34_condition(lipschitz)
    return replace(expert.value_basis(), theorem_34_holds=holds, theorem_34=text)


def lipschitz_checks(loop: NPPLoop, expert: Expert, rollout_slope: float = 0.0) -> list[LipschitzCheck]:
    """Compare the L in use with every slope this run can compute or estimate (warns on shortfalls)."""
    task = get_task(loop.config.task)
    slopes: list[tuple[float, str]] = []
    if "analytic" in task.lipschitz_choices():
        slopes.append((task.analytic_lipschitz(expert).value, "analytic (expert trajectories from S0)"))
    slope = task.value_slope(expert)
    if slope is not None and len(loop.dataset):
        slopes.append((float(np.max(slope(loop.dataset.states))), "exact |grad V| over the dataset"))
    if len(loop.dataset) >= 2:
        slopes.append((estimate_global(loop.dataset), "data-estimated (global)"))
    if rollout_slope and math.isfinite(rollout_slope):  # NaN: the expert knows no closed-form slope
        slopes.append((rollout_slope, "exact |grad V| over the evaluation rollouts"))
    if isinstance(expert, MeasuresValueSlope) and expert.requests:
        what = f"optimizer's own (max |W_x| of its backward pass over {expert.requests} requests; a floor)"
        slopes.append((expert.slope_floor(), what))
    return [check_lipschitz(loop.spec.lipschitz.value, slope, source) for slope, source in slopes]
