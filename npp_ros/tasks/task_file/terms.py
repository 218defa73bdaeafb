"""A task file's reward: tolerance terms on named quantities of the model, or a Python function.

A term is dm_control.utils.rewards.tolerance of one quantity: ``joint_position``, ``joint_velocity``
(a joint), ``site_position`` (a site, with ``axis`` x, y or z), ``site_distance`` (two sites) or
``control`` (an actuator, or a list of actuators: the mean of their tolerances, as dm_control's
``tolerance(physics.control(), ...).mean()``). A term's ``floor`` lifts its value to floor + (1 - floor) x
tolerance, dm_control's ``(4 + small_control) / 5`` with floor 0.8. The reward combines the terms as a
weighted sum or a product, computed from the physics after each step with the applied (clamped) control, as
dm_control's suite does. The same terms give the iLQR expert its smooth cost (npp_ros.tasks.task_file.cost).
The expert's own cost (``[[expert.terms]]``) may also use ``energy``: the model's mechanical energy (MuJoCo's
potential plus kinetic) less that of a named pose at rest, which an underactuated swing-up must pump before
it can catch. No reward is paid for energy.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from npp_ros.policy.dataset import FloatArray
from npp_ros.tasks.task_file.model import model_ids, named_objects
from npp_ros.tasks.task_file.reader import Reader

QUANTITIES = ("joint_position", "joint_velocity", "site_position", "site_distance", "control")
COST_QUANTITIES = ("energy",)  # the expert's cost only: no reward is paid for energy
SIGMOIDS = ("gaussian", "hyperbolic", "long_tail", "reciprocal", "cosine", "linear", "quadratic", "tanh_squared")
BOUNDED_SIGMOIDS = ("linear", "quadratic", "cosine")  # reach 0 at the margin: any value_at_margin will do
COMBINES = ("sum", "product")
REWARD_KEYS = {"combine", "terms", "function"}
TERM_KEYS = {*QUANTITIES, *COST_QUANTITIES, "axis", "bounds", "margin", "sigmoid", "value_at_margin", "weight", "floor",
             "hessian"}  # fmt: skip
# How the expert's cost takes a distance's curvature (npp_ros.tasks.task_file.cost.TermCost): "distance", the
# Gauss-Newton Hessian of the scalar distance (rank one), or "offset", that of the offset vector (rank three).
DISTANCE_HESSIANS = ("distance", "offset")
AXES = ("x", "y", "z")
DEFAULT_COMBINE = "product"
# dm_control's tolerance defaults
DEFAULT_BOUNDS = (0.0, 0.0)
DEFAULT_MARGIN = 0.0
DEFAULT_SIGMOID = "gaussian"
DEFAULT_VALUE_AT_MARGIN = 0.1
DEFAULT_WEIGHT = 1.0
DEFAULT_FLOOR = 0.0  # a term's value is floor + (1 - floor) x its tolerance


@dataclass(frozen=True)
class Term:
    """One tolerance term: which quantity, and dm_control's tolerance parameters."""

    quantity: str
    target: tuple[int, ...]  # joint, site or actuator ids (two sites for a distance; a control term's mean: several)
    axis: int
    bounds: tuple[float, float]
    margin: float
    sigmoid: str
    value_at_margin: float
    weight: float
    label: str
    floor: float = DEFAULT_FLOOR
    offset: float = 0.0  # subtracted from the quantity: an energy term's reference, the energy of its pose at rest
    hessian: str = "distance"  # a distance term in the expert's cost: one of DISTANCE_HESSIANS

    @property
    def on_control(self) -> bool:
        return self.quantity == "control"


# ----------------------------------------------------------------------------- reading the terms
def read_terms(
    reader: Reader, entries: Any, key: str, model: Any, weighted: bool, cost: bool = False
) -> tuple[Term, ...]:
    """The list of term tables at ``key``; ``weighted``: the terms are summed, so a weight is allowed;
    ``cost``: they are the expert's cost, so an ``energy`` term is allowed."""
    if not isinstance(entries, list) or not entries:
        raise reader.fail(key, "must be a non-empty list of terms ([[...]] tables)")
    ids = {kind: model_ids(model, kind) for kind in ("joint", "site", "actuator")}
    return tuple(
        _read_energy_term(reader, entry, f"{key}[{k}]", model, ids["joint"])
        if cost and isinstance(entry, dict) and "energy" in entry
        else _read_term(reader, entry, f"{key}[{k}]", ids, weighted, cost)
        for k, entry in enumerate(entries)
    )


def _read_term(
    reader: Reader, entry: Any, where: str, ids: dict[str, dict[str, int]], weighted: bool, cost: bool = False
) -> Term:
    entry = reader.table(entry, where)
    reader.unknown_keys(entry, TERM_KEYS, f"{where}.")
    if "energy" in entry:
        raise reader.fail(f"{where}.energy", "an energy term is the expert's cost only: write it in [[expert.terms]]")
    quantity, kind, wanted = _quantity_and_names(reader, entry, where, ids)
    axis = _axis(reader, entry, where, quantity)
    bounds = reader.interval(entry.get("bounds", list(DEFAULT_BOUNDS)), f"{where}.bounds")
    margin = reader.non_negative(entry.get("margin", DEFAULT_MARGIN), f"{where}.margin")
    sigmoid = entry.get("sigmoid", DEFAULT_SIGMOID)
    if sigmoid not in SIGMOIDS:
        raise reader.fail(f"{where}.sigmoid", f"unknown sigmoid {sigmoid!r}; known: {', '.join(SIGMOIDS)}")
    at_margin = reader.number(entry.get("value_at_margin", DEFAULT_VALUE_AT_MARGIN), f"{where}.value_at_margin")
    if margin > 0 and not 0 < at_margin < 1 and sigmoid not in BOUNDED_SIGMOIDS:
        raise reader.fail(f"{where}.value_at_margin", f"must lie in (0, 1) for a {sigmoid} sigmoid")
    weight = reader.number(entry.get("weight", DEFAULT_WEIGHT), f"{where}.weight", positive=True)
    if not weighted and "weight" in entry:
        raise reader.fail(f"{where}.weight", 'weights apply to combine = "sum" only')
    floor = reader.non_negative(entry.get("floor", DEFAULT_FLOOR), f"{where}.floor")
    if floor >= 1:
        raise reader.fail(f"{where}.floor", f"must lie in [0, 1), got {floor!r}")
    hessian = entry.get("hessian", DISTANCE_HESSIANS[0])
    if "hessian" in entry:
        if not cost or quantity != "site_distance":
            raise reader.fail(f"{where}.hessian", "applies to a site_distance term of [[expert.terms]] only")
        if hessian not in DISTANCE_HESSIANS:
            raise reader.fail(f"{where}.hessian", f"must be one of {', '.join(DISTANCE_HESSIANS)}, got {hessian!r}")
    target = tuple(ids[kind][name] for name in wanted)
    label = f"{quantity} {'-'.join(wanted)}"
    return Term(quantity, target, axis, bounds, margin, sigmoid, at_margin, weight, label, floor, hessian=hessian)


ENERGY_KEYS = {"energy", "bounds", "margin", "weight"}


def _read_energy_term(reader: Reader, entry: dict[str, Any], where: str, model: Any, joints: dict[str, int]) -> Term:
    """``energy = { joint = position, ... }``: the energy less that of this pose at rest (joints it does not
    name at the model's qpos0), with ``bounds`` (J, default [0, 0]), ``margin`` (J, the penalty's scale)
    and ``weight``."""
    reader.unknown_keys(entry, ENERGY_KEYS, f"{where}.")
    key = f"{where}.energy"
    pose = reader.table(entry["energy"], key)
    qpos = np.array(model.qpos0, dtype=np.float64)
    for name, position in pose.items():
        named_objects(reader, name, key, joints, "joint", pair=False)
        qpos[int(model.jnt_qposadr[joints[name]])] = reader.number(position, f"{key}.{name}")
    bounds = reader.interval(entry.get("bounds", list(DEFAULT_BOUNDS)), f"{where}.bounds")
    margin = reader.non_negative(entry.get("margin", DEFAULT_MARGIN), f"{where}.margin")
    weight = reader.number(entry.get("weight", DEFAULT_WEIGHT), f"{where}.weight", positive=True)
    label = "energy at " + (", ".join(f"{name} = {value:g}" for name, value in pose.items()) or "qpos0")
    return Term(
        "energy", (), 0, bounds, margin, DEFAULT_SIGMOID, DEFAULT_VALUE_AT_MARGIN, weight, label,
        offset=mechanical_energy(model, qpos, np.zeros(model.nv)),
    )  # fmt: skip


def mechanical_energy(model: Any, qpos: FloatArray, qvel: FloatArray, data: Any = None) -> float:
    """MuJoCo's potential (gravity and springs) plus kinetic energy at (qpos, qvel), in J."""
    import mujoco

    data = mujoco.MjData(model) if data is None else data
    data.qpos[:] = qpos
    data.qvel[:] = qvel
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)
    mujoco.mj_makeM(model, data)
    mujoco.mj_energyPos(model, data)
    mujoco.mj_energyVel(model, data)
    return float(data.energy[0] + data.energy[1])


def _quantity_and_names(
    reader: Reader, entry: dict[str, Any], where: str, ids: dict[str, dict[str, int]]
) -> tuple[str, str, list[str]]:
    """The term's one quantity, the kind of model object it is on, and the object(s) it names."""
    named = [q for q in QUANTITIES if q in entry]
    if not named:
        raise reader.fail(where, f"the term is on nothing: name one quantity ({', '.join(QUANTITIES)})")
    if len(named) > 1:
        raise reader.fail(where, f"one quantity per term, got {', '.join(named)}")
    quantity = named[0]
    kind = {"control": "actuator", "site_position": "site", "site_distance": "site"}.get(quantity, "joint")
    key = f"{where}.{quantity}"
    if quantity == "control" and isinstance(entry[quantity], list):  # the mean over these actuators
        names = reader.names(entry[quantity], key)
        if not names:
            raise reader.fail(key, "must name at least one actuator")
        return quantity, kind, [named_objects(reader, name, key, ids[kind], kind, pair=False)[0] for name in names]
    wanted = named_objects(reader, entry[quantity], key, ids[kind], kind, pair=quantity == "site_distance")
    return quantity, kind, wanted


def _axis(reader: Reader, entry: dict[str, Any], where: str, quantity: str) -> int:
    """The axis of a site_position term (0, 1, 2 for x, y, z); other terms have none (0)."""
    if quantity == "site_position":
        axis_name = entry.get("axis")
        if axis_name not in AXES:
            raise reader.fail(f"{where}.axis", f"site_position needs axis x, y or z, got {axis_name!r}")
        return AXES.index(axis_name)
    if "axis" in entry:
        raise reader.fail(f"{where}.axis", "only site_position terms have an axis")
    return 0


# ----------------------------------------------------------------------------- the reward
def quantity(term: Term, physics: Any) -> float:
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


def term_value(term: Term, physics: Any) -> float:
    """The term's tolerance (a control term over several actuators: their mean), lifted by its floor."""
    from dm_control.utils.rewards import tolerance

    if term.on_control:
        values = np.asarray(physics.data.ctrl)[list(term.target)]
    else:
        values = np.array([quantity(term, physics)])
    tol = float(np.mean(tolerance(values, term.bounds, term.margin, term.sigmoid, term.value_at_margin)))
    return term.floor + (1.0 - term.floor) * tol


@dataclass(frozen=True)
class TermReward:
    """The file's reward: a sum (weighted) or product of tolerance terms, read from the physics after a step."""

    terms: tuple[Term, ...]
    combine: str

    def get_reward(self, physics: Any) -> float:
        values = [term_value(t, physics) for t in self.terms]
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


def read_reward(reader: Reader, doc: dict[str, Any], model: Any) -> TermReward | FunctionReward:
    """``[reward]``: tolerance terms and how they combine, or a function."""
    table = reader.table(doc.get("reward", {}), "reward")
    reader.unknown_keys(table, REWARD_KEYS, "reward.")
    combine = table.get("combine", DEFAULT_COMBINE)
    if combine not in COMBINES:
        raise reader.fail("reward.combine", f"must be sum or product, got {combine!r}")
    if "function" in table:
        if "terms" in table:
            raise reader.fail("reward", "give terms or a function, not both")
        return FunctionReward(*_function(reader, table["function"]))
    if "terms" in table:
        return TermReward(read_terms(reader, table["terms"], "reward.terms", model, combine == "sum"), combine)
    raise reader.fail("reward", "missing: give [[reward.terms]] (tolerance terms) or function = 'module:function'")


def _function(reader: Reader, target: Any) -> tuple[str, Callable[[Any], float]]:
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
