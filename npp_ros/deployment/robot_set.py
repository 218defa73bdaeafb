"""Whether a robot's model lies inside the set of robots a run was certified on, compared from its MJCF.

A run made with model uncertainty certifies a set of robots (its metadata's ``uncertainty``,
npp_ros.tasks.uncertainty), not one model, so the gate cannot ask for the certified fingerprint: a robot
whose masses differ by 10% from the model's is one the certificate covers. :func:`match_model` compares
the robot's compiled model with the certified one:

- structure exactly: the same bodies, joints and actuators, by name, in the same order, and the same sizes;
- each uncertain parameter (``PARAMETERS``) as the ratio robot / nominal per element, inside the range the
  set certifies for it (within ``RELATIVE_TOLERANCE``); an element the set does not name must be nominal, and
  a parameter the model sets to zero must stay zero (a scale cannot move it);
- every other dynamics array (``COMPARED``) equal to ``RELATIVE_TOLERANCE``.

A description cannot show a delay or the noise on states; those the monitor watches (model_monitor.py). An
exact-model certificate still needs the exact model's fingerprint (gate.py): this module is only asked for
a run that names a set.
"""

from __future__ import annotations

import math
import operator
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import Any

import numpy as np

from npp_ros.deployment.robot_model import DescriptionError, model_mjcf
from npp_ros.run.records import RunMetadata
from npp_ros.tasks.registry import Plant
from npp_ros.tasks.uncertainty import PARAMETERS, ModelParameters, Robot, ScaleRange, UncertaintySet, model_elements

# MuJoCo's own XML writer keeps 6 significant digits (relative error up to 5e-6): a description it wrote still
# matches, and no range a certificate names is that narrow.
RELATIVE_TOLERANCE = 1e-5
ABSOLUTE_TOLERANCE = 1e-12  # for entries that are zero in one model and rounding noise in the other

# The arrays of a compiled model that define its dynamics; the uncertain ones are compared as ratios instead.
SCALED = ("body_mass", "body_inertia", "dof_damping", "dof_frictionloss", "dof_armature")
COMPARED = (
    "opt.timestep", "opt.gravity", "opt.integrator", "opt.wind", "opt.density", "opt.viscosity", "jnt_type",
    "jnt_stiffness", "jnt_range", "jnt_limited", "jnt_axis", "jnt_pos", "qpos0", "qpos_spring", "body_parentid",
    "body_ipos", "body_iquat", "body_pos", "body_quat", "geom_type", "geom_size", "geom_pos", "geom_quat",
    "geom_contype", "geom_conaffinity", "geom_friction", "site_pos", "actuator_trntype", "actuator_trnid",
    "actuator_ctrlrange", "actuator_ctrllimited", "actuator_forcerange", "actuator_forcelimited",
    "actuator_gainprm", "actuator_biasprm", "actuator_dyntype", "actuator_gaintype", "actuator_biastype",
    "tendon_stiffness", "tendon_damping", "tendon_lengthspring", "eq_data", "opt.disableflags", "opt.enableflags",
)  # fmt: skip
UNITS = {"mass": "kg", "gear": "", "damping": "", "frictionloss": "", "armature": ""}


@dataclass(frozen=True)
class RobotMatch:
    """A robot's model against a certified set: the robot it is (its scales of the nominal model) and why it
    lies outside the set (none: inside)."""

    robot: Robot
    reasons: tuple[str, ...]

    @property
    def inside(self) -> bool:
        return not self.reasons

    def describe(self) -> str:
        """The robot in words: its parameters that differ from the nominal model."""
        changed = [(p, n, f) for p, n, f in self.robot.scales if abs(f - 1) > RELATIVE_TOLERANCE]
        if not changed:
            return "the nominal model"
        return "the nominal model with " + ", ".join(f"{p} of {n} x{f:.4g}" for p, n, f in changed)


def compiled(mjcf: str) -> Any:
    """The MuJoCo model an MJCF text compiles to; a DescriptionError with MuJoCo's first line when it does not."""
    import mujoco

    try:
        return mujoco.MjModel.from_xml_string(mjcf)
    except Exception as exc:  # MuJoCo's XML and compile errors are plain ValueErrors with the line
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DescriptionError(f"it does not compile as a MuJoCo model (MJCF): {first}") from None


def _raw(model: Any) -> Any:
    return getattr(model, "ptr", model)


def match_model(nominal: Any, robot: Any, robots: UncertaintySet) -> RobotMatch:
    """``robot`` (a compiled model) against the set ``robots`` of scales of ``nominal``; see the module's rules."""
    nominal, robot = _raw(nominal), _raw(robot)
    structure = structure_reasons(nominal, robot)
    if structure:
        return RobotMatch(Robot(), tuple(structure))
    ranges = {(s.parameter, name): s for s in robots.resolved(nominal).scales for name in s.names}
    elements = model_elements(nominal)
    scales: list[tuple[str, str, float]] = []
    reasons: list[str] = []
    for parameter, (kind, _) in PARAMETERS.items():
        for index, name in enumerate(elements[kind]):
            now, was = _value(robot, parameter, index), _value(nominal, parameter, index)
            scale = ranges.get((parameter, name), ScaleRange(parameter, 1.0, 1.0, (name,)))
            factor, why = _ratio(now, was)
            if why:
                reasons.append(f"{parameter} of {kind} {name}: {why}")
                continue
            scales.append((parameter, name, factor))
            if not scale.low * (1 - RELATIVE_TOLERANCE) <= factor <= scale.high * (1 + RELATIVE_TOLERANCE):
                unit = f" {UNITS[parameter]}" if UNITS[parameter] else ""
                reasons.append(
                    f"{parameter} of {kind} {name}: the robot's {now:.6g}{unit} is x{factor:.4g} the certified "
                    f"{was:.6g}{unit}, outside the certified range x[{scale.low:g}, {scale.high:g}]"
                )
    reasons += _inertia_reasons(nominal, robot, elements["body"])
    reasons += _other_reasons(nominal, robot)
    return RobotMatch(Robot(tuple(scales)), tuple(reasons))


def structure_reasons(nominal: Any, robot: Any) -> list[str]:
    """Why ``robot``'s structure (bodies, joints, actuators, their order and sizes) is not ``nominal``'s; none when it
    is. Compiled models, or their dm_control wrappers."""
    nominal, robot = _raw(nominal), _raw(robot)
    mine, theirs = model_elements(robot), model_elements(nominal)
    reasons = [
        f"its {kind}s are {', '.join(mine[kind]) or 'none'}, the certified model's {', '.join(theirs[kind]) or 'none'}"
        for kind in ("body", "joint", "actuator")
        if mine[kind] != theirs[kind]
    ]
    for size in ("nq", "nv", "nu", "na", "ngeom", "nsite", "ntendon", "neq"):
        if getattr(robot, size) != getattr(nominal, size):
            reasons.append(f"its {size} is {getattr(robot, size)}, the certified model's {getattr(nominal, size)}")
    if not reasons and not np.array_equal(robot.jnt_dofadr, nominal.jnt_dofadr):
        reasons.append("its joints' degrees of freedom are not the certified model's")
    return [f"its structure is not the certified model's: {reason}" for reason in reasons]


def _value(model: Any, parameter: str, index: int) -> float:
    if parameter == "mass":
        return float(model.body_mass[index + 1])  # the world body is not an element
    if parameter == "gear":
        return float(model.actuator_gear[index, 0])
    return float(getattr(model, f"dof_{parameter}")[int(model.jnt_dofadr[index])])


def _ratio(now: float, was: float) -> tuple[float, str]:
    """robot / nominal, 1 for a zero that stayed zero; a reason when a scale cannot give ``now``."""
    if abs(was) <= ABSOLUTE_TOLERANCE:
        if abs(now) <= ABSOLUTE_TOLERANCE:
            return 1.0, ""
        return math.nan, f"the robot's {now:.6g} where the certified model has 0 (a scale keeps a zero at zero)"
    factor = now / was
    if not factor > 0:
        return math.nan, f"the robot's {now:.6g} against the certified {was:.6g} (not a positive scale)"
    return factor, ""


def _inertia_reasons(nominal: Any, robot: Any, bodies: tuple[str, ...]) -> list[str]:
    """A mass scale scales a body's inertia by the same factor (its density): any other inertia is another body."""
    reasons = []
    for index, name in enumerate(bodies, start=1):
        was, now = nominal.body_inertia[index], robot.body_inertia[index]
        mass_was, mass_now = float(nominal.body_mass[index]), float(robot.body_mass[index])
        factor = mass_now / mass_was if mass_was > ABSOLUTE_TOLERANCE else 1.0
        if not np.allclose(now, factor * was, rtol=RELATIVE_TOLERANCE, atol=ABSOLUTE_TOLERANCE):
            reasons.append(
                f"inertia of body {name}: the robot's {np.round(now, 8).tolist()} is not its mass's scale "
                f"x{factor:.4g} of the certified {np.round(was, 8).tolist()} (a mass scale scales the inertia with it)"
            )
    return reasons


def _other_reasons(nominal: Any, robot: Any) -> list[str]:
    """Every array the set leaves alone: equal to the tolerance (the gear's other entries too)."""
    reasons = []
    pairs = [(name, operator.attrgetter(name)) for name in COMPARED]
    pairs.append(("actuator_gear[:, 1:]", lambda m: np.asarray(m.actuator_gear)[:, 1:]))
    for name, get in pairs:
        try:
            was, now = np.asarray(get(nominal), dtype=np.float64), np.asarray(get(robot), dtype=np.float64)
        except AttributeError:
            continue  # not in this MuJoCo version's model
        if was.shape != now.shape:
            reasons.append(f"{name} has shape {now.shape}, the certified model's {was.shape}")
        elif not np.allclose(now, was, rtol=RELATIVE_TOLERANCE, atol=ABSOLUTE_TOLERANCE):
            where = int(np.argmax(np.abs(now - was).ravel()))
            reasons.append(
                f"{name} differs from the certified model's (entry {where}: the robot's {now.ravel()[where]:.6g}, "
                f"the certified {was.ravel()[where]:.6g}), and the certified set does not cover it"
            )
    return reasons


def robots_of(metadata: RunMetadata) -> UncertaintySet:
    """The set of robots a run's metadata records (the exact model for a run without one)."""
    return UncertaintySet.from_record(str(getattr(metadata, "uncertainty", "") or ""))


def gate_reasons(
    metadata: RunMetadata, plant: Plant, description: str, fingerprint_reasons: list[str]
) -> tuple[list[str], str]:
    """The gate's reasons about the robot's model, and which robot the certificate then covers, in words.

    An exact-model run keeps ``fingerprint_reasons`` (the fingerprint must be the certified one). A run that
    names a set compares the robot's ``description`` (its MJCF) with the certified model; without one, only
    the certified fingerprint itself (the nominal model) can be placed in the set."""
    try:
        robots = robots_of(metadata)
    except ValueError as exc:
        return [f"the run's set of robots cannot be read: {exc}"], ""
    if robots.empty:
        return fingerprint_reasons, ""
    if description:
        try:
            match = match_model(plant.physics.model, compiled(description), robots)  # type: ignore[attr-defined]
        except DescriptionError as exc:
            return [f"the robot's description: {exc}"], ""
        if not match.inside:
            return [f"the robot's model lies outside the certified set ({'; '.join(match.reasons)})"], ""
        return [], f"{match.describe()}, inside the certified set (whose certificate is an average over the set)"
    if fingerprint_reasons:
        return [*fingerprint_reasons, "the run certifies a set of robots: give the robot's MJCF to place it in it"], ""
    nominal = Robot(tuple((s.parameter, n, 1.0) for s in robots.resolved(plant.physics.model).scales for n in s.names))  # type: ignore[attr-defined]
    outside = robots.contains(nominal)
    if outside:
        return [f"the nominal model lies outside the certified set ({'; '.join(outside)})"], ""
    return [], "the nominal model, inside the certified set (whose certificate is an average over the set)"


# ---------------------------------------------------------------------------------------------- a robot as MJCF
def robot_mjcf(plant: Plant, robot: Robot) -> str | None:
    """The plant's MJCF with ``robot``'s parameters written in, so that it compiles to the model ``robot`` makes of
    the plant's (ModelParameters.apply); None when the plant names no MJCF.

    Each scaled element gets its values explicitly, as the nominal compiled value times the factor (repr: no
    digits lost): a body an ``<inertial>`` (its pose and principal inertia), an actuator its ``gear``, a joint its
    ``damping``, ``frictionloss`` or ``armature``."""
    text = model_mjcf(plant)
    if text is None:
        return None
    parameters = ModelParameters(plant.physics.model)  # type: ignore[attr-defined]
    values = parameters.values(robot)
    model = parameters.model
    root = ET.fromstring(text)
    named = {(el.tag, el.get("name")): el for el in root.iter() if el.get("name") is not None}
    actuator_tags = {el.tag for el in root.iter() if el.get("joint") is not None and el.tag != "spatial"}
    for parameter, name, _ in robot.scales:
        kind = PARAMETERS[parameter][0]
        if kind == "body":
            index = model_elements(model)["body"].index(name) + 1
            element = _find(named, ("body",), name)
            for old in element.findall("inertial"):
                element.remove(old)
            inertial = ET.Element("inertial", {
                "pos": _numbers(model.body_ipos[index]), "quat": _numbers(model.body_iquat[index]),
                "mass": repr(float(values["body_mass"][index])),
                "diaginertia": _numbers(values["body_inertia"][index]),
            })  # fmt: skip
            element.insert(0, inertial)
        elif kind == "actuator":
            index = model_elements(model)["actuator"].index(name)
            _find(named, tuple(actuator_tags), name).set("gear", _numbers(values["actuator_gear"][index]))
        else:
            index = model_elements(model)["joint"].index(name)
            value = values[f"dof_{parameter}"][int(model.jnt_dofadr[index])]
            _find(named, ("joint",), name).set(parameter, repr(float(value)))
    return ET.tostring(root, encoding="unicode")


def _find(named: dict[tuple[str, str | None], ET.Element], tags: tuple[str, ...], name: str) -> ET.Element:
    for tag in tags:
        if (tag, name) in named:
            return named[(tag, name)]
    raise ValueError(f"the model's MJCF names no {' or '.join(tags)} {name!r}")


def _numbers(values: Any) -> str:
    return " ".join(repr(float(x)) for x in np.ravel(values))
