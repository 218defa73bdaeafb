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
from npp_ros.certificate.choices import (
    DATA_ANSWERS,
    DATA_FACTOR,
    DATA_PAIR_FLOOR,
    DATA_RULE,
    DATA_WITHIN,
    LIPSCHITZ_FLAG,
)
from npp_ros.certificate.values import ValueBasis
from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import Dataset, FloatArray, Trajectory
from npp_ros.policy.feedback import DEFAULT_POLICY, ControlSpace, PolicyKind, check_policy_kind
from npp_ros.policy.lipschitz import (
    LipschitzCheck,
    LipschitzConstant,
    PairSlope,
    check_lipschitz,
    estimate_global,
    steepest_pair,
)
from npp_ros.run import defaults
from npp_ros.run.explore import PolicyReplay, RolloutExplorer, check_radius
from npp_ros.run.loop import EpisodeDriver, NPPLoop, Observer, Oracle, RunConfig, make_policy
from npp_ros.run.nominal_plan import DEFAULT_EXPERT_MODEL, check_expert_model, stores_window_values, tracked_on_robot
from npp_ros.run.policy_lipschitz import check_policy_lipschitz
from npp_ros.run.records import EpisodeRow, RunFileError, RunMetadata, SuccessCounts, expert_settings
from npp_ros.run.store import RunStore
from npp_ros.tasks.registry import (
    Expert,
    ExpertOptions,
    MeasuresValueSlope,
    Plant,
    control_space,
    get_task,
    task_label,
)
from npp_ros.tasks.sources import short_name
from npp_ros.tasks.uncertainty import Robot, UncertaintySet, as_robot, supports_robots, where_expert_failed


def resolve_lipschitz(
    task: str,
    choice: str | float | None,
    expert: Expert,
    *,
    seed: int = 0,
    horizon: int | None = None,
    run_file: Path | None = None,
) -> LipschitzConstant:
    """'analytic' (a true bound, where the expert computes one), 'paper' (the paper's, not a bound), 'data'
    (:func:`data_lipschitz`: the run's seed, horizon and run file decide it) or a number; None: the task's default
    (Task.default_lipschitz_choice, a task file's key lipschitz)."""
    definition = get_task(task)
    choice = definition.default_lipschitz_choice() if choice is None else choice
    if choice == "data":
        return data_lipschitz(task, seed, expert, horizon, run_file)
    return definition.resolve_lipschitz(choice, expert)


def data_lipschitz(
    task: str, seed: int, expert: Expert, horizon: int | None = None, run_file: Path | None = None
) -> LipschitzConstant:
    """L = 'data' (DATA_RULE): fixed from the expert's answers from the s0 of episodes 0 .. DATA_ANSWERS - 1.

    A run file that already records a 'data' L gives it back, so a resumed run keeps the L it began with
    whatever the expert answers now. The answers cost DATA_ANSWERS requests before the run starts (episode 0
    asks for the first again). The slope is one the data shows, so L is a scale for the policy's bounds, never a
    bound on the value's slope: in oracle mode a choice, in the other modes an assumption the certificate names.
    """
    recorded = _recorded_lipschitz(run_file)
    if recorded is not None and recorded[1] == "data":  # another recorded L: the run file's resume check refuses
        return LipschitzConstant(recorded[0], "data", f"{DATA_RULE}; read back from the run file")
    definition = get_task(task)
    answers = Dataset(definition.state_dim, definition.action_dim)
    for episode in range(DATA_ANSWERS):
        answers.append(expert.trajectory(definition.initial_state(seed, episode), horizon))
    pair = data_slope(answers, getattr(expert, "values", "") == "window")
    stored = pair.slope if pair is not None else 0.0
    own = expert.slope_floor() if isinstance(expert, MeasuresValueSlope) else 0.0
    steepest = max(stored, own)
    if not (math.isfinite(steepest) and steepest > 0):
        raise ValueError(
            f"L = 'data': the expert's first {DATA_ANSWERS} answers show no slope (their values do not change "
            f"with the state): {LIPSCHITZ_FLAG} with a number"
        )
    measured = f"stored values {pair.describe() if pair else 'no pair'}" + (
        f"; the expert's |W_x| {own:.6g}" if own else ""
    )
    return LipschitzConstant(DATA_FACTOR * steepest, "data", f"{DATA_RULE} ({measured})")


def data_slope(answers: Dataset, continued: bool) -> PairSlope | None:
    """The stored values' slope the 'data' rule takes: between points DATA_PAIR_FLOOR x the median pair distance
    apart; where values are ``continued`` past the horizon (window values), on each answer's steps
    t <= (1 - DATA_WITHIN) H only, whose values lie mostly within it."""
    steps = None
    if continued and answers.num_trajectories:
        length = len(answers.trajectory(0).values)
        steps = math.floor((1.0 - DATA_WITHIN) * length) + 1
    return steepest_pair(answers, steps=steps, floor_share=DATA_PAIR_FLOOR)


def _recorded_lipschitz(run_file: Path | None) -> tuple[float, str] | None:
    """The L and its source a run file records, or None when there is no readable run file there yet."""
    if run_file is None or not run_file.is_file():
        return None
    try:
        with RunStore.open(run_file) as store:
            return float(store.metadata.lipschitz), str(store.metadata.lipschitz_source)  # type: ignore[arg-type]
    except (RunFileError, ValueError, TypeError):
        return None  # empty or damaged: opening it for the run says why


def build_config(
    task: str,
    seed: int,
    lipschitz: LipschitzConstant,
    epsilon: float,
    *,
    condition: Condition = defaults.CONDITION,  # type: ignore[assignment]
    p: float = defaults.P,
    delta: float = defaults.DELTA,
    horizon: int | None = None,
    gamma: float = defaults.GAMMA,
    certify: CheckedQuantity | None = None,
    rule: StoppingRule | None = None,
    policy: PolicyKind = DEFAULT_POLICY,
    explore: float = defaults.EXPLORE,
    uncertainty: float = defaults.UNCERTAINTY,
    expert_model: str = DEFAULT_EXPERT_MODEL,
    options: ExpertOptions | None = None,
    expert: Expert | None = None,
    policy_lipschitz: str = defaults.POLICY_LIPSCHITZ,
) -> RunConfig:
    """The run's config; every default is the request's (npp_ros.run.defaults); ``horizon`` None is the task's,
    ``certify`` None is the task's default (rollout on lqr, oracle for optimizer experts),
    ``rule`` None the default rule of that checked quantity (DEFAULT_RULES), ``policy`` how the policy acts,
    ``explore`` > 0 the radius beyond which a failed check also asks where the policy went (npp_ros.run.explore),
    ``uncertainty`` > 0 the task's uncertainty set, its ranges' distance from the nominal model multiplied by this
    (1: the set the task declares; 0: the exact model), a robot drawn from it per episode (:func:`robot_fn`),
    ``expert_model`` the model the expert plans on then (npp_ros.run.nominal_plan), ``policy_lipschitz`` the L the
    policy chooses by (the claim's, or selected from the run's data: npp_ros.run.policy_lipschitz).

    ``options`` are the expert's (None: the task's, with this gamma) and ``expert`` the run's expert built with them
    (None: one is built here to read them off): the config records the settings that decide its answers as that
    expert resolved them (records.expert_settings), so a run asking for the task's default and one asking for its
    value are the same run.

    Refuses a bad combination (ValueError) when the run is defined, not episodes later.
    """
    definition = get_task(task)
    horizon = definition.default_horizon if horizon is None else horizon
    certify = certify or definition.default_certify
    spec = CertificationSpec(
        condition, epsilon, p, delta, lipschitz, definition.initial_state_diameter,
        certify=certify, rule=rule or DEFAULT_RULES[certify], policy=check_policy_kind(policy),
    )  # fmt: skip
    options = ExpertOptions(gamma=gamma) if options is None else options
    settings = (
        _expert_settings(task, seed, horizon, replace(options, threads=None))
        if expert is None
        else expert_settings(expert, definition.expert_kind(options), options)
    )
    return RunConfig(
        task, seed, definition.state_dim, definition.action_dim, spec,
        horizon=horizon, gamma=gamma, plant_fingerprint=plant_fingerprint(task, seed), explore=check_radius(explore),
        policy_lipschitz=check_policy_lipschitz(policy_lipschitz, certify),
        uncertainty=uncertainty_record(task, seed, uncertainty, expert_model),
        expert_model=check_expert_model(expert_model, uncertainty), **settings,  # type: ignore[arg-type]
    )  # fmt: skip


@functools.lru_cache(maxsize=64)
def _expert_settings(task: str, seed: int, horizon: int, options: ExpertOptions) -> dict[str, object]:
    """build_config's expert settings where no expert is given: the task's expert built with ``options`` (speed-only
    ones cleared), read off once per options (building an expert compiles its model)."""
    definition = get_task(task)
    expert = definition.make_expert(seed, horizon, options)
    return expert_settings(expert, definition.expert_kind(options), options)


def uncertainty_record(task: str, seed: int, factor: float, expert_model: str = DEFAULT_EXPERT_MODEL) -> str:
    """The run's set of robots for an uncertainty factor, as the run file records it ('' for the exact model).

    Refused (ValueError, saying why) where the task declares nothing uncertain, its plant is not a MuJoCo model a
    robot can be drawn into, or, for an expert asked to plan on each robot (``expert_model`` robot), its expert
    cannot (``nominal`` needs nothing of the expert).
    """
    if check_uncertainty(factor) == 0:
        return ""
    definition = get_task(task)
    name = short_name(task)
    if definition.uncertainty.empty:
        raise ValueError(f"{name} declares nothing uncertain (a task file's [uncertainty] table): uncertainty 0")
    plant = definition.make_plant(seed)
    if not supports_robots(plant):
        raise ValueError(f"{name}: its plant is no MuJoCo model a drawn robot can be made of: uncertainty 0")
    if check_expert_model(expert_model) == "robot" and not getattr(definition, "plans_on_robot", False):
        raise ValueError(
            f"{name}: its expert cannot plan on a drawn robot (only the iLQR experts plan on the plant's own model "
            "each request): ask for --expert-model nominal (its nominal plan run on each robot) or uncertainty 0"
        )
    return definition.uncertainty.widened(factor).resolved(plant.physics.model).record()


def check_uncertainty(factor: float) -> float:
    """An uncertainty factor: finite and >= 0 (0: the exact model)."""
    if not (math.isfinite(factor) and factor >= 0):
        raise ValueError(f"the uncertainty factor must be finite and >= 0 (0: the exact model), got {factor!r}")
    return float(factor)


def robot_fn(config: RunConfig) -> Callable[[int], Robot] | None:
    """theta for episode e from the run's seed and e only (None: the exact model), so a resumed run, the graph
    and a held-out check draw the same robots."""
    if not config.uncertainty:
        return None
    robots = UncertaintySet.from_record(config.uncertainty)
    return lambda episode: robots.draw(config.seed, episode)


class NominalPlanExpert:
    """The oracle of a run whose expert plans on the nominal model (npp_ros.run.nominal_plan): the expert (in
    process, or the graph's expert service) is asked for a nominal plan, which then runs on the episode's robot on
    a local copy of the plant; that rollout is the answer. The same here and in the supervisor."""

    def __init__(self, oracle: Oracle, plant: Plant, control: ControlSpace, *, window: bool) -> None:
        self.oracle = oracle
        self.plant = plant
        self.control = control
        self.window = window

    def trajectory(self, initial_state: FloatArray, robot: Robot | None = None) -> Trajectory:
        plan = self.oracle.trajectory(initial_state)
        if robot is None:
            return plan
        return tracked_on_robot(self.plant, plan, initial_state, robot, self.control, window=self.window)


class PrivilegedExpert:
    """The task's expert planning on the episode's robot: its own plant's model is made into the robot for the
    request and is nominal again after it (a teacher that knows theta; the policy does not)."""

    def __init__(self, expert: Expert) -> None:
        self.expert = expert

    def trajectory(self, initial_state: FloatArray, robot: Robot | None = None) -> Trajectory:
        with as_robot(self.expert.plant, robot):
            return self.expert.trajectory(initial_state)


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


def policy_for(
    data: Dataset, spec: CertificationSpec, task: str, seed: int, lipschitz: LipschitzConstant | None = None
) -> NonparametricPolicy:
    """The policy ``spec`` names over ``data`` for this task's plant: what a run's checks, its evaluations and a
    robot act with; ``lipschitz`` the L it acts by where the run chose its own (None: the claim's)."""
    return make_policy(data, spec, task_control_space(task, seed), lipschitz)


def initial_state_fn(task: str, seed: int) -> Callable[[int], FloatArray]:
    """s0 for episode e: its own seeded stream, so a resumed run replays the same states."""
    spec = get_task(task)
    return lambda episode: spec.initial_state(seed, episode)


class PolicyRollouts:
    """Episode driver: the greedy policy drives the plant for H steps; returns the return. Its rollout is the
    replay's, which the success check and the explorer of the same episode then share."""

    def __init__(self, replay: PolicyReplay) -> None:
        self.replay = replay

    def run_episode(
        self, episode: int, initial_state: FloatArray, policy: NonparametricPolicy, robot: Robot | None = None
    ) -> float | None:
        if len(policy.dataset) == 0:
            return None
        return self.replay.rollout(initial_state, policy, robot).total_return


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
    answers: Oracle | None = None,
) -> NPPLoop:
    """The loop for ``config`` with this expert: every front end builds its run here, so a loop option is added once.

    In one process (npp-learn, npp-experiment) the expert answers directly and the policy drives a local copy of
    the plant (the sound modes always let it drive; ``rollouts`` in surrogate mode too). The supervisor node gives
    its own ``oracle`` (the expert service) and ``driver`` (the sim, or None when it does not let the policy
    drive) and the ``store`` it opened; the expert is then still the task's, for L, V(s0) and the value basis.

    The policy's rollout is judged on the task's success criterion and explored from on one local replay: in one
    process it is the driver's own rollout; behind the graph's sim, the same rollout re-run on a local copy of the
    plant (deterministic, as every certificate assumes), so both give the same rows.

    ``answers``: the run's expert answers as it stored them (a re-derivation of a stored run, rederive.py), the
    oracle as it is: in process, and never wrapped, since a stored answer is already what the robot did.
    """
    if store is None and store_path is not None:
        store = RunStore.open_or_create(store_path, config.metadata())
    task = get_task(config.task)
    needs_replay = (
        oracle is None or task.success is not None or config.explore > 0 or config.policy_lipschitz != "claim"
    )
    replay = PolicyReplay(task.make_plant(config.seed), config.horizon) if needs_replay else None
    if oracle is None:
        drive = rollouts or config.spec.certify != "surrogate"
        assert replay is not None
        driver = PolicyRollouts(replay) if drive else None
    if answers is not None:
        oracle = answers
    elif config.uncertainty and config.expert_model == "nominal":  # a nominal plan, run on the robot here
        control = task_control_space(config.task, config.seed)
        window = stores_window_values(expert)
        oracle = NominalPlanExpert(oracle or expert, task.make_plant(config.seed), control, window=window)
    elif oracle is None and config.uncertainty:  # in process: the expert plans on each episode's robot
        oracle = PrivilegedExpert(expert)
    return NPPLoop(
        config,
        oracle or expert,
        initial_state_fn(config.task, config.seed),
        store=store,
        driver=driver,
        observers=observers,
        expert_value=task.expert_value(expert),
        basis=value_basis(expert, config.spec.lipschitz.value),
        control=task_control_space(config.task, config.seed),
        explorer=RolloutExplorer(replay, config.explore) if config.explore and replay is not None else None,
        success=task.success,
        replay=replay if driver is not None or config.policy_lipschitz != "claim" else None,
        robots=robot_fn(config),
    )


def expert_notice(
    task: str, counts: SuccessCounts, rows: Sequence[EpisodeRow] = (), *, relative: bool = True
) -> list[str]:
    """What a command prints before a run's certificate about its expert: a warning when the expert failed the
    task's success criterion on most of its answers, a note when the task states no criterion, and, for a run on a
    set of robots (``rows`` with robots), where in the set the expert failed (a set must stay within what the
    expert can do); else nothing. ``relative`` False (the success claim, which needs no expert): no warning that
    the certificate is relative to a failing expert."""
    criterion = get_task(task).success
    if criterion is None:
        return [
            f"note: {task_label(task)} states no success criterion: nothing measured whether its expert does the "
            "task, and a certificate is relative to that expert"
        ]
    judged = [row for row in rows if row.robot and row.expert_success is not None]
    where = where_expert_failed(
        [Robot.from_record(str(row.robot)) for row in judged], [not row.expert_success for row in judged]
    )
    warning = counts.warning(criterion.describe()) if relative else []
    return warning + ([f"note: {where}"] if where else [])


def run_file_notice(run_file: Path) -> list[str]:
    """:func:`expert_notice` for the run a run file holds (npp-run reads it after the graph's run); nothing for a
    file that cannot be read or a task that no longer loads (the run's own output says why)."""
    try:
        with RunStore.open(run_file) as store:
            rows, task, certify = store.episodes(), str(store.metadata.task), store.metadata.certify
        counts = SuccessCounts.of(rows, policy=certify != "surrogate")
        return expert_notice(task, counts, rows, relative=certify != "success")
    except (RunFileError, ValueError):
        return []


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
