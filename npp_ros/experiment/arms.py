"""Arms (task x expert x L x certification x how the policy acts x the set of robots) and the settings every (arm,
seed) shares."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import product

from npp_ros.certificate.certifier import CERTIFY_MODES, DEFAULT_RULES, STOPPING_RULES
from npp_ros.policy.dataset import FloatArray
from npp_ros.policy.feedback import PAPER_POLICY, check_policy_kind
from npp_ros.run import defaults
from npp_ros.run.held_out import held_out_states
from npp_ros.run.nominal_plan import DEFAULT_EXPERT_MODEL, check_expert_model
from npp_ros.run.policy_lipschitz import check_policy_lipschitz
from npp_ros.run.request import RunRequest
from npp_ros.run.setup import check_uncertainty
from npp_ros.tasks.registry import Expert, ExpertOptions, OptimizerTask, get_task
from npp_ros.tasks.sources import short_name
from npp_ros.tasks.task import DEFAULT_HORIZON

EXPERTS = ("optimal", "detuned", "ilqr")  # every task's expert kinds (Task.experts)
LIPSCHITZ_SETTINGS = ("paper", "analytic", "data")  # named L settings (npp_ros.certificate.choices)
DEFAULT_CHECKPOINTS = (10, 25, 50, 100, 250, 500, 1000)
DETUNED_CONTROL_WEIGHT = 0.1
# rng stream for the checkpoint evaluations' s0; the run's own s0 use [seed, episode], and the certificate's held-out
# s0 npp_ros.run.held_out.EXPERIMENT_HELD_OUT_STREAM, the next stream (declared there beside npp-learn's)
EVALUATION_STREAM = 1 << 30
EVALUATION_CHUNK = 25  # rollouts stepped in lockstep (batched policy queries)
HELD_OUT = 1000  # fresh s0 on which every certificate is checked


@dataclass(frozen=True)
class Arm:
    """One line of the results table, over seeds."""

    task: str
    expert: str  # "optimal" or "detuned"
    lipschitz: str  # "paper", "analytic", "data" or a number
    certify: str = "surrogate"  # the paper's checked quantity ...
    rule: str = "paper"  # ... and its stopping rule, unless the arm says otherwise
    policy: str = PAPER_POLICY  # how the policy acts at its chosen point (npp_ros.policy.feedback)
    explore: float = defaults.EXPLORE  # > 0: a failed check also asks where the policy went (npp_ros.run.explore)
    policy_lipschitz: str = defaults.POLICY_LIPSCHITZ  # the claim's L, or one chosen from the run's data (select)
    uncertainty: float = defaults.UNCERTAINTY  # > 0: each episode on a robot of the task's set widened by this
    expert_model: str = DEFAULT_EXPERT_MODEL  # on a set: what the expert plans on (npp_ros.run.nominal_plan)

    def __post_init__(self) -> None:
        check_policy_kind(self.policy)
        check_policy_lipschitz(self.policy_lipschitz, self.certify)
        check_expert_model(self.expert_model, check_uncertainty(self.uncertainty))
        if self.certify not in CERTIFY_MODES:
            raise ValueError(f"unknown certification mode {self.certify!r}; known: {', '.join(CERTIFY_MODES)}")
        if self.rule not in STOPPING_RULES:
            raise ValueError(f"unknown stopping rule {self.rule!r}; known: {', '.join(STOPPING_RULES)}")
        experts = get_task(self.task).experts
        if self.expert not in experts:
            raise ValueError(f"unknown expert {self.expert!r} for {self.task}; it has: {', '.join(experts)}")
        if self.lipschitz not in LIPSCHITZ_SETTINGS:
            try:
                value = float(self.lipschitz)
            except ValueError:
                value = math.nan
            if not (math.isfinite(value) and value > 0):
                known = ", ".join(LIPSCHITZ_SETTINGS)
                raise ValueError(f"L setting must be one of {known} or a number > 0, got {self.lipschitz!r}")

    @property
    def paper_certification(self) -> bool:
        return (self.certify, self.rule) == ("surrogate", "paper")

    @property
    def name(self) -> str:
        base = f"{short_name(self.task)}-{self.expert}-L{self.lipschitz}"  # a task file's path is no folder name
        base = base if self.paper_certification else f"{base}-{self.certify}-{self.rule}"
        base = base if self.policy == PAPER_POLICY else f"{base}-{self.policy}"
        base = base if not self.explore else f"{base}-explore{self.explore:g}"
        base = base if self.policy_lipschitz == "claim" else f"{base}-policyL{self.policy_lipschitz}"
        base = base if not self.uncertainty else f"{base}-u{self.uncertainty:g}"  # the exact model keeps its names
        return base if self.expert_model == DEFAULT_EXPERT_MODEL else f"{base}-{self.expert_model}-expert"

    @property
    def acts(self) -> str:
        """How the arm's policy acts and on what, as a suffix of its label ('' for the paper's open-loop policy on
        the exact model): the table tells arms apart by it."""
        acts = "" if self.policy == PAPER_POLICY else f", {self.policy} policy"
        acts += f", exploring beyond {self.explore:g}" if self.explore else ""
        acts += ", the policy's L selected from its data" if self.policy_lipschitz == "select" else ""
        acts += f", robots of uncertainty {self.uncertainty:g}" if self.uncertainty else ""
        return acts + (f", the expert planning on the {self.expert_model} model"
                       if self.expert_model != DEFAULT_EXPERT_MODEL else "")  # fmt: skip

    @property
    def label(self) -> str:
        expert = f"{self.expert} expert"
        how = "" if self.paper_certification else f", certify={self.certify} ({self.rule})"
        return f"{self.task}, {expert}, {self.lipschitz} L{how}{self.acts}"


@dataclass(frozen=True)
class ExperimentSettings:
    """What every (arm, seed) shares; defaults follow the paper."""

    max_episodes: dict[str, int]
    evaluations: int = 100  # N
    checkpoints: tuple[int, ...] = DEFAULT_CHECKPOINTS
    horizon: int = DEFAULT_HORIZON  # npp-experiment's default: the tasks' own (a task file's key horizon)
    p: float = defaults.P
    delta: float = defaults.DELTA
    epsilon: dict[str, float] | None = None
    control_weight: float = DETUNED_CONTROL_WEIGHT
    time_budget: float | None = None  # seconds per expert request (optimizer experts); None = the task's
    stop: str | None = None  # what ends an optimizer expert's request ("iterations" or "time"); None = the task's
    held_out: int = HELD_OUT  # fresh s0 on which each certificate is checked
    condition: str = defaults.CONDITION  # Theorem 4.1's condition every run certifies
    gamma: float = 1.0  # the discount of every run's values
    values: str | None = None  # what an optimizer expert stores as Q_t (window, return-to-go); None = the task's
    max_iterations: int | None = None  # an optimizer expert's iterations per request; None = the task's

    def epsilon_for(self, task: str) -> float:
        return get_task(task).epsilon((self.epsilon or {}).get(task))

    def checkpoints_for(self, task: str) -> list[int]:
        budget = self.max_episodes[task]
        return sorted({c for c in self.checkpoints if 0 < c <= budget} | {budget})


def default_lipschitz_settings(task: str) -> tuple[str, ...]:
    """The L settings a task runs with when none are asked for: the paper's and the analytic L side by side where
    the task has them (the lqr tasks: both), else its own default (a task file's key lipschitz: a number or data)."""
    definition = get_task(task)
    named = tuple(s for s in ("paper", "analytic") if s in definition.lipschitz_choices())
    if named and definition.own_lipschitz is None:
        return named
    choice = definition.default_lipschitz_choice()
    return (choice if isinstance(choice, str) else f"{choice:g}",)


def default_arms(
    tasks: Sequence[str],
    lipschitz: Sequence[str] | None,
    experts: Sequence[str] | None,
    certify: Sequence[str] | None = ("paper",),
    rules: Sequence[str] | None = None,
    policies: Sequence[str] = (PAPER_POLICY,),
    explore: Sequence[float] = (0.0,),
    policy_lipschitz: Sequence[str] = ("claim",),
    uncertainty: Sequence[float] = (0.0,),
    expert_models: Sequence[str] = (DEFAULT_EXPERT_MODEL,),
) -> list[Arm]:
    """Each task with the experts, L settings and modes it offers among those asked for.

    ``experts`` None: every expert of each task. ``lipschitz`` None: each task's own
    (:func:`default_lipschitz_settings`). A named L setting a task cannot resolve is left
    out for it (no 'analytic' for the pendulum), and the detuned expert is not run with the paper's
    L: the paper gives none for it. ``certify`` lists "paper" (the surrogate gap under the paper's
    one-shot rule) and sound modes (rollout, oracle, surrogate) under the sequential rule; None is
    "paper" for a task whose expert is optimal and the task's default mode otherwise. ``rules``
    lists the rules the sound modes run under, side by side; None is each mode's default rule.
    ``policies`` lists how the policy acts, ``explore`` the exploration radii and ``policy_lipschitz`` the policy's
    L (the claim's, selected), side by side (same seeds, same s0 streams); a surrogate arm takes the claim's only.
    ``uncertainty`` lists the sets of robots (0: the exact model) and ``expert_models`` what the expert plans on
    there, side by side; the exact model runs with the default expert model only (another changes nothing there)
    unless no set is asked for, where the arm refuses it with its reason.
    """
    on_a_set = any(factor > 0 for factor in uncertainty)
    robots = [(factor, model) for factor, model in product(uncertainty, expert_models)
              if factor > 0 or model == DEFAULT_EXPERT_MODEL or not on_a_set]  # fmt: skip
    arms = []
    for task in tasks:
        spec = get_task(task)
        modes = certify or (("paper",) if spec.optimal_expert else (spec.default_certify,))
        for expert in spec.experts if experts is None else [e for e in experts if e in spec.experts]:
            for setting in default_lipschitz_settings(task) if lipschitz is None else lipschitz:
                if setting in LIPSCHITZ_SETTINGS and setting not in (*spec.lipschitz_choices(), "data"):
                    continue
                if expert == "detuned" and setting == "paper":
                    continue
                for mode, policy, radius, own, (factor, model) in product(
                    modes, policies, explore, policy_lipschitz, robots
                ):
                    if own != "claim" and mode in ("paper", "surrogate"):
                        continue  # the surrogate gap speaks of the policy greedy on the claim's L
                    if mode == "paper":
                        arms.append(Arm(task, expert, setting, policy=policy, explore=radius, uncertainty=factor,
                                        expert_model=model))  # fmt: skip
                        continue
                    chosen = rules or (DEFAULT_RULES[mode],)
                    arms += [Arm(task, expert, setting, mode, rule, policy, radius, own, factor, model)
                             for rule in chosen]  # fmt: skip
    return arms


def arm_request(arm: Arm, seed: int, settings: ExperimentSettings) -> RunRequest:
    """The run request of one (arm, seed): what npp-learn would be asked for the same run. Refuses a bad value
    (ValueError naming the field), as the request does."""
    optimizer = isinstance(get_task(arm.task), OptimizerTask)  # closed-form experts take no optimizer options
    return RunRequest(
        task=arm.task, seed=seed, epsilon=(settings.epsilon or {}).get(arm.task), lipschitz=arm.lipschitz,
        certify=arm.certify, rule=arm.rule, policy=arm.policy, explore=arm.explore,  # type: ignore[arg-type]
        policy_lipschitz=arm.policy_lipschitz, uncertainty=arm.uncertainty, expert_model=arm.expert_model,
        condition=settings.condition, gamma=settings.gamma,  # type: ignore[arg-type]
        p=settings.p, delta=settings.delta, horizon=settings.horizon, max_episodes=settings.max_episodes[arm.task],
        time_budget=settings.time_budget if optimizer else None, expert_stop=settings.stop if optimizer else None,
        values=settings.values if optimizer else None, max_iterations=settings.max_iterations if optimizer else None,
    )  # fmt: skip


def expert_options(arm: Arm, settings: ExperimentSettings) -> ExpertOptions:
    """The options of an arm's data expert: what, with the task and seed, decides its answers."""
    request = arm_request(arm, 0, settings)
    return request.expert_options(kind=arm.expert, control_weight=settings.control_weight)


def make_expert(arm: Arm, seed: int, settings: ExperimentSettings) -> Expert:
    return get_task(arm.task).make_expert(seed, settings.horizon, expert_options(arm, settings))


def evaluation_states(task: str, seed: int, count: int) -> FloatArray:
    """The fixed N initial states every checkpoint of a seed is evaluated on (common random numbers), drawn as
    held-out s0 are, on a stream of their own."""
    return held_out_states(task, seed, count, EVALUATION_STREAM)
