"""A run's settings, typed and declared once, and their resolution against the task into what the run needs.

Every door to a run (npp-learn, npp-run and its supervisor, npp-experiment, ``npp_ros.learn``, the graph client)
takes a :class:`RunRequest`: each field carries its one help text and its kind (how a command line and a ROS
parameter spell it), and the request checks its values with the core's own checks when it is made, before any
task is known. None is "the task's value" (its epsilon, its L choice, its checked quantity, its horizon, its
expert's options). :func:`resolve_run` turns a request into the expert options, the expert, epsilon, L and the
RunConfig, the one recipe every door runs; ``build_config`` and ``build_loop`` stay the layer below it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import Field, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from npp_ros.certificate.certifier import (
    CERTIFY_MODES,
    CONDITIONS,
    DEFAULT_RULES,
    STOPPING_RULES,
    SUCCESS_EPSILON,
    CheckedQuantity,
    Condition,
    StoppingRule,
    check_spec_choices,
)
from npp_ros.certificate.choices import LIPSCHITZ_CHOICES, LIPSCHITZ_HELP, check_gamma, parse_lipschitz
from npp_ros.policy.feedback import POLICY_HELP, POLICY_KINDS, PolicyKind
from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.run import defaults
from npp_ros.run.explore import EXPLORE_HELP, check_radius
from npp_ros.run.loop import RunConfig
from npp_ros.run.nominal_plan import DEFAULT_EXPERT_MODEL, EXPERT_MODEL_HELP, EXPERT_MODELS, check_expert_model
from npp_ros.run.policy_lipschitz import POLICY_LIPSCHITZ_HELP, POLICY_LIPSCHITZ_MODES, check_policy_lipschitz
from npp_ros.run.setup import build_config, check_uncertainty, resolve_lipschitz
from npp_ros.tasks.registry import Expert, ExpertOptions, Task, by_task, check_horizon, get_task
from npp_ros.tasks.uncertainty import UNCERTAINTY_HELP
from npp_ros.trajopt.expert import STOP_HELP, STOP_MODES, TIME_BUDGET_HELP, VALUE_MODES, check_stop
from npp_ros.trajopt.ilqr import check_time_budget

TASK_HELP = "a task: a registered name (see --list-tasks; plug-ins too) or a task file (path ending in .toml)"
PLANT_FIELDS = ("task", "seed", "horizon")  # on the graph the sim's plant names these; the supervisor learns them
EXPERT_FIELDS = ("gamma", "time_budget", "expert_stop", "values", "max_iterations")  # what the expert is built with

# A setting's kind: how a command line parses it and how a ROS parameter holds it.
TASK, INDEX, COUNT, NUMBER, LIPSCHITZ, CHOICE = "task", "index", "count", "number", "lipschitz", "choice"


@dataclass(frozen=True)
class Setting:
    """What a request field means and how it is spelled: ``--name-with-dashes`` on a command line, ``name`` as a
    ROS parameter (the text ``task`` where the field is None). ``help`` is a callable where the text lists every
    task's value, so that importing the request loads no task."""

    help: str | Callable[[], str]
    kind: str
    choices: tuple[str, ...] = ()
    metavar: str | None = None
    low: float | None = None  # inclusive bounds of a ROS parameter's range (the request checks the exact ones)
    high: float | None = None

    def text(self) -> str:
        return self.help() if callable(self.help) else self.help


def spelled(help: str | Callable[[], str], kind: str, **how: Any) -> dict[str, Setting]:
    """A request field's metadata: its help and how it is spelled."""
    return {"setting": Setting(help, kind, **how)}


def _epsilon_help() -> str:
    return (
        f"target gap, in the task's return; default: the paper's ({by_task('paper_epsilon')}) or a task file's key "
        "epsilon (a task with neither needs this option)"
    )


def _lipschitz_help() -> str:
    return (
        f"L: {LIPSCHITZ_HELP}; paper is {by_task('paper_lipschitz')}. Default: analytic where the task has it, else "
        "a task file's key lipschitz (data when the file gives none), else paper"
    )


def _certify_help() -> str:
    return (
        "what each episode checks: rollout (V_ub + tail - the policy's own return; sound when L bounds the value's "
        "slope), oracle (the expert's return - the policy's; the check needs no L, though the policy chooses with "
        "one; relative to the expert), surrogate (the paper's V_ub - V_lb; rests on Theorem 3.4) or success (the "
        f"task's success criterion). Default: the task's ({by_task('default_certify')}; oracle where the expert is "
        "suboptimal; a task file's key certify)"
    )


def _policy_help() -> str:
    return f"{POLICY_HELP}, unless the task names another (a task file's key policy)"


RULE_HELP = (
    "when to stop: sequential (a streak of passes per policy, valid however often it is checked), mixture (a 20-pass "
    "screen, then a failure-tolerant mixture test of the frozen policy, also valid) or paper (the one-shot test of "
    "Theorem 4.1, to reproduce the paper); default: the checked quantity's "
    f"({', '.join(f'{mode} {rule}' for mode, rule in DEFAULT_RULES.items())})"
)
VALUES_HELP = (
    "what an iLQR expert stores as Q_t: window (the H-step return of s_t: one value per state) or return-to-go "
    "(depends on the time left, so rollout mode refuses it); default: a task file's [expert] values, else window"
)


@dataclass(frozen=True)
class RunRequest:
    """Every setting of a run; None is the task's value. Refuses a bad value (ValueError naming the field) when
    made, with the checks the run's own types use, so that a door refuses it before anything starts."""

    task: str = field(default=defaults.TASK, metadata=spelled(TASK_HELP, TASK))
    seed: int = field(
        default=defaults.SEED, metadata=spelled("task seed: the plant's and the initial-state stream's", INDEX)
    )
    epsilon: float | None = field(default=None, metadata=spelled(_epsilon_help, NUMBER))
    lipschitz: str | LipschitzConstant | None = field(
        default=None, metadata=spelled(_lipschitz_help, LIPSCHITZ, choices=LIPSCHITZ_CHOICES)
    )
    certify: CheckedQuantity | None = field(
        default=None, metadata=spelled(_certify_help, CHOICE, choices=CERTIFY_MODES)
    )
    rule: StoppingRule | None = field(default=None, metadata=spelled(RULE_HELP, CHOICE, choices=STOPPING_RULES))
    policy: PolicyKind | None = field(default=None, metadata=spelled(_policy_help, CHOICE, choices=POLICY_KINDS))
    policy_lipschitz: str = field(
        default=defaults.POLICY_LIPSCHITZ,
        metadata=spelled(POLICY_LIPSCHITZ_HELP, CHOICE, choices=POLICY_LIPSCHITZ_MODES),
    )
    condition: Condition = field(
        default=defaults.CONDITION, metadata=spelled("Theorem 4.1 condition", CHOICE, choices=CONDITIONS)
    )
    p: float = field(
        default=defaults.P,
        metadata=spelled("condition (i): share of initial states within epsilon, in (0, 1)", NUMBER, low=0.0, high=1.0),
    )
    delta: float = field(
        default=defaults.DELTA,
        metadata=spelled("the claim holds with probability >= 1 - delta, in (0, 1)", NUMBER, low=0.0, high=1.0),
    )
    horizon: int | None = field(
        default=None, metadata=spelled("episode length H; default: the task's (1000; a task file's key horizon)", COUNT)
    )
    gamma: float = field(
        default=defaults.GAMMA,
        metadata=spelled("discount, in (0, 1]; 1 = undiscounted H-step values", NUMBER, low=0.0, high=1.0),
    )
    explore: float = field(default=defaults.EXPLORE, metadata=spelled(EXPLORE_HELP, NUMBER, metavar="RADIUS", low=0.0))
    uncertainty: float = field(
        default=defaults.UNCERTAINTY, metadata=spelled(UNCERTAINTY_HELP, NUMBER, metavar="FACTOR", low=0.0)
    )
    expert_model: str = field(
        default=DEFAULT_EXPERT_MODEL, metadata=spelled(EXPERT_MODEL_HELP, CHOICE, choices=EXPERT_MODELS)
    )
    max_episodes: int = field(
        default=defaults.MAX_EPISODES, metadata=spelled("stop uncertified after this many episodes", COUNT, low=1)
    )
    time_budget: float | None = field(default=None, metadata=spelled(TIME_BUDGET_HELP, NUMBER))
    expert_stop: str | None = field(
        default=None, metadata=spelled(f"{STOP_HELP}; default: the task's", CHOICE, choices=STOP_MODES)
    )
    values: str | None = field(default=None, metadata=spelled(VALUES_HELP, CHOICE, choices=VALUE_MODES))
    max_iterations: int | None = field(
        default=None, metadata=spelled("iLQR iterations per expert request; default: the task's", COUNT)
    )

    def __post_init__(self) -> None:
        if self.lipschitz is not None and not isinstance(self.lipschitz, LipschitzConstant):
            object.__setattr__(self, "lipschitz", parse_lipschitz(self.lipschitz))
        check_spec_choices(
            self.condition, self.p, self.delta, self.policy, epsilon=self.epsilon, certify=self.certify, rule=self.rule
        )
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed!r}")
        if self.horizon is not None:
            check_horizon(self.horizon)
        check_gamma(self.gamma)
        check_radius(self.explore)
        check_policy_lipschitz(self.policy_lipschitz, self.certify)
        check_uncertainty(self.uncertainty)
        check_expert_model(self.expert_model, self.uncertainty)
        if self.max_episodes < 1:
            raise ValueError(f"max_episodes must be >= 1, got {self.max_episodes!r}")
        if self.time_budget is not None:
            check_time_budget(self.time_budget)
        if self.expert_stop is not None:
            check_stop(self.expert_stop)
        if self.values is not None and self.values not in VALUE_MODES:
            raise ValueError(f"values must be one of {', '.join(VALUE_MODES)}; got {self.values!r}")
        if self.max_iterations is not None and self.max_iterations < 1:
            raise ValueError(f"max_iterations must be >= 1, got {self.max_iterations!r}")

    @classmethod
    def of(cls, request: RunRequest | None = None, **given: Any) -> RunRequest:
        """A request from another one and fields over it; an unknown field is a TypeError naming it."""
        unknown = sorted(set(given) - set(FIELD_NAMES))
        if unknown:
            raise TypeError(f"unknown run setting {', '.join(unknown)}; known: {', '.join(FIELD_NAMES)}")
        return replace(request, **given) if request is not None else cls(**given)

    def expert_options(
        self, *, kind: str | None = None, control_weight: float | None = None, threads: int | None = None
    ) -> ExpertOptions:
        """The options the run's expert is built with: the request's, and what a door adds that is no run setting
        (an experiment's expert kind and its detuning, a process's derivative threads)."""
        extra = {} if control_weight is None else {"control_weight": control_weight}
        return ExpertOptions(
            kind=kind, gamma=self.gamma, time_budget=self.time_budget, max_iterations=self.max_iterations,
            stop=self.expert_stop, values=self.values, threads=threads, **extra,
        )  # fmt: skip

    def changed(self) -> dict[str, Any]:
        """The fields that differ from their defaults, by name."""
        return {f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) != f.default}


FIELD_NAMES: tuple[str, ...] = tuple(f.name for f in fields(RunRequest))


def request_fields(names: tuple[str, ...] | None = None) -> Iterator[tuple[Field[Any], Setting]]:
    """The request's fields (those named, in the request's order) with how each is spelled."""
    for f in fields(RunRequest):
        if names is None or f.name in names:
            yield f, f.metadata["setting"]


@dataclass(frozen=True)
class ResolvedRun:
    """A request resolved against its task: everything a run needs besides its store and its observers."""

    request: RunRequest  # with the task's horizon filled in
    options: ExpertOptions
    expert: Expert
    epsilon: float
    lipschitz: LipschitzConstant
    config: RunConfig


def success_lipschitz_choice(task: Task) -> str | float:
    """The L a success claim's policy acts with when the request names none: the task's default where it has one,
    else 'data' (from the run's first answers). The claim rests on no L, so no task refuses one for want of it."""
    try:
        return task.default_lipschitz_choice()
    except ValueError:
        return "data"


def resolve_run(
    request: RunRequest,
    *,
    run_file: Path | None = None,
    kind: str | None = None,
    control_weight: float | None = None,
    threads: int | None = None,
) -> ResolvedRun:
    """The expert options, the expert, epsilon, L and the RunConfig of a request, as every door builds its run.

    ``run_file``: where the run is stored (a 'data' L already recorded there is read back). ``kind``,
    ``control_weight`` and ``threads`` are the expert's besides the request's options. Raises ValueError for what
    the task refuses (no epsilon of its own, an L it has not, options its expert cannot honour).
    """
    definition = get_task(request.task)
    if request.horizon is None:
        request = replace(request, horizon=definition.default_horizon)
    assert request.horizon is not None
    certify = request.certify or definition.default_certify
    if certify == "success" and request.epsilon is None and definition.paper_epsilon is None:
        epsilon = SUCCESS_EPSILON  # the success claim bounds no gap: the spec's epsilon is never read
    else:
        epsilon = definition.epsilon(request.epsilon)
    options = request.expert_options(kind=kind, control_weight=control_weight, threads=threads)
    expert = definition.make_expert(request.seed, request.horizon, options)
    choice = request.lipschitz.value if isinstance(request.lipschitz, LipschitzConstant) else request.lipschitz
    if choice is None and certify == "success":
        choice = success_lipschitz_choice(definition)
    lipschitz = resolve_lipschitz(
        request.task, choice, expert, seed=request.seed, horizon=request.horizon, run_file=run_file
    )
    config = build_config(
        request.task, request.seed, lipschitz, epsilon,
        condition=request.condition, p=request.p, delta=request.delta, horizon=request.horizon, gamma=request.gamma,
        certify=request.certify, rule=request.rule, policy=request.policy or definition.default_policy,
        explore=request.explore,
        uncertainty=request.uncertainty, expert_model=request.expert_model, options=options, expert=expert,
        policy_lipschitz=request.policy_lipschitz,
    )  # fmt: skip
    return ResolvedRun(request, options, expert, epsilon, lipschitz, config)
