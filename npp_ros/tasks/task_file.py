"""A task from a file: a MuJoCo model (MJCF) and a TOML description of its task, no Python.

``--task path/to/task.toml`` (and the sim's ``task`` parameter) loads one; README "Your own robot"
describes every key. In short::

    model = "arm.xml"              # MJCF, relative to this file
    control_timestep = 0.01        # optional; must equal the model's timestep (one MuJoCo step per control step)
    horizon = 200                  # default episode length
    epsilon = 40.0                 # default target gap
    lipschitz = 100.0              # default L of the policy's bounds (a choice, not a bound on the value)
    certify = "oracle"             # default certification mode
    actuators = ["shoulder_motor", "elbow_motor"]   # optional check: the model's actuators, in order

    [state]
    joints = ["shoulder", "elbow"] # every joint of the model (hinge or slide), in the model's order
    wrap = ["shoulder"]            # hinge angles stored wrapped to (-pi, pi]

    [rho]                          # s0 uniform in these ranges; joints not named start at 0, at rest
    shoulder = { position = [-3.14, 3.14], velocity = [0.0, 0.0] }

    [reward]
    combine = "sum"                # or "product"
    [[reward.terms]]               # dm_control.utils.rewards.tolerance of one named quantity
    site_distance = ["fingertip", "target"]
    bounds = [0.0, 0.02]
    margin = 0.3
    sigmoid = "gaussian"           # and value_at_margin, weight (sum only)
    # or: function = "my_module:reward", called as reward(physics) -> float after each step

    [expert]                       # the iLQR expert (npp_ros.trajopt.OptimizingExpert)
    max_iterations = 30
    time_budget = 5.0
    warm_start = "zero"

Quantities: ``joint_position``, ``joint_velocity`` (a joint), ``site_position`` (a site, with
``axis`` x, y or z), ``site_distance`` (two sites), ``control`` (an actuator). The reward is
computed from the physics after each step with the applied (clamped) control, as dm_control's
suite does.

The expert optimises a smooth surrogate of the reward (:class:`TermCost`): each term costs
0.5 w ((q - clip(q, bounds)) / margin)^2, zero exactly where its tolerance is 1; the values it
stores are the true rewards replayed on the plant, as for every iLQR expert.

Agreement: the task's name is the file's absolute path and its content's SHA-256
(``/abs/task.toml#sha256=...``); the sim publishes that name, and the expert and the supervisor
load the file at that path and refuse it when its content differs (naming both hashes). The
compiled model is compared by its fingerprint, as for every task.

A bad file is refused with one line naming the file, the key and the problem (:class:`TaskFileError`).
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import math
import os
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from npp_ros.certificate.certifier import CERTIFY_MODES
from npp_ros.policy.dataset import FloatArray
from npp_ros.policy.feedback import wrap_angle
from npp_ros.tasks.suite_plant import SuitePlant
from npp_ros.tasks.task import DEFAULT_OPTIONS, Expert, ExpertOptions, OptimizerTask, check_horizon
from npp_ros.trajopt.ilqr import VALUE_MODES, OptimizingExpert, check_time_budget

HASH_MARK = "#sha256="
QUANTITIES = ("joint_position", "joint_velocity", "site_position", "site_distance", "control")
SIGMOIDS = ("gaussian", "hyperbolic", "long_tail", "reciprocal", "cosine", "linear", "quadratic", "tanh_squared")
WARM_STARTS = ("zero",)
TOP_KEYS = {"name", "model", "control_timestep", "horizon", "epsilon", "lipschitz", "certify", "actuators", "state",
            "rho", "reward", "expert"}  # fmt: skip
TERM_KEYS = {*QUANTITIES, "axis", "bounds", "margin", "sigmoid", "value_at_margin", "weight"}
EXPERT_KEYS = {"max_iterations", "time_budget", "values", "warm_start", "control_weight", "velocity_weight", "terms"}
FINGERPRINT_FIELDS = (
    "opt.timestep", "opt.gravity", "opt.integrator", "opt.wind", "opt.density", "opt.viscosity", "dof_damping",
    "dof_armature", "dof_frictionloss", "jnt_stiffness", "jnt_range", "jnt_limited", "qpos0", "body_mass",
    "body_inertia", "body_ipos", "body_iquat", "body_pos", "body_quat", "geom_size", "geom_pos", "site_pos",
    "actuator_gear", "actuator_ctrlrange", "actuator_ctrllimited", "actuator_gainprm", "actuator_biasprm",
)  # fmt: skip


class TaskFileError(ValueError):
    """A task file that cannot define a task; the message names the file, the key and the problem."""


# ----------------------------------------------------------------------------- reading the file
class _Reader:
    """Typed access to the parsed file, every refusal naming the dotted key."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def fail(self, key: str, problem: str) -> TaskFileError:
        return TaskFileError(f"task file {self.path}: {key}: {problem}")

    def unknown_keys(self, table: dict[str, Any], allowed: set[str], where: str) -> None:
        for key in table:
            if key not in allowed:
                known = ", ".join(sorted(allowed))
                raise self.fail(f"{where}{key}", f"unknown key (known here: {known})")

    def number(self, value: Any, key: str, positive: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise self.fail(key, f"must be a finite number, got {value!r}")
        if positive and value <= 0:
            raise self.fail(key, f"must be > 0, got {value!r}")
        return float(value)

    def text(self, value: Any, key: str) -> str:
        if not isinstance(value, str) or not value:
            raise self.fail(key, f"must be a non-empty string, got {value!r}")
        return value

    def names(self, value: Any, key: str) -> list[str]:
        if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
            raise self.fail(key, f"must be a list of names, got {value!r}")
        return list(value)

    def interval(self, value: Any, key: str) -> tuple[float, float]:
        if not isinstance(value, list) or len(value) != 2:
            raise self.fail(key, f"must be [low, high], got {value!r}")
        low, high = (self.number(v, key) for v in value)
        if low > high:
            raise self.fail(key, f"is empty: low {low:g} > high {high:g}")
        return low, high

    def table(self, value: Any, key: str) -> dict[str, Any]:
        if not isinstance(value, dict):
            raise self.fail(key, f"must be a table, got {value!r}")
        return value


@dataclass(frozen=True)
class Term:
    """One tolerance term: which quantity, and dm_control's tolerance parameters."""

    quantity: str
    target: tuple[int, ...]  # joint, site or actuator ids (two sites for a distance)
    axis: int
    bounds: tuple[float, float]
    margin: float
    sigmoid: str
    value_at_margin: float
    weight: float
    label: str

    @property
    def on_control(self) -> bool:
        return self.quantity == "control"


def _model_ids(model: Any, kind: str) -> dict[str, int]:
    import mujoco

    obj = {"joint": mujoco.mjtObj.mjOBJ_JOINT, "site": mujoco.mjtObj.mjOBJ_SITE,
           "actuator": mujoco.mjtObj.mjOBJ_ACTUATOR}[kind]  # fmt: skip
    count = {"joint": model.njnt, "site": model.nsite, "actuator": model.nu}[kind]
    return {mujoco.mj_id2name(model, obj, i): i for i in range(count)}


def _terms(reader: _Reader, entries: Any, key: str, model: Any, weighted: bool) -> tuple[Term, ...]:
    if not isinstance(entries, list) or not entries:
        raise reader.fail(key, "must be a non-empty list of terms ([[...]] tables)")
    ids = {kind: _model_ids(model, kind) for kind in ("joint", "site", "actuator")}
    out = []
    for k, entry in enumerate(entries):
        where = f"{key}[{k}]"
        entry = reader.table(entry, where)
        reader.unknown_keys(entry, TERM_KEYS, f"{where}.")
        named = [q for q in QUANTITIES if q in entry]
        if not named:
            raise reader.fail(where, f"the term is on nothing: name one quantity ({', '.join(QUANTITIES)})")
        if len(named) > 1:
            raise reader.fail(where, f"one quantity per term, got {', '.join(named)}")
        quantity = named[0]
        kind = {"control": "actuator", "site_position": "site", "site_distance": "site"}.get(quantity, "joint")
        value = entry[quantity]
        wanted = reader.names(value, f"{where}.{quantity}") if quantity == "site_distance" else [
            reader.text(value, f"{where}.{quantity}")]  # fmt: skip
        if quantity == "site_distance" and len(wanted) != 2:
            raise reader.fail(f"{where}.{quantity}", f"must name two sites, got {wanted!r}")
        for name in wanted:
            if name not in ids[kind]:
                known = ", ".join(sorted(n for n in ids[kind] if n)) or "none"
                raise reader.fail(f"{where}.{quantity}", f"unknown {kind} {name!r} (the model's: {known})")
        axis = 0
        if quantity == "site_position":
            axis_name = entry.get("axis")
            if axis_name not in ("x", "y", "z"):
                raise reader.fail(f"{where}.axis", f"site_position needs axis x, y or z, got {axis_name!r}")
            axis = "xyz".index(axis_name)
        elif "axis" in entry:
            raise reader.fail(f"{where}.axis", "only site_position terms have an axis")
        bounds = reader.interval(entry.get("bounds", [0.0, 0.0]), f"{where}.bounds")
        margin = reader.number(entry.get("margin", 0.0), f"{where}.margin")
        if margin < 0:
            raise reader.fail(f"{where}.margin", f"must be >= 0, got {margin:g}")
        sigmoid = entry.get("sigmoid", "gaussian")
        if sigmoid not in SIGMOIDS:
            raise reader.fail(f"{where}.sigmoid", f"unknown sigmoid {sigmoid!r}; known: {', '.join(SIGMOIDS)}")
        at_margin = reader.number(entry.get("value_at_margin", 0.1), f"{where}.value_at_margin")
        if margin > 0 and not 0 < at_margin < 1 and sigmoid not in ("linear", "quadratic", "cosine"):
            raise reader.fail(f"{where}.value_at_margin", f"must lie in (0, 1) for a {sigmoid} sigmoid")
        weight = reader.number(entry.get("weight", 1.0), f"{where}.weight", positive=True)
        if not weighted and "weight" in entry:
            raise reader.fail(f"{where}.weight", 'weights apply to combine = "sum" only')
        target = tuple(ids[kind][name] for name in wanted)
        out.append(Term(quantity, target, axis, bounds, margin, sigmoid, at_margin, weight,
                        f"{quantity} {'-'.join(wanted)}"))  # fmt: skip
    return tuple(out)


# ----------------------------------------------------------------------------- quantities and rewards
def _quantity(term: Term, physics: Any) -> float:
    """The term's quantity in the physics' current state (kinematics up to date, as after a step)."""
    data = physics.data
    model = physics.model
    if term.quantity == "joint_position":
        return float(data.qpos[model.jnt_qposadr[term.target[0]]])
    if term.quantity == "joint_velocity":
        return float(data.qvel[model.jnt_dofadr[term.target[0]]])
    if term.quantity == "site_position":
        return float(data.site_xpos[term.target[0], term.axis])
    if term.quantity == "site_distance":
        return float(np.linalg.norm(data.site_xpos[term.target[0]] - data.site_xpos[term.target[1]]))
    return float(data.ctrl[term.target[0]])


@dataclass(frozen=True)
class TermReward:
    """The file's reward: a sum (weighted) or product of tolerance terms, read from the physics after a step."""

    terms: tuple[Term, ...]
    combine: str

    def get_reward(self, physics: Any) -> float:
        from dm_control.utils.rewards import tolerance

        values = [
            float(tolerance(_quantity(t, physics), t.bounds, t.margin, t.sigmoid, t.value_at_margin))
            for t in self.terms
        ]
        if self.combine == "product":
            return float(np.prod(values))
        return float(sum(t.weight * v for t, v in zip(self.terms, values, strict=True)))

    def bounds(self) -> tuple[float, float]:
        """The reward's range: [0, 1] for a product, [0, sum of weights] for a sum."""
        return (0.0, 1.0) if self.combine == "product" else (0.0, float(sum(t.weight for t in self.terms)))


@dataclass(frozen=True)
class FunctionReward:
    """The file's ``reward.function``: module:function called as function(physics) -> float."""

    target: str
    function: Callable[[Any], float]

    def get_reward(self, physics: Any) -> float:
        return float(self.function(physics))


# ----------------------------------------------------------------------------- the definition
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
    lipschitz: float | None
    certify: str
    joint_names: tuple[str, ...]
    actuator_names: tuple[str, ...]
    actuated_joint_names: tuple[str, ...]
    wrapped: tuple[int, ...]  # qpos indices stored wrapped
    rho_low: FloatArray
    rho_high: FloatArray
    reward: TermReward | FunctionReward
    cost_terms: tuple[Term, ...]
    expert: dict[str, Any] = field(default_factory=dict)

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
        return f"qpos then qvel of {', '.join(self.joint_names)}{wrapped}"

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


def _hinge_or_slide(reader: _Reader, model: Any) -> None:
    import mujoco

    allowed = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
    for j in range(model.njnt):
        if int(model.jnt_type[j]) not in allowed:
            name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j)
            raise reader.fail("state.joints", f"joint {name!r} is a ball or free joint; the state [qpos, qvel] "
                              "needs hinge and slide joints only")  # fmt: skip
    if model.na:
        raise reader.fail("model", "actuators with activation state are not supported (the state is [qpos, qvel])")


def parse(path: Path, content: bytes) -> TaskDefinition:
    """The definition in ``content`` (the file at ``path``); TaskFileError naming the key on any problem."""
    import mujoco

    reader = _Reader(path)
    try:
        doc = tomllib.loads(content.decode())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise TaskFileError(f"task file {path}: not valid TOML: {exc}") from None
    reader.unknown_keys(doc, TOP_KEYS, "")
    if "model" not in doc:
        raise reader.fail("model", "missing: name the MJCF file (relative to this file)")
    model_path = (path.parent / reader.text(doc["model"], "model")).resolve()
    if not model_path.is_file():
        raise reader.fail("model", f"no model file at {model_path}")
    try:
        model = mujoco.MjModel.from_xml_path(str(model_path))
    except Exception as exc:  # MuJoCo's own parse error, in one line
        raise reader.fail("model", f"MuJoCo cannot load {model_path}: {' '.join(str(exc).split())}") from None
    _hinge_or_slide(reader, model)

    dt = float(model.opt.timestep)
    if "control_timestep" in doc:
        given = reader.number(doc["control_timestep"], "control_timestep", positive=True)
        if not math.isclose(given, dt, rel_tol=1e-9):
            raise reader.fail("control_timestep", f"{given:g} s differs from the model's timestep {dt:g} s: one "
                              "control step is one MuJoCo step; set <option timestep> in the model")  # fmt: skip
    horizon = int(reader.number(doc.get("horizon", 1000), "horizon", positive=True))
    try:
        check_horizon(horizon)
    except ValueError as exc:
        raise reader.fail("horizon", str(exc)) from None
    epsilon = reader.number(doc["epsilon"], "epsilon", positive=True) if "epsilon" in doc else None
    lipschitz = reader.number(doc["lipschitz"], "lipschitz", positive=True) if "lipschitz" in doc else None
    certify = doc.get("certify", "oracle")
    if certify not in CERTIFY_MODES:
        raise reader.fail("certify", f"must be one of {', '.join(CERTIFY_MODES)}, got {certify!r}")

    joints = _model_ids(model, "joint")
    model_joints = [n for n, _ in sorted(joints.items(), key=lambda item: item[1])]
    state = reader.table(doc.get("state", {}), "state")
    reader.unknown_keys(state, {"joints", "wrap"}, "state.")
    if "joints" not in state:
        raise reader.fail("state.joints", f"missing: list the model's joints ({', '.join(model_joints)})")
    listed = reader.names(state["joints"], "state.joints")
    for name in listed:
        if name not in joints:
            raise reader.fail("state.joints", f"unknown joint {name!r} (the model's: {', '.join(model_joints)})")
    if listed != model_joints:
        raise reader.fail("state.joints", f"must list every joint of the model in its order: {model_joints}, got "
                          f"{listed} (the iLQR expert optimises the whole [qpos, qvel])")  # fmt: skip
    wrapped = []
    for name in reader.names(state.get("wrap", []), "state.wrap"):
        if name not in joints:
            raise reader.fail("state.wrap", f"unknown joint {name!r} (the model's: {', '.join(model_joints)})")
        if int(model.jnt_type[joints[name]]) != int(mujoco.mjtJoint.mjJNT_HINGE):
            raise reader.fail("state.wrap", f"joint {name!r} is not a hinge: only angles wrap")
        wrapped.append(int(model.jnt_qposadr[joints[name]]))

    actuators = _model_ids(model, "actuator")
    actuator_names = tuple(n for n, _ in sorted(actuators.items(), key=lambda item: item[1]))
    if not actuator_names:
        raise reader.fail("model", "the model has no actuator: nothing for a policy to do")
    if "actuators" in doc:
        given_actuators = reader.names(doc["actuators"], "actuators")
        for name in given_actuators:
            if name not in actuators:
                raise reader.fail("actuators", f"unknown actuator {name!r} (the model's: {', '.join(actuator_names)})")
        if tuple(given_actuators) != actuator_names:
            raise reader.fail("actuators", f"must be the model's actuators in order: {list(actuator_names)}")
    actuated = []
    for i, name in enumerate(actuator_names):
        if int(model.actuator_trntype[i]) != int(mujoco.mjtTrn.mjTRN_JOINT):
            raise reader.fail("actuators", f"actuator {name!r} does not drive a joint (the action message names "
                              "each actuator's joint)")  # fmt: skip
        actuated.append(model_joints[int(model.actuator_trnid[i, 0])])

    if "rho" not in doc:
        raise reader.fail("rho", "missing: give each joint's initial position range, e.g. hinge = { position = "
                          "[-3.14, 3.14] }")  # fmt: skip
    rho = reader.table(doc["rho"], "rho")
    if not rho:
        raise reader.fail("rho", "is empty: give at least one joint's position or velocity range")
    n = len(model_joints)
    low = np.concatenate([np.asarray(model.qpos0, dtype=np.float64), np.zeros(n)])
    high = low.copy()
    for name, ranges in rho.items():
        if name not in joints:
            raise reader.fail(f"rho.{name}", f"unknown joint {name!r} (the model's: {', '.join(model_joints)})")
        ranges = reader.table(ranges, f"rho.{name}")
        reader.unknown_keys(ranges, {"position", "velocity"}, f"rho.{name}.")
        if not ranges:
            raise reader.fail(f"rho.{name}", "is empty: give position = [low, high] and/or velocity = [low, high]")
        j = joints[name]
        for key, index in (("position", int(model.jnt_qposadr[j])), ("velocity", n + int(model.jnt_dofadr[j]))):
            if key in ranges:
                low[index], high[index] = reader.interval(ranges[key], f"rho.{name}.{key}")

    reward_table = reader.table(doc.get("reward", {}), "reward")
    reader.unknown_keys(reward_table, {"combine", "terms", "function"}, "reward.")
    combine = reward_table.get("combine", "product")
    if combine not in ("sum", "product"):
        raise reader.fail("reward.combine", f"must be sum or product, got {combine!r}")
    reward: TermReward | FunctionReward
    if "function" in reward_table:
        if "terms" in reward_table:
            raise reader.fail("reward", "give terms or a function, not both")
        reward = FunctionReward(*_function(reader, reward_table["function"]))
    elif "terms" in reward_table:
        reward = TermReward(_terms(reader, reward_table["terms"], "reward.terms", model, combine == "sum"), combine)
    else:
        raise reader.fail("reward", "missing: give [[reward.terms]] (tolerance terms) or function = 'module:function'")

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
    if expert.get("values", "window") not in VALUE_MODES:
        raise reader.fail("expert.values", f"must be one of {', '.join(VALUE_MODES)}, got {expert['values']!r}")
    options["values"] = expert.get("values", "window")
    if expert.get("warm_start", "zero") not in WARM_STARTS:
        raise reader.fail("expert.warm_start", f"must be one of {', '.join(WARM_STARTS)}")
    for key, default in (("control_weight", 1e-3), ("velocity_weight", 1e-4)):
        options[key] = reader.number(expert.get(key, default), f"expert.{key}")
        if options[key] < 0:
            raise reader.fail(f"expert.{key}", f"must be >= 0, got {options[key]:g}")
    if "terms" in expert:
        cost_terms = _terms(reader, expert["terms"], "expert.terms", model, True)
    elif isinstance(reward, TermReward):
        cost_terms = reward.terms
    else:
        raise reader.fail("expert.terms", "a reward function needs [[expert.terms]]: the iLQR expert's smooth cost")

    label = doc.get("name", path.parent.name or path.stem)
    return TaskDefinition(
        path=path, sha256=hashlib.sha256(content).hexdigest(), label=reader.text(label, "name"),
        model_path=model_path, dt=dt, horizon=horizon, epsilon=epsilon, lipschitz=lipschitz, certify=certify,
        joint_names=tuple(model_joints), actuator_names=actuator_names, actuated_joint_names=tuple(actuated),
        wrapped=tuple(wrapped), rho_low=low, rho_high=high, reward=reward, cost_terms=cost_terms, expert=options,
    )  # fmt: skip


def _function(reader: _Reader, target: Any) -> tuple[str, Callable[[Any], float]]:
    text = reader.text(target, "reward.function")
    module, _, attribute = text.partition(":")
    if not module or not attribute:
        raise reader.fail("reward.function", f"must be 'module:function', got {text!r}")
    try:
        function = getattr(importlib.import_module(module), attribute)
    except Exception as exc:
        raise reader.fail("reward.function", f"{text} does not load: {type(exc).__name__}: {exc}") from None
    if not callable(function):
        raise reader.fail("reward.function", f"{text} is not callable")
    return text, function


# ----------------------------------------------------------------------------- plant, cost, expert
class FilePlant(SuitePlant):
    """The file's model stepped one MuJoCo step per control step, its reward from the file."""

    def __init__(self, definition: TaskDefinition, seed: int = 0) -> None:
        os.environ.setdefault("MUJOCO_GL", "disable")
        from dm_control import mujoco as dm_mujoco

        self.definition = definition
        self.task = definition.name
        self.state_entries = definition.stored_state()
        self.fingerprint_fields = FINGERPRINT_FIELDS
        self.represent = definition.represent  # type: ignore[method-assign]  # the file's wrapping, per instance
        self.angles = tuple(definition.wrapped)
        self.seed = int(seed)
        self.physics = dm_mujoco.Physics.from_xml_path(str(definition.model_path))
        self._task = definition.reward
        model = self.physics.model
        self.dt = float(model.opt.timestep)
        self.positions = int(model.nq)
        self.state_dim = int(model.nq + model.nv)
        self.action_dim = int(model.nu)
        self.joint_names = list(definition.joint_names)
        self.actuated_joint_names = list(definition.actuated_joint_names)
        self.action_low = np.where(model.actuator_ctrllimited, model.actuator_ctrlrange[:, 0], -np.inf)
        self.action_high = np.where(model.actuator_ctrllimited, model.actuator_ctrlrange[:, 1], np.inf)
        self.steps = 0


class TermCost:
    """The iLQR expert's smooth cost from tolerance terms: 0.5 w ((q - clip(q, bounds)) / scale)^2 each.

    scale is the term's margin (1 without one). Zero exactly where the term's tolerance is 1, and
    its gradient points there from anywhere (a Gaussian tolerance is flat far from its bounds).
    State terms are differentiated through MuJoCo's kinematics (site Jacobians); the Hessian is
    Gauss-Newton. Small velocity and control weights keep the problem well posed.
    """

    def __init__(self, terms: tuple[Term, ...], model: Any, options: dict[str, Any]) -> None:
        import mujoco

        self._mujoco = mujoco
        self.model = model
        self.data = mujoco.MjData(model)
        self.nq, self.nu = int(model.nq), int(model.nu)
        self.state_terms_list = [t for t in terms if not t.on_control]
        self.control_terms_list = [t for t in terms if t.on_control]
        self.velocity_weight = float(options.get("velocity_weight", 1e-4))
        self.control_weight = float(options.get("control_weight", 1e-3))
        self._jac = np.zeros((3, model.nv))
        self._jac2 = np.zeros((3, model.nv))

    @staticmethod
    def _residual(term: Term, q: float) -> float:
        scale = term.margin if term.margin > 0 else 1.0
        low, high = term.bounds
        return (q - min(max(q, low), high)) / scale

    def _site_jacobian(self, site: int, out: FloatArray) -> None:
        self._mujoco.mj_jacSite(self.model, self.data, out, None, site)

    def _value_and_gradient(self, term: Term, x: FloatArray) -> tuple[float, FloatArray]:
        """The term's quantity at x (kinematics already at x) and its gradient in x = [qpos, qvel]."""
        n = 2 * self.nq
        grad = np.zeros(n)
        model, data = self.model, self.data
        if term.quantity == "joint_position":
            index = int(model.jnt_qposadr[term.target[0]])
            grad[index] = 1.0
            return float(x[index]), grad
        if term.quantity == "joint_velocity":
            index = self.nq + int(model.jnt_dofadr[term.target[0]])
            grad[index] = 1.0
            return float(x[index]), grad
        if term.quantity == "site_position":
            self._site_jacobian(term.target[0], self._jac)
            grad[: self.nq] = self._jac[term.axis]
            return float(data.site_xpos[term.target[0], term.axis]), grad
        a, b = term.target
        delta = data.site_xpos[a] - data.site_xpos[b]
        distance = float(np.linalg.norm(delta))
        if distance > 1e-12:
            self._site_jacobian(a, self._jac)
            self._site_jacobian(b, self._jac2)
            grad[: self.nq] = delta @ (self._jac - self._jac2) / distance
        return distance, grad

    def state_terms(self, states: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        count, n = len(states), 2 * self.nq
        value = 0.5 * self.velocity_weight * np.sum(states[:, self.nq :] ** 2, axis=1)
        grad = np.zeros((count, n))
        grad[:, self.nq :] = self.velocity_weight * states[:, self.nq :]
        hess = np.zeros((count, n, n))
        hess[:, np.arange(self.nq, n), np.arange(self.nq, n)] = self.velocity_weight
        if not self.state_terms_list:
            return value, grad, hess
        mj, model, data = self._mujoco, self.model, self.data
        for k in range(count):
            data.qpos[:] = states[k, : self.nq]
            data.qvel[:] = states[k, self.nq :]
            mj.mj_kinematics(model, data)
            mj.mj_comPos(model, data)
            for term in self.state_terms_list:
                q, dq = self._value_and_gradient(term, states[k])
                scale = term.margin if term.margin > 0 else 1.0
                e = self._residual(term, q)
                value[k] += 0.5 * term.weight * e * e
                if e != 0.0:
                    grad[k] += term.weight * e / scale * dq
                    hess[k] += term.weight / (scale * scale) * np.outer(dq, dq)
        return value, grad, hess

    def state_values(self, states: FloatArray) -> FloatArray:
        """state_terms' values alone, the same numbers: the line search needs no Jacobians, nor the
        centre-of-mass pass they need (site positions come from the kinematics alone)."""
        value = 0.5 * self.velocity_weight * np.sum(states[:, self.nq :] ** 2, axis=1)
        if not self.state_terms_list:
            return value
        mj, model, data = self._mujoco, self.model, self.data
        for k in range(len(states)):
            data.qpos[:] = states[k, : self.nq]
            mj.mj_kinematics(model, data)
            for term in self.state_terms_list:
                e = self._residual(term, self._quantity(term, states[k]))
                value[k] += 0.5 * term.weight * e * e
        return value

    def _quantity(self, term: Term, x: FloatArray) -> float:
        """The term's quantity at x (kinematics already at x), as _value_and_gradient computes it."""
        model, site_xpos = self.model, self.data.site_xpos
        if term.quantity == "joint_position":
            return float(x[int(model.jnt_qposadr[term.target[0]])])
        if term.quantity == "joint_velocity":
            return float(x[self.nq + int(model.jnt_dofadr[term.target[0]])])
        if term.quantity == "site_position":
            return float(site_xpos[term.target[0], term.axis])
        a, b = term.target
        return float(np.linalg.norm(site_xpos[a] - site_xpos[b]))

    def control_terms(self, actions: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        count, m = actions.shape
        value = 0.5 * self.control_weight * np.sum(actions * actions, axis=1)
        grad = self.control_weight * actions.copy()
        hess = np.broadcast_to(self.control_weight * np.eye(m), (count, m, m)).copy()
        for term in self.control_terms_list:
            j = term.target[0]
            scale = term.margin if term.margin > 0 else 1.0
            low, high = term.bounds
            e = (actions[:, j] - np.clip(actions[:, j], low, high)) / scale
            value += 0.5 * term.weight * e * e
            grad[:, j] += term.weight * e / scale
            hess[:, j, j] += np.where(e != 0.0, term.weight / (scale * scale), 0.0)
        return value, grad, hess


class FileExpert(OptimizingExpert):
    """The iLQR expert on the file's model, its smooth cost from the file's terms, warm-started at u = 0."""

    def __init__(
        self,
        definition: TaskDefinition,
        seed: int = 0,
        horizon: int | None = None,
        time_budget: float = 5.0,
        max_iterations: int = 30,
        values: str = "window",
    ) -> None:
        plant = FilePlant(definition, seed)
        zero = np.zeros(plant.action_dim)
        super().__init__(
            plant,
            TermCost(definition.cost_terms, plant.physics.model.ptr, definition.expert),
            lambda _x: zero,
            definition.represent,
            horizon=definition.horizon if horizon is None else horizon,
            time_budget=time_budget,
            max_iterations=max_iterations,
            values=values,
        )
        self.seed = int(seed)
        self.task = definition.name
        self.reward_lipschitz_detail = "not computed for a task file's reward"


@dataclass(frozen=True)
class FileTask(OptimizerTask):
    """A task from a file: its plant, its iLQR expert, its rho and its defaults, as the file says."""

    definition: TaskDefinition | None = None

    def make_plant(self, seed: int) -> FilePlant:
        assert self.definition is not None
        return FilePlant(self.definition, seed)

    def make_expert(self, seed: int, horizon: int, options: ExpertOptions = DEFAULT_OPTIONS) -> Expert:
        assert self.definition is not None
        self.expert_kind(options)
        if options.gamma != 1.0:
            raise ValueError(
                f"the {self.definition.label} expert computes undiscounted H-step returns; gamma must be 1"
            )
        own = self.definition.expert
        expert = FileExpert(
            self.definition, seed, check_horizon(horizon),
            time_budget=options.time_budget or own.get("time_budget", self.default_time_budget),
            max_iterations=options.max_iterations or own.get("max_iterations", 30),
            values=options.values or own.get("values", "window"),
        )  # fmt: skip
        if options.threads is not None:
            expert.optimizer.dynamics.threads = options.threads
        return expert

    def sample_initial_state(self, rng: np.random.Generator) -> FloatArray:
        assert self.definition is not None
        return self.definition.sample_initial_state(rng)

    def epsilon(self, given: float | None) -> float:
        if given is not None:
            return float(given)
        if self.definition is None or self.definition.epsilon is None:
            raise ValueError("the task file gives no epsilon; give one")
        return self.definition.epsilon


def split_name(name: str) -> tuple[Path, str | None]:
    """A task file's path (absolute) and the content hash its name asks for (None: whatever the file holds)."""
    path, mark, digest = name.partition(HASH_MARK)
    return Path(path).expanduser().resolve(), digest if mark else None


def load_task_file(name: str) -> FileTask:
    """The task in a file, by path or by the name a sim published (path and content hash).

    A file whose content differs from the hash in the name is refused, naming both.
    """
    path, expected = split_name(name)
    try:
        content = path.read_bytes()
    except OSError as exc:
        raise TaskFileError(f"task file {path}: cannot be read: {exc.strerror or exc}") from None
    digest = hashlib.sha256(content).hexdigest()
    if expected is not None and digest != expected:
        raise TaskFileError(
            f"task file mismatch: the task is {path}{HASH_MARK}{expected[:16]}..., but the file at that path now holds "
            f"{path}{HASH_MARK}{digest[:16]}...: the processes of a run must read the same task file"
        )
    return _task(path, digest, content)


@functools.lru_cache(maxsize=32)
def _task(path: Path, digest: str, content: bytes) -> FileTask:
    definition = parse(path, content)
    return FileTask(
        name=definition.name,
        state_dim=definition.state_dim,
        action_dim=definition.action_dim,
        stored_state=definition.stored_state(),
        initial_state_diameter=definition.initial_state_diameter(),
        default_certify=definition.certify,  # type: ignore[arg-type]  # checked against CERTIFY_MODES
        no_analytic_lipschitz="its iLQR expert computes no bound on its value's slope",
        paper_lipschitz=definition.lipschitz,
        paper_lipschitz_note="the task file's choice (its key lipschitz); not a bound on the expert's value",
        default_time_budget=definition.expert.get("time_budget", 5.0),
        default_horizon=definition.horizon,
        reward_range=definition.reward.bounds() if isinstance(definition.reward, TermReward) else None,
        definition=definition,
    )
