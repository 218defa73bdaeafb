"""A task file read into a TaskDefinition, section by section, every key checked.

:func:`parse` reads the TOML, then each part in the file's order: the model and its timestep
(npp_ros.tasks.task_file.model), the run's defaults (horizon, epsilon, L, certification mode),
``[state]``, ``actuators``, ``[rho]``, ``[reward]`` (npp_ros.tasks.task_file.terms), ``[expert]`` and
``[success]`` (npp_ros.tasks.task_file.success), ``[uncertainty]`` (npp_ros.tasks.task_file.uncertainty).
The first problem is refused with one line naming the file and the key (TaskFileError).
"""

from __future__ import annotations

import hashlib
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from npp_ros.certificate.certifier import CERTIFY_MODES
from npp_ros.policy.dataset import FloatArray
from npp_ros.policy.feedback import DEFAULT_POLICY, POLICY_KINDS, wrap_angle
from npp_ros.tasks.success import SuccessCriterion
from npp_ros.tasks.task import DEFAULT_HORIZON, check_horizon
from npp_ros.tasks.task_file.cost import DEFAULT_CONTROL_WEIGHT, DEFAULT_VELOCITY_WEIGHT
from npp_ros.tasks.task_file.model import (
    load_model,
    read_actuators,
    read_rho,
    read_state,
    read_timestep,
    read_weights,
)
from npp_ros.tasks.task_file.reader import Reader, TaskFileError
from npp_ros.tasks.task_file.success import read_success
from npp_ros.tasks.task_file.terms import FunctionReward, Term, TermReward, read_reward, read_terms
from npp_ros.tasks.task_file.uncertainty import read_uncertainty
from npp_ros.tasks.uncertainty import EXACT, UncertaintySet
from npp_ros.trajopt.expert import DEFAULT_VALUES, STOP_MODES, VALUE_MODES
from npp_ros.trajopt.ilqr import check_time_budget
from npp_ros.trajopt.receding import DEFAULT_PLANNER, PLANNER_KEYS, PlannerSettings, SettingError

HASH_MARK = "#sha256="  # a task file's name: its absolute path, this, and its content's SHA-256
TOP_KEYS = {"name", "model", "control_timestep", "horizon", "epsilon", "lipschitz", "certify", "policy", "actuators",
            "state", "rho", "reward", "expert", "success", "uncertainty"}  # fmt: skip
EXPERT_KEYS = {"max_iterations", "time_budget", "stop", "values", "warm_start", "control_weight", "velocity_weight",
               "terms", *PLANNER_KEYS}  # fmt: skip
WARM_STARTS = ("zero", "gravity")  # u = 0, or the torques that hold the start at rest (task_file.GravityHold)
DEFAULT_CERTIFY = "oracle"  # the check of every task with an iLQR expert (OptimizerTask)
# iLQR iterations per request of a task file's expert. Measured on examples/two_link_arm under the earlier 5 s budget
# (npp-bench --only experts --expert-tasks examples/two_link_arm/task.toml, 10 requests at H = 1000, load 0.9-3.7):
# 9 of 10 requests ended by convergence or this cap in 1.39-4.40 s, one by the budget (4.85 s, the load at its peak).
DEFAULT_MAX_ITERATIONS = 30
DEFAULT_WARM_START = "zero"


@dataclass(frozen=True)
class TaskDefinition:
    """Everything the file says, checked against the compiled model."""

    path: Path
    sha256: str
    label: str
    model_path: Path
    dt: float
    horizon: int
    epsilon: float | None
    lipschitz: float | str  # a number (a user's L) or 'data'
    certify: str
    policy: str  # how a run's policy acts when its command line names none
    joint_names: tuple[str, ...]
    actuator_names: tuple[str, ...]
    actuated_joint_names: tuple[str, ...]
    wrapped: tuple[int, ...]  # qpos indices stored wrapped
    rho_low: FloatArray
    rho_high: FloatArray
    reward: TermReward | FunctionReward
    cost_terms: tuple[Term, ...]
    expert: dict[str, Any] = field(default_factory=dict)
    success: SuccessCriterion | None = None  # [success]: when an episode did the task (None: the file states none)
    uncertainty: UncertaintySet = EXACT  # [uncertainty]: what of the robot is uncertain (the exact model: nothing)
    invariant: tuple[int, ...] = ()  # [state] invariant: qpos indices whose value changes neither dynamics nor reward
    target_joints: tuple[str, ...] = ()  # [state] target: the x, y, z slide joints of a point no torque moves
    distance_weights: tuple[float, ...] = ()  # [state.weights]: each state entry's weight in the policy's distance

    @property
    def name(self) -> str:
        return f"{self.path}{HASH_MARK}{self.sha256}"

    @property
    def state_dim(self) -> int:
        return 2 * len(self.joint_names)

    @property
    def action_dim(self) -> int:
        return len(self.actuator_names)

    def stored_state(self) -> str:
        angles = [self.joint_names[i] for i in self.wrapped]
        wrapped = f" ({', '.join(angles)} wrapped to (-pi, pi])" if angles else ""
        target = f"; {', '.join(self.target_joints)} the target, at rest" if self.target_joints else ""
        return f"qpos then qvel of {', '.join(self.joint_names)}{wrapped}{target}"

    def represent(self, raw: ArrayLike) -> FloatArray:
        x = np.array(raw, dtype=np.float64, copy=True)
        for i in self.wrapped:
            x[..., i] = wrap_angle(x[..., i])
        return x

    def sample_initial_state(self, rng: np.random.Generator) -> FloatArray:
        """s0 ~ rho: uniform in each entry's range (an entry whose range is a point is not drawn)."""
        return rng.uniform(self.rho_low, self.rho_high)

    def initial_state_diameter(self) -> float:
        widths = self.rho_high - self.rho_low
        for i in self.wrapped:
            widths[i] = min(widths[i], 2 * math.pi)
        return float(np.linalg.norm(widths))


def parse(path: Path, content: bytes) -> TaskDefinition:
    """The definition in ``content`` (the file at ``path``); TaskFileError naming the key on any problem."""
    reader = Reader(path)
    try:
        doc = tomllib.loads(content.decode())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise TaskFileError(f"task file {path}: not valid TOML: {exc}") from None
    reader.unknown_keys(doc, TOP_KEYS, "")
    model_path, model = load_model(reader, doc, path)
    dt = read_timestep(reader, doc, model)
    horizon, epsilon, lipschitz, certify, policy = _run_defaults(reader, doc)
    joint_names, wrapped, invariant, target = read_state(reader, doc, model)
    weights = read_weights(reader, doc, model)
    actuator_names, actuated = read_actuators(reader, doc, model)
    driven = sorted(set(actuated) & set(target))
    if driven:
        raise reader.fail("state.target", f"joint {driven[0]!r} is driven by an actuator: nothing may move a target")
    low, high = read_rho(reader, doc, model)
    for name in target:
        at = len(joint_names) + joint_names.index(name)  # qvel index = nq + index (hinge and slide joints only)
        if low[at] != 0.0 or high[at] != 0.0:
            raise reader.fail(f"rho.{name}.velocity", "a target coordinate starts at rest, and stays so: give none")
    reward = read_reward(reader, doc, model)
    options, cost_terms = _read_expert(reader, doc, model, reward)
    success = read_success(reader, doc, model, model_path, dt)
    uncertainty = read_uncertainty(reader, doc, model)
    label = doc.get("name", path.parent.name or path.stem)
    return TaskDefinition(
        path=path, sha256=hashlib.sha256(content).hexdigest(), label=reader.text(label, "name"),
        model_path=model_path, dt=dt, horizon=horizon, epsilon=epsilon, lipschitz=lipschitz, certify=certify,
        policy=policy, joint_names=joint_names, actuator_names=actuator_names, actuated_joint_names=actuated,
        wrapped=wrapped, rho_low=low, rho_high=high, reward=reward, cost_terms=cost_terms, expert=options,
        success=success, uncertainty=uncertainty, invariant=invariant, target_joints=target,
        distance_weights=weights,
    )  # fmt: skip


def _run_defaults(reader: Reader, doc: dict[str, Any]) -> tuple[int, float | None, float | str, str, str]:
    """The horizon, epsilon, L, certification mode and policy a run takes when its command line gives none.

    epsilon has no default (a gap in the task's own return units: the file or the command line says it); L
    defaults to 'data' (npp_ros.certificate.choices.DATA_RULE)."""
    horizon = int(reader.number(doc.get("horizon", DEFAULT_HORIZON), "horizon", positive=True))
    try:
        check_horizon(horizon)
    except ValueError as exc:
        raise reader.fail("horizon", str(exc)) from None
    epsilon = reader.number(doc["epsilon"], "epsilon", positive=True) if "epsilon" in doc else None
    lipschitz = doc.get("lipschitz", "data")
    if isinstance(lipschitz, str) and lipschitz != "data":
        raise reader.fail("lipschitz", f'must be a number > 0 or "data", got {lipschitz!r}')
    if lipschitz != "data":
        lipschitz = reader.number(lipschitz, "lipschitz", positive=True)
    certify = doc.get("certify", DEFAULT_CERTIFY)
    if certify not in CERTIFY_MODES:
        raise reader.fail("certify", f"must be one of {', '.join(CERTIFY_MODES)}, got {certify!r}")
    policy = doc.get("policy", DEFAULT_POLICY)
    if policy not in POLICY_KINDS:
        raise reader.fail("policy", f"must be one of {', '.join(POLICY_KINDS)}, got {policy!r}")
    return horizon, epsilon, lipschitz, certify, policy


def _read_planner(reader: Reader, expert: dict[str, Any]) -> PlannerSettings:
    """The planner keys of ``[expert]`` (npp_ros.trajopt.receding), each only where the chosen planner uses it."""
    given = {key: expert[key] for key in PLANNER_KEYS if key in expert}
    planner = given.get("planner", DEFAULT_PLANNER)
    try:
        settings = PlannerSettings(**given)
    except SettingError as exc:
        raise reader.fail(f"expert.{exc.key}", exc.problem) from None
    for key in given:
        if planner not in PlannerSettings.planners_using(key):
            users = " or ".join(f'"{name}"' for name in PlannerSettings.planners_using(key))
            raise reader.fail(f"expert.{key}", f'applies to planner = {users}, not "{planner}"')
    return settings


def _read_expert(
    reader: Reader, doc: dict[str, Any], model: Any, reward: TermReward | FunctionReward
) -> tuple[dict[str, Any], tuple[Term, ...]]:
    """``[expert]``: the iLQR expert's options (only those the file gives, and its value mode and cost weights)
    and the terms of its smooth cost (the reward's own, or ``[[expert.terms]]``, which a reward function needs)."""
    expert = reader.table(doc.get("expert", {}), "expert")
    reader.unknown_keys(expert, EXPERT_KEYS, "expert.")
    options: dict[str, Any] = {}
    if "max_iterations" in expert:
        options["max_iterations"] = int(reader.number(expert["max_iterations"], "expert.max_iterations", True))
    if "time_budget" in expert:
        try:
            options["time_budget"] = check_time_budget(expert["time_budget"])
        except ValueError as exc:
            raise reader.fail("expert.time_budget", str(exc)) from None
    if "stop" in expert:
        if expert["stop"] not in STOP_MODES:
            raise reader.fail("expert.stop", f"must be one of {', '.join(STOP_MODES)}, got {expert['stop']!r}")
        options["stop"] = expert["stop"]
    options["values"] = expert.get("values", DEFAULT_VALUES)
    if options["values"] not in VALUE_MODES:
        raise reader.fail("expert.values", f"must be one of {', '.join(VALUE_MODES)}, got {expert['values']!r}")
    options["warm_start"] = expert.get("warm_start", DEFAULT_WARM_START)
    if options["warm_start"] not in WARM_STARTS:
        raise reader.fail(
            "expert.warm_start", f"must be one of {', '.join(WARM_STARTS)}, got {options['warm_start']!r}"
        )
    for key, default in (("control_weight", DEFAULT_CONTROL_WEIGHT), ("velocity_weight", DEFAULT_VELOCITY_WEIGHT)):
        options[key] = reader.non_negative(expert.get(key, default), f"expert.{key}")
    options["planner"] = _read_planner(reader, expert)
    if "terms" in expert:
        return options, read_terms(reader, expert["terms"], "expert.terms", model, True, cost=True)
    if isinstance(reward, TermReward):
        return options, reward.terms
    raise reader.fail("expert.terms", "a reward function needs [[expert.terms]]: the iLQR expert's smooth cost")
