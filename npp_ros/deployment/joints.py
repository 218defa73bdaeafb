"""The robot's joints: its state assembled by joint name, its command in the controller's joint order.

A robot names its joints in messages of its own order, with joints the task does not have; the policy acts on
the task's stored state. :class:`JointLayout` maps one to the other and refuses a state the policy cannot act
on, naming the joints at fault.

A task whose state holds a target (a task file's ``state.target``: three slide joints of a body nothing moves)
has joints no robot measures: the target is a point a user gives (npp-deploy reads it from a topic), which
:class:`TargetBox` turns into those joints' positions, their velocities 0, and refuses outside the box rho draws
targets from, the only targets the certificate covers.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from npp_ros.policy.dataset import FloatArray
from npp_ros.policy.vectors import MAX_MAGNITUDE
from npp_ros.tasks.registry import Plant
from npp_ros.tasks.task_file.loader import target_origin

_MJ_JOINT_SLIDE, _MJ_JOINT_HINGE = 2, 3  # MuJoCo joint types with one position and one velocity


class RobotStateError(ValueError):
    """A joint state the policy cannot act on; the message names the joints or values at fault."""


class NonFiniteState(RobotStateError):
    """A joint state with a NaN or infinite value on one of the task's joints."""


class NoTarget(RobotStateError):
    """A joint state of a task whose state holds a target, before any target was given: nothing to act on yet,
    though the state itself is fine. ``raw`` is that state with the target's entries at 0 (what a safe command
    that holds the robot's pose may read; never what the policy acts on)."""

    def __init__(self, message: str, raw: FloatArray) -> None:
        super().__init__(message)
        self.raw = raw


class TargetRefused(ValueError):
    """A target the policy must not be given: not a finite point, or outside the box the certificate covers."""


TARGET_TOLERANCE = 1e-9  # m: a target this far outside the box is rounding (a point typed at its edge), not outside


@dataclass(frozen=True, eq=False)
class TargetBox:
    """A task's target as a point in the world: the target joints' positions are the point less ``origin`` (where
    the target is with its joints at 0), and rho draws them in [``low``, ``high``]; a certificate covers no other."""

    joints: tuple[str, ...]
    origin: FloatArray
    low: FloatArray
    high: FloatArray

    @classmethod
    def of_plant(cls, plant: Plant) -> TargetBox | None:
        """The box of a task file's ``state.target`` (None for a plant without one)."""
        joints = tuple(getattr(plant, "target_joints", ()))
        if not joints:
            return None
        definition = plant.definition  # type: ignore[attr-defined]  # a task file's plant (FilePlant)
        at = [definition.joint_names.index(name) for name in joints]  # qpos indices: hinge and slide joints only
        low, high = np.asarray(definition.rho_low)[at], np.asarray(definition.rho_high)[at]
        return cls(joints, target_origin(plant), low, high)  # type: ignore[arg-type]  # a FilePlant

    def coordinates(self, point: ArrayLike) -> FloatArray:
        """The target joints' positions for a world point; TargetRefused, with the reason, for a point that is not
        finite or lies outside the box (refused, never clamped: a clamped target is not the one asked for)."""
        p = np.asarray(point, dtype=np.float64).reshape(-1)
        if p.size != len(self.joints) or not np.isfinite(p).all():
            raise TargetRefused(f"target {describe_point(p)} is not a finite point (x, y, z)")
        q = p - self.origin
        if np.any(q < self.low - TARGET_TOLERANCE) or np.any(q > self.high + TARGET_TOLERANCE):
            raise TargetRefused(
                f"target {describe_point(p)} lies outside the box {self.describe()} that rho draws targets from: "
                "the certificate covers those targets only"
            )
        return q

    def point(self, coordinates: FloatArray) -> FloatArray:
        """The world point of the target joints' positions."""
        return self.origin + coordinates

    def describe(self) -> str:
        """The box in world coordinates: "x [0.1, 0.3], y [0, 0.2], z [0, 0] m"."""
        low, high = self.origin + self.low, self.origin + self.high
        return ", ".join(f"{axis} [{lo:.6g}, {hi:.6g}]" for axis, lo, hi in zip("xyz", low, high, strict=True)) + " m"


def describe_point(point: ArrayLike) -> str:
    """A point as the log and /diagnostics show it: "(0.25, 0.15, 0)"."""
    return "(" + ", ".join(f"{float(x):.6g}" for x in np.asarray(point, dtype=np.float64).reshape(-1)) + ")"


@dataclass
class JointLayout:
    """The task's joints as a robot names them: its state assembled by joint name, its command in the
    controller's joint order.

    ``state_joints``: the task's joints in the state's order (qpos then qvel, one each);
    ``actuated``: the task's actuated joints in the action's order; ``command_joints``: the
    controller's joints, in the order its command array lists them (a permutation of ``actuated``);
    ``target``: the task's target, whose joints (among ``state_joints``) no robot measures: the state holds the
    target last given (:meth:`aim`), at rest.
    """

    state_joints: tuple[str, ...]
    actuated: tuple[str, ...]
    command_joints: tuple[str, ...]
    target: TargetBox | None = None
    # The last message's names and where the task's joints are in them; None until the first message, so
    # that a first message naming no joints is checked like any other (an empty cache would match it).
    _names: tuple[str, ...] | None = field(default=None, init=False, repr=False)
    _where: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.intp), init=False, repr=False)
    _aim: FloatArray | None = field(default=None, init=False, repr=False)  # the target joints' positions now

    def __post_init__(self) -> None:
        if not self.state_joints:
            raise ValueError("a joint layout needs the task's joints; this one names none")
        aimed = () if self.target is None else self.target.joints
        if not set(aimed) <= set(self.state_joints) or set(aimed) & set(self.actuated):
            raise ValueError(f"the target's joints {list(aimed)} must be unactuated joints of the task")
        self.measured = tuple(name for name in self.state_joints if name not in aimed)  # what a robot reports
        if sorted(self.command_joints) != sorted(self.actuated):
            raise ValueError(
                f"the command joints {list(self.command_joints)} must be the task's actuated joints "
                f"{list(self.actuated)}, each once, in any order"
            )
        self._command_order = np.array([self.actuated.index(name) for name in self.command_joints], dtype=np.intp)
        self._command_in_state = np.array([self.state_joints.index(n) for n in self.command_joints], dtype=np.intp)

    @classmethod
    def of_plant(cls, plant: Plant, command_joints: Sequence[str] = ()) -> JointLayout:
        """The plant's joints; ``command_joints`` empty: the plant's actuated joints, in its order."""
        model = getattr(getattr(plant, "physics", None), "model", None)
        if model is not None and any(int(t) not in (_MJ_JOINT_SLIDE, _MJ_JOINT_HINGE) for t in model.jnt_type):
            raise ValueError(f"{plant.task} has joints with more than one position (free or ball): not supported")
        actuated = tuple(plant.actuated_joint_names)
        return cls(tuple(plant.joint_names), actuated, tuple(command_joints) or actuated, TargetBox.of_plant(plant))

    @property
    def aimed(self) -> FloatArray | None:
        """The target joints' positions the state holds now (None: no target given yet, or the task has none)."""
        return None if self._aim is None else self._aim.copy()

    def aim(self, point: ArrayLike) -> FloatArray:
        """Take a world point as the target from now on; its joints' positions. TargetRefused (the target held
        before kept) for a point the certificate does not cover."""
        if self.target is None:
            raise TargetRefused("this task's state holds no target")
        self._aim = self.target.coordinates(point)
        return self._aim.copy()

    def aim_as(self, raw_state: FloatArray) -> None:
        """Take the target a whole state holds (a reset's start, which put the simulated target there)."""
        if self.target is not None:
            self._aim = np.array([raw_state[self.state_joints.index(name)] for name in self.target.joints])

    def state(self, names: Sequence[str], positions: Sequence[float], velocities: Sequence[float]) -> FloatArray:
        """[positions, velocities] of the task's joints, whatever order and extra joints the message has, the
        target's (if the task has one) those last given, at rest; a RobotStateError naming what is wrong for a
        state the policy cannot act on, NoTarget for a good one before any target was given."""
        names = tuple(names)
        if names != self._names:
            self._where = self._index(names)
            self._names = names
        if len(positions) != len(names) or len(velocities) != len(names):
            raise RobotStateError(
                f"joint state names {len(names)} joints but has {len(positions)} positions and "
                f"{len(velocities)} velocities (one each per named joint needed)"
            )
        where = self._where
        position, velocity = np.asarray(positions, dtype=np.float64), np.asarray(velocities, dtype=np.float64)
        if self.target is not None:  # the target's entries follow the message's own (see _index), at rest
            aim = self._aim if self._aim is not None else np.zeros(len(self.target.joints))
            position, velocity = np.concatenate([position, aim]), np.concatenate([velocity, np.zeros(len(aim))])
        raw = np.concatenate([position[where], velocity[where]])
        finite = np.isfinite(raw)
        if not finite.all():
            raise NonFiniteState(f"joint state has non-finite values: {self._entries(~finite, raw)}")
        huge = np.abs(raw) > MAX_MAGNITUDE
        if huge.any():
            raise RobotStateError(
                f"joint state has values too large to compare with the certified data: {self._entries(huge, raw)} "
                f"(entries must be within +-{MAX_MAGNITUDE:g})"
            )
        if self.target is not None and self._aim is None:
            raise NoTarget(
                f"no target given yet: the state holds the target's joints {', '.join(self.target.joints)}", raw
            )
        return raw

    def _entries(self, which: np.ndarray, raw: FloatArray) -> str:
        """The flagged entries of a state, by joint: "joint_1 velocity = nan"."""
        count = len(self.state_joints)
        return ", ".join(
            f"{self.state_joints[i % count]} {'position' if i < count else 'velocity'} = {raw[i]:g}"
            for i in np.flatnonzero(which)
        )

    def _index(self, names: tuple[str, ...]) -> np.ndarray:
        if len(set(names)) != len(names):
            twice = sorted({n for n in names if names.count(n) > 1})
            raise RobotStateError(f"joint state names {', '.join(twice)} more than once")
        where = {name: i for i, name in enumerate(names)}
        if self.target is not None:  # a message naming them too is not heard on them: the target is given
            where.update((name, len(names) + k) for k, name in enumerate(self.target.joints))
        missing = [name for name in self.state_joints if name not in where]
        if missing:
            shown = ", ".join(names[:10]) + (", ..." if len(names) > 10 else "") if names else "none"
            raise RobotStateError(f"joint state lacks the task's joints {', '.join(missing)} (it names: {shown})")
        return np.array([where[name] for name in self.state_joints], dtype=np.intp)

    def command(self, action: ArrayLike) -> FloatArray:
        """An action (the task's actuator order) in the controller's joint order."""
        return np.asarray(action, dtype=np.float64)[self._command_order]

    def action(self, command: ArrayLike) -> FloatArray:
        """A command (the controller's joint order) as an action in the task's actuator order."""
        action = np.empty(len(self.actuated))
        action[self._command_order] = np.asarray(command, dtype=np.float64)
        return action

    def hold(self, raw_state: FloatArray) -> FloatArray:
        """The command joints' measured positions (a position interface's safe command)."""
        return raw_state[self._command_in_state].copy()


def stored_state(plant: Plant, raw: FloatArray) -> FloatArray:
    """The robot's [qpos, qvel] as the task stores states (angles wrapped where the task wraps them)."""
    represent = getattr(plant, "represent", None)
    return raw if represent is None else represent(raw)


def parse_names(text: str) -> tuple[str, ...]:
    """A comma-separated list of joint names (a ROS parameter holds it as one string)."""
    return tuple(name.strip() for name in text.split(",") if name.strip())


def parse_vector(text: str, size: int, what: str) -> FloatArray:
    """A comma-separated vector of ``size`` finite numbers."""
    try:
        values = [float(x) for x in text.split(",") if x.strip()]
    except ValueError as exc:
        raise ValueError(f"{what} must be {size} comma-separated numbers: {exc}") from None
    arr = np.asarray(values, dtype=np.float64)
    if arr.size != size or not np.isfinite(arr).all():
        raise ValueError(f"{what} must be {size} finite comma-separated numbers, got {text!r}")
    return arr
