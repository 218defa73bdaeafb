"""What a task is: its plant, its expert, how s0 ~ rho is drawn, and what a certificate needs to know.

Every source of tasks fills in this contract: npp_ros's own task modules, plug-in packages and task
files. :class:`Task` is one task; :class:`OptimizerTask` fills it in for an expert built on the iLQR
optimizer (:class:`~npp_ros.trajopt.expert.OptimizingExpert`). Which tasks exist, and the lookup every
command and node uses, is npp_ros.tasks.registry; of npp_ros.tasks this module imports only the success
criterion's type and the uncertainty set's (npp_ros.tasks.success and npp_ros.tasks.uncertainty, which import
none of them).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike

from npp_ros.certificate.certifier import CheckedQuantity
from npp_ros.certificate.choices import EPSILON_FLAG, LIPSCHITZ_CHOICES, LIPSCHITZ_FLAG
from npp_ros.certificate.values import ValueBasis
from npp_ros.policy.dataset import FloatArray, Trajectory
from npp_ros.policy.feedback import DEFAULT_POLICY, ControlSpace, PolicyKind
from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.tasks.success import SuccessCriterion
from npp_ros.tasks.uncertainty import EXACT, Robot, UncertaintySet, as_robot
from npp_ros.trajopt.expert import DEFAULT_STOP, DEFAULT_VALUES, OptimizingExpert

MAX_HORIZON = 100_000
DEFAULT_HORIZON = 1000  # the episode length of a task that names none


class UnknownTaskError(ValueError):
    """A task name that names no task (or, as TaskLoadError, one that does not load)."""


def check_horizon(horizon: int) -> int:
    if isinstance(horizon, bool) or not isinstance(horizon, (int, np.integer)):
        raise ValueError(f"horizon must be an integer, got {horizon!r}")
    if not 1 <= horizon <= MAX_HORIZON:
        raise ValueError(f"horizon must lie in [1, {MAX_HORIZON}], got {horizon}")
    return int(horizon)


def episode_rng(seed: int, episode: int) -> np.random.Generator:
    """One independent stream per (seed, episode): runs resume and replay exactly."""
    return np.random.default_rng([int(seed), int(episode)])


class Plant(Protocol):
    """A dm_control task stepped one control step at a time; ``state()`` is what the dataset stores.

    ``angles`` (the state entries stored wrapped to (-pi, pi]) and ``action_low``/``action_high`` (the
    actuator range) are what the feedback policy needs; a plant without them has no angles and no limits.
    """

    task: str  # the task's name, as the registry knows it (a task file's: its path and content hash)
    seed: int  # the seed the plant was made for
    dt: float  # seconds per control step
    state_dim: int  # entries of a stored state
    action_dim: int  # entries of an action (one per actuator)
    joint_names: list[str]  # the model's joints, in the state's order
    actuated_joint_names: list[str]  # the joint each actuator drives, in the action's order

    def model_sha256(self) -> str:
        """The compiled model's fingerprint: the sim publishes it and the expert and supervisor check theirs."""
        ...

    def clone(self) -> Any:
        """An independent copy at the same state (a local rollout must not step the original)."""
        ...

    def reset(self, state: ArrayLike) -> FloatArray:
        """Set the plant to ``state`` (a stored state); return it as stored."""
        ...

    def state(self) -> FloatArray:
        """The current state as the dataset stores it (angles wrapped where the task wraps them)."""
        ...

    def step(self, action: ArrayLike) -> float:
        """Apply ``action`` for one control step; return that step's reward."""
        ...


class Expert(Protocol):
    """The TrajectoryOptimizer of Algorithm 1, with what a certificate needs to know about its values."""

    task: str  # the task it answers for
    seed: int  # the plant seed it models
    horizon: int  # H, the steps of an answer when a request names none
    plant: Any  # its own Plant instance; its fingerprint must match the sim's

    def trajectory(self, initial_state: ArrayLike, horizon: int | None = None) -> Trajectory:
        """One answer: the states, actions and values Q_t of an H-step trajectory from ``initial_state``."""
        ...

    def value_basis(self) -> ValueBasis:
        """What its stored values are (V*, or the expert's own return) and the tail a rollout check adds."""
        ...

    def theorem_34_condition(self, lipschitz: float) -> tuple[bool, str]:
        """Whether Theorem 3.4's condition holds for this L on its plant, and in words why (surrogate mode)."""
        ...


@runtime_checkable
class MeasuresValueSlope(Protocol):
    """An expert that sees the slope of its own value as it works (an optimizer's backward pass)."""

    requests: int  # requests answered so far

    def slope_floor(self) -> float:
        """The steepest slope of its value seen over its requests so far: a floor for L, never a bound."""
        ...


@runtime_checkable
class StopsAtTimeBudget(Protocol):
    """An expert whose requests may stop at a wall-clock budget: such an answer depends on the machine's speed."""

    time_budget: float
    budget_stops: int  # requests so far that the budget stopped before convergence or the iteration cap


SPEED_ONLY_OPTIONS = ("threads",)  # ExpertOptions that change how fast an expert answers, never what


@dataclass(frozen=True)
class ExpertOptions:
    """How to build a task's expert; None means the task's default. A task refuses what it cannot honour."""

    kind: str | None = None  # which of the task's experts (Task.experts); None = the first
    gamma: float = 1.0  # the discount; 1: undiscounted H-step values (the only one an optimizer expert takes)
    time_budget: float | None = None  # seconds per request (optimizer experts); a guard under stop "iterations"
    max_iterations: int | None = None  # iLQR iterations per request (optimizer experts)
    stop: str | None = None  # what ends an optimizer expert's request: "iterations" (reproducible) or "time"
    values: str | None = None  # value mode (optimizer experts, see OptimizingExpert)
    threads: int | None = None  # iLQR derivative threads (mujoco.batch, same answers at any count); None = 1
    control_weight: float = 0.1  # the detuned lqr expert's control-cost scale

    def answer_identity(self) -> dict[str, Any]:
        """The options that decide the expert's answers, for records that must match a run's own.

        SPEED_ONLY_OPTIONS (``threads``) are left out: a record made at one thread count (or before the
        option existed) stays this run's at any other.
        """
        return {field.name: getattr(self, field.name) for field in fields(self) if field.name not in SPEED_ONLY_OPTIONS}


DEFAULT_OPTIONS = ExpertOptions()


@dataclass(frozen=True)
class Task:
    """One task: its plant, its expert, rho, what is stored, and the constants the paper gives for it."""

    name: str  # the registry's name (a plug-in's: its entry point's name)
    state_dim: int  # entries of a stored state
    action_dim: int  # entries of an action
    stored_state: str  # what one stored state's entries are
    initial_state_diameter: float | None  # diam(S0) in the stored metric; condition (ii) needs it
    default_certify: CheckedQuantity  # what each episode checks when a run names nothing: rollout, oracle or surrogate
    experts: tuple[str, ...]  # expert kinds; the first is the default
    paper_lipschitz: float | None = None  # the paper's L for this task, where it gives one (the choice 'paper')
    paper_epsilon: float | None = None  # the paper's epsilon, where it gives one: the default epsilon
    paper_lipschitz_note: str = "the paper's choice (Section 5); not a bound on V*"  # what the certificate says of it
    # The L the task states itself, a user's choice (a task file's key lipschitz): a number (source 'user') or 'data'
    # (fixed from the run's first expert answers, npp_ros.run.setup); it is the default where no analytic L exists.
    own_lipschitz: float | str | None = None
    own_lipschitz_note: str = "the task's own choice; not a bound on its value"  # what the certificate says of it
    no_analytic_lipschitz: str = "its expert computes no bound on its value's slope"  # why 'analytic' is refused
    optimal_expert: bool = False  # the expert's values are V* (else claims are relative to the expert)
    default_horizon: int = DEFAULT_HORIZON  # the episode length when a command line gives none
    default_policy: PolicyKind = DEFAULT_POLICY  # how the policy acts when a run names none (a task file's key policy)
    reward_range: tuple[float, float] | None = None  # what one step's reward can be, where known (answer checks)
    # When an episode did the task (npp_ros.tasks.success): every run measures its expert and its policy on it and
    # the certificate states both; None = the task states none, and the certificate says that nothing was measured.
    success: SuccessCriterion | None = None
    # What of the robot is uncertain (npp_ros.tasks.uncertainty): a run asks for it (its uncertainty factor) and then
    # draws a robot from it per episode; the exact model by default, so a run that asks for nothing is the paper's.
    uncertainty: UncertaintySet = EXACT

    # ------------------------------------------------------------------ what each task provides
    def make_plant(self, seed: int) -> Plant:
        """A new plant for ``seed`` (the sim's, and each local copy a run steps)."""
        raise NotImplementedError

    def make_expert(self, seed: int, horizon: int, options: ExpertOptions = DEFAULT_OPTIONS) -> Expert:
        """A new expert on its own plant; a ValueError for options it cannot honour (ExpertOptions)."""
        raise NotImplementedError

    def sample_initial_state(self, rng: np.random.Generator) -> FloatArray:
        """One s0 ~ rho, drawn from ``rng`` only (so a seed and episode give the same s0 everywhere)."""
        raise NotImplementedError

    def invariant_entries(self) -> tuple[int, ...]:
        """The state entries whose value changes neither dynamics nor reward (the policy's distance ignores them);
        its plant's ``invariant``. None by default."""
        return ()

    def analytic_lipschitz(self, expert: Expert) -> LipschitzConstant:
        """A bound on the expert's value slope it computes (the choice 'analytic'); by default refused, saying why."""
        raise ValueError(
            f"L = 'analytic' is not available for {self.name}: {self.no_analytic_lipschitz}; "
            f"use {'paper, ' if self.paper_lipschitz else ''}data or a number"
        )

    def expert_value(self, expert: Expert) -> Callable[[FloatArray], float] | None:
        """The expert's value at any s0 in closed form, or None (then the episode log has it only when called)."""
        return None

    def value_slope(self, expert: Expert) -> Callable[[ArrayLike], FloatArray] | None:
        """|grad V^expert| at given states, where the expert knows it in closed form."""
        return None

    def optimal_returns(self, expert: Expert, plant: Plant, states: FloatArray, horizon: int) -> FloatArray | None:
        """The optimal H-step return from each s0, where it is known; None for a suboptimal-only task."""
        return None

    def expert_returns(
        self,
        expert: Expert,
        plant: Plant,
        states: FloatArray,
        horizon: int,
        progress: Callable[[int, int], None] | None = None,
        robots: Sequence[Robot] | None = None,
    ) -> FloatArray:
        """The expert's own H-step return from each s0: one request each (its reported return); with ``robots``,
        planning on s0 k's robot k (its model nominal again after), as a privileged expert does.

        ``progress(done, total)`` after each request: an optimizer's requests take seconds each.
        """
        out = np.empty(len(states))
        for k, s0 in enumerate(states):
            with as_robot(expert.plant, None if robots is None else robots[k]):
                ret = expert.trajectory(s0, horizon).expert_return
            out[k] = math.nan if ret is None else ret
            if progress is not None:
                progress(k + 1, len(states))
        return out

    # ------------------------------------------------------------------ derived, shared
    def initial_state(self, seed: int, episode: int) -> FloatArray:
        """s0 of ``episode``: its own seeded stream, so a resumed run and the graph see the same states."""
        return self.sample_initial_state(episode_rng(seed, episode))

    def expert_kind(self, options: ExpertOptions) -> str:
        kind = options.kind or self.experts[0]
        if kind not in self.experts:
            raise ValueError(f"{self.name} has no {kind!r} expert; it has {', '.join(self.experts)}")
        return kind

    def epsilon(self, given: float | None) -> float:
        """The given epsilon, or the paper's for this task when None; refused naming the flag when there is none."""
        if given is not None:
            return float(given)
        if self.paper_epsilon is None:
            raise ValueError(f"the paper gives no epsilon for {self.name}: {EPSILON_FLAG}")
        return self.paper_epsilon

    def lipschitz_choices(self) -> tuple[str, ...]:
        """The named L choices this task resolves besides 'data' (which every task resolves)."""
        analytic = type(self).analytic_lipschitz is not Task.analytic_lipschitz
        return (("analytic",) if analytic else ()) + (("paper",) if self.paper_lipschitz is not None else ())

    def default_lipschitz_choice(self) -> str | float:
        """'analytic' where the expert computes a bound, else the task's own L (a number or 'data'), else the
        paper's; a task with none of them is refused, naming the flag that gives one."""
        choices = self.lipschitz_choices()
        if choices and choices[0] == "analytic":
            return "analytic"
        if self.own_lipschitz is not None:
            return self.own_lipschitz
        if not choices:
            raise ValueError(f"{self.name} has no analytic, paper or own L: {LIPSCHITZ_FLAG} (a number or data)")
        return choices[0]

    def resolve_lipschitz(self, choice: str | float, expert: Expert) -> LipschitzConstant:
        """'analytic' (where the expert computes a bound), 'paper' (the paper's value, a choice) or a number (a
        user's L). 'data' needs the run (its seed, horizon and run file): npp_ros.run.setup resolves it."""
        if choice == "analytic":
            return self.analytic_lipschitz(expert)
        if choice == "paper":
            if self.paper_lipschitz is None:
                raise ValueError(f"the paper gives no L for {self.name}; use data or a number")
            return LipschitzConstant(self.paper_lipschitz, "paper", self.paper_lipschitz_note)
        if choice == "data":
            raise ValueError("L = 'data' is fixed from a run's first expert answers: resolve it with npp_ros.run.setup")
        try:
            value = float(choice)
        except ValueError:
            known = ", ".join(LIPSCHITZ_CHOICES)
            raise ValueError(f"the Lipschitz choice must be one of {known} or a number, got {choice!r}") from None
        own = isinstance(self.own_lipschitz, float) and value == self.own_lipschitz
        return LipschitzConstant(value, "user", self.own_lipschitz_note if own else "given as a run setting")


@dataclass(frozen=True)
class OptimizerTask(Task):
    """A task whose expert is an :class:`~npp_ros.trajopt.expert.OptimizingExpert` (iLQR on the plant's model).

    Its values are the expert's own true H-step returns, a local optimum of a smooth surrogate: a
    claim is relative to this expert, so the default check is ``oracle`` (V^E(s0) - R^pi(s0)).
    """

    default_certify: CheckedQuantity = "oracle"  # claims relative to the expert's own return
    experts: tuple[str, ...] = ("ilqr",)
    plant_factory: Callable[[int], Plant] | None = None  # seed -> a new plant (make_plant)
    # called as expert_factory(seed=, horizon=, time_budget=, values=, stop=, [max_iterations=]) -> an Expert
    expert_factory: Callable[..., Expert] | None = None
    sampler: Callable[[np.random.Generator], FloatArray] | None = None  # rng -> one s0 ~ rho (sample_initial_state)
    default_values: str = DEFAULT_VALUES  # what the expert stores as Q_t: window (H-step return) or return-to-go
    default_time_budget: float | None = None  # the task's own time budget; None: its expert's default for the stop
    plans_on_robot: bool = True  # its expert plans on its plant's model at each request, so it can plan on a robot

    def make_plant(self, seed: int) -> Plant:
        assert self.plant_factory is not None
        return self.plant_factory(seed)

    def make_expert(self, seed: int, horizon: int, options: ExpertOptions = DEFAULT_OPTIONS) -> Expert:
        assert self.expert_factory is not None
        self.expert_kind(options)
        if options.gamma != 1.0:
            raise ValueError(f"the {self.name} expert computes undiscounted H-step returns; gamma must be 1")
        extra: dict[str, Any] = {}
        if options.max_iterations is not None:
            extra["max_iterations"] = options.max_iterations
        expert = self.expert_factory(
            seed=seed,
            horizon=check_horizon(horizon),
            time_budget=self.default_time_budget if options.time_budget is None else options.time_budget,
            values=options.values or self.default_values,
            stop=options.stop or DEFAULT_STOP,
            **extra,
        )
        if options.threads is not None and isinstance(expert, OptimizingExpert):
            expert.optimizer.dynamics.threads = options.threads
        return expert

    def sample_initial_state(self, rng: np.random.Generator) -> FloatArray:
        assert self.sampler is not None
        return self.sampler(rng)


def control_space(plant: Plant) -> ControlSpace:
    """How the plant's states differ and how far its actuators reach (npp_ros.policy.feedback)."""
    low = getattr(plant, "action_low", np.full(plant.action_dim, -np.inf))
    high = getattr(plant, "action_high", np.full(plant.action_dim, np.inf))
    return ControlSpace.of(
        plant.state_dim, getattr(plant, "angles", ()), low, high, getattr(plant, "invariant", ()),
        getattr(plant, "distance_weights", ()),
    )  # fmt: skip
