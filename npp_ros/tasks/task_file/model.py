"""The MuJoCo model a task file names, read against the file: its timestep, joints, actuators and rho.

Each function reads one part of the file (``model``, ``control_timestep``, ``[state]``, ``actuators``,
``[rho]``) and checks it against the compiled model, refusing with the key (npp_ros.tasks.task_file.reader).
The stored state is [qpos, qvel] of every joint, so the model may hold hinge and slide joints only.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from npp_ros.policy.dataset import FloatArray
from npp_ros.tasks.suite_plant import substeps_per_control_step
from npp_ros.tasks.task_file.reader import Reader

STATE_KEYS = {"joints", "wrap", "invariant", "target", "weights"}
WEIGHT_KEYS = {"position", "velocity"}
TARGET_AXES = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))  # target_x, _y, _z: the world's axes, in order
RHO_KEYS = {"position", "velocity"}


def model_ids(model: Any, kind: str) -> dict[str, int]:
    """The model's joints, sites or actuators (``kind``) by name -> id."""
    import mujoco

    obj = {"joint": mujoco.mjtObj.mjOBJ_JOINT, "site": mujoco.mjtObj.mjOBJ_SITE,
           "actuator": mujoco.mjtObj.mjOBJ_ACTUATOR}[kind]  # fmt: skip
    count = {"joint": model.njnt, "site": model.nsite, "actuator": model.nu}[kind]
    return {mujoco.mj_id2name(model, obj, i): i for i in range(count)}


def named_objects(reader: Reader, value: Any, key: str, ids: dict[str, int], kind: str, *, pair: bool) -> list[str]:
    """The one name (or, with ``pair``, the two names) ``key`` gives, each an object of the model of ``kind``."""
    if pair:
        wanted = reader.names(value, key)
        if len(wanted) != 2:
            raise reader.fail(key, f"must name two sites, got {wanted!r}")
    else:
        wanted = [reader.text(value, key)]
    for name in wanted:
        if name not in ids:
            known = ", ".join(sorted(n for n in ids if n)) or "none"
            raise reader.fail(key, f"unknown {kind} {name!r} (the model's: {known})")
    return wanted


def in_model_order(ids: dict[str, int]) -> list[str]:
    return [name for name, _ in sorted(ids.items(), key=lambda item: item[1])]


def load_model(reader: Reader, doc: dict[str, Any], path: Path) -> tuple[Path, Any]:
    """The file's ``model`` (MJCF, relative to the file at ``path``), its path and the compiled MjModel."""
    import mujoco

    if "model" not in doc:
        raise reader.fail("model", "missing: name the MJCF file (relative to this file)")
    model_path = (path.parent / reader.text(doc["model"], "model")).resolve()
    if not model_path.is_file():
        raise reader.fail("model", f"no model file at {model_path}")
    try:
        model = mujoco.MjModel.from_xml_path(str(model_path))
    except Exception as exc:  # MuJoCo's own parse error, in one line
        raise reader.fail("model", f"MuJoCo cannot load {model_path}: {' '.join(str(exc).split())}") from None
    _check_state_is_qpos_qvel(reader, model)
    return model_path, model


def _check_state_is_qpos_qvel(reader: Reader, model: Any) -> None:
    """Hinge and slide joints only, and no actuator with activation state: the state is [qpos, qvel]."""
    import mujoco

    allowed = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
    for j in range(model.njnt):
        if int(model.jnt_type[j]) not in allowed:
            name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j)
            raise reader.fail("state.joints", f"joint {name!r} is a ball or free joint; the state [qpos, qvel] "
                              "needs hinge and slide joints only")  # fmt: skip
    if model.na:
        raise reader.fail("model", "actuators with activation state are not supported (the state is [qpos, qvel])")


def read_timestep(reader: Reader, doc: dict[str, Any], model: Any) -> float:
    """The control step: ``control_timestep``, a whole multiple k of the model's timestep (k MuJoCo steps per
    control step, the action held, as dm_control's n_sub_steps); the model's timestep when not given."""
    dt = float(model.opt.timestep)
    if "control_timestep" not in doc:
        return dt
    given = reader.number(doc["control_timestep"], "control_timestep", positive=True)
    if substeps_per_control_step(given, dt) is None:
        raise reader.fail("control_timestep", f"{given:g} s is not a whole multiple of the model's timestep {dt:g} s: "
                          "a control step is k MuJoCo steps; set <option timestep> in the model")  # fmt: skip
    return given


def read_state(
    reader: Reader, doc: dict[str, Any], model: Any
) -> tuple[tuple[str, ...], tuple[int, ...], tuple[int, ...], tuple[str, ...]]:
    """``[state]``: the model's joints, every one in its order, the qpos indices stored wrapped, those of the
    joints declared invariant (their position changes neither dynamics nor reward; checked on the model at load,
    npp_ros.tasks.task_file.loader.check_invariance), and the target's joints (:func:`read_target`)."""
    import mujoco

    joints = model_ids(model, "joint")
    model_joints = in_model_order(joints)
    state = reader.table(doc.get("state", {}), "state")
    reader.unknown_keys(state, STATE_KEYS, "state.")
    if "joints" not in state:
        raise reader.fail("state.joints", f"missing: list the model's joints ({', '.join(model_joints)})")
    listed = reader.names(state["joints"], "state.joints")
    for name in listed:
        _known_joint(reader, "state.joints", name, joints)
    if listed != model_joints:
        raise reader.fail("state.joints", f"must list every joint of the model in its order: {model_joints}, got "
                          f"{listed} (the iLQR expert optimises the whole [qpos, qvel])")  # fmt: skip
    wrapped = []
    for name in reader.names(state.get("wrap", []), "state.wrap"):
        _known_joint(reader, "state.wrap", name, joints)
        if int(model.jnt_type[joints[name]]) != int(mujoco.mjtJoint.mjJNT_HINGE):
            raise reader.fail("state.wrap", f"joint {name!r} is not a hinge: only angles wrap")
        wrapped.append(int(model.jnt_qposadr[joints[name]]))
    invariant = []
    one_position = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
    for name in reader.names(state.get("invariant", []), "state.invariant"):
        _known_joint(reader, "state.invariant", name, joints)
        if int(model.jnt_type[joints[name]]) not in one_position:
            raise reader.fail("state.invariant", f"joint {name!r} is not a hinge or a slide: it has no one position")
        invariant.append(int(model.jnt_qposadr[joints[name]]))
    if len(invariant) == len(model_joints):
        raise reader.fail("state.invariant", "every joint is declared invariant: the policy would compare no position")
    target = read_target(reader, state, model, joints)
    for name in target:
        if int(model.jnt_qposadr[joints[name]]) in (*wrapped, *invariant):
            raise reader.fail(
                "state.target", f"joint {name!r} is a target coordinate: it neither wraps nor is invariant"
            )
    return tuple(model_joints), tuple(wrapped), tuple(sorted(invariant)), target


def read_weights(reader: Reader, doc: dict[str, Any], model: Any) -> tuple[float, ...]:
    """``[state.weights]``: each joint's weight in the policy's distance, a number (its position's) or a table
    ``{ position = w, velocity = w }``; entries not named weigh 1. () when every weight is 1 (the plain distance)."""
    state = reader.table(doc.get("state", {}), "state")
    if "weights" not in state:
        return ()
    table = reader.table(state["weights"], "state.weights")
    joints = model_ids(model, "joint")
    n = len(joints)
    weights = np.ones(2 * n)
    for name, given in table.items():
        key = f"state.weights.{name}"
        _known_joint(reader, key, name, joints)
        parts = given if isinstance(given, dict) else {"position": given}
        reader.unknown_keys(parts, WEIGHT_KEYS, f"{key}.")
        j = joints[name]
        for part, index in (("position", int(model.jnt_qposadr[j])), ("velocity", n + int(model.jnt_dofadr[j]))):
            if part in parts:
                weights[index] = reader.number(parts[part], f"{key}.{part}" if isinstance(given, dict) else key, True)
    return tuple(float(w) for w in weights) if np.any(weights != 1.0) else ()


def read_target(reader: Reader, state: dict[str, Any], model: Any, joints: dict[str, int]) -> tuple[str, ...]:
    """``state.target``: three slide joints, along the world's x, y and z in that order, of one body of the world
    that nothing touches and gravity does not pull (``gravcomp="1"``, no collision): a point the task is about
    (a reach's target), part of the state, that no torque moves (checked by stepping at load,
    loader.check_target). A robot has no such joints: a deployment reads the point from a topic."""
    import mujoco

    if "target" not in state:
        return ()
    names = reader.names(state["target"], "state.target")
    if len(names) != 3:
        raise reader.fail("state.target", f"must name three slide joints (x, y, z), got {names!r}")
    bodies = set()
    for name, axis, letter in zip(names, TARGET_AXES, "xyz", strict=True):
        _known_joint(reader, "state.target", name, joints)
        j = joints[name]
        if int(model.jnt_type[j]) != int(mujoco.mjtJoint.mjJNT_SLIDE):
            raise reader.fail("state.target", f"joint {name!r} is not a slide: a target coordinate is a position")
        if not np.allclose(model.jnt_axis[j], axis):
            along = model.jnt_axis[j].tolist()
            raise reader.fail("state.target", f"joint {name!r} slides along {along}, not the world's {letter} axis")
        bodies.add(int(model.jnt_bodyid[j]))
    if len(bodies) != 1:
        raise reader.fail("state.target", "the three joints must move one body")
    body = bodies.pop()
    body_name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, body)
    if int(model.body_parentid[body]) != 0 or not np.allclose(model.body_quat[body], (1, 0, 0, 0)):
        raise reader.fail("state.target", f"body {body_name!r} must be a child of the world, not rotated")
    if int(model.body_jntnum[body]) != 3:
        raise reader.fail("state.target", f"body {body_name!r} must have exactly the three target joints")
    if not np.isclose(model.body_gravcomp[body], 1.0) and np.any(model.opt.gravity):
        raise reader.fail("state.target", f'body {body_name!r} must set gravcomp="1": gravity would pull the target')
    for g in range(model.ngeom):
        if int(model.geom_bodyid[g]) == body and (model.geom_contype[g] or model.geom_conaffinity[g]):
            raise reader.fail("state.target", f'body {body_name!r} has a geom that collides: give it contype="0" '
                              'conaffinity="0" (the arm must pass through its target)')  # fmt: skip
    return tuple(names)


def _known_joint(reader: Reader, key: str, name: str, joints: dict[str, int]) -> None:
    if name not in joints:
        raise reader.fail(key, f"unknown joint {name!r} (the model's: {', '.join(in_model_order(joints))})")


def read_actuators(reader: Reader, doc: dict[str, Any], model: Any) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The model's actuators in order (``actuators``, if given, must name them so) and the joint each drives."""
    import mujoco

    actuators = model_ids(model, "actuator")
    actuator_names = tuple(in_model_order(actuators))
    if not actuator_names:
        raise reader.fail("model", "the model has no actuator: nothing for a policy to do")
    if "actuators" in doc:
        given = reader.names(doc["actuators"], "actuators")
        for name in given:
            if name not in actuators:
                raise reader.fail("actuators", f"unknown actuator {name!r} (the model's: {', '.join(actuator_names)})")
        if tuple(given) != actuator_names:
            raise reader.fail("actuators", f"must be the model's actuators in order: {list(actuator_names)}")
    model_joints = in_model_order(model_ids(model, "joint"))
    actuated = []
    for i, name in enumerate(actuator_names):
        if int(model.actuator_trntype[i]) != int(mujoco.mjtTrn.mjTRN_JOINT):
            raise reader.fail("actuators", f"actuator {name!r} does not drive a joint (the action message names "
                              "each actuator's joint)")  # fmt: skip
        actuated.append(model_joints[int(model.actuator_trnid[i, 0])])
    return actuator_names, tuple(actuated)


def read_rho(reader: Reader, doc: dict[str, Any], model: Any) -> tuple[FloatArray, FloatArray]:
    """``[rho]``: the low and high ends of s0's entries; a joint not named starts at its qpos0, at rest."""
    if "rho" not in doc:
        raise reader.fail("rho", "missing: give each joint's initial position range, e.g. hinge = { position = "
                          "[-3.14, 3.14] }")  # fmt: skip
    rho = reader.table(doc["rho"], "rho")
    if not rho:
        raise reader.fail("rho", "is empty: give at least one joint's position or velocity range")
    joints = model_ids(model, "joint")
    n = len(joints)
    low = np.concatenate([np.asarray(model.qpos0, dtype=np.float64), np.zeros(n)])
    high = low.copy()
    for name, ranges in rho.items():
        _known_joint(reader, f"rho.{name}", name, joints)
        ranges = reader.table(ranges, f"rho.{name}")
        reader.unknown_keys(ranges, RHO_KEYS, f"rho.{name}.")
        if not ranges:
            raise reader.fail(f"rho.{name}", "is empty: give position = [low, high] and/or velocity = [low, high]")
        j = joints[name]
        for key, index in (("position", int(model.jnt_qposadr[j])), ("velocity", n + int(model.jnt_dofadr[j]))):
            if key in ranges:
                low[index], high[index] = reader.interval(ranges[key], f"rho.{name}.{key}")
    return low, high
