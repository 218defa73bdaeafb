"""The robot's joints: its state assembled by joint name, its command in the controller's joint order.

A robot names its joints in messages of its own order, with joints the task does not have; the policy acts on
the task's stored state. :class:`JointLayout` maps one to the other and refuses a state the policy cannot act
on, naming the joints at fault.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from npp_ros.policy.dataset import FloatArray
from npp_ros.policy.vectors import MAX_MAGNITUDE
from npp_ros.tasks.registry import Plant

_MJ_JOINT_SLIDE, _MJ_JOINT_HINGE = 2, 3  # MuJoCo joint types with one position and one velocity


class RobotStateError(ValueError):
    """A joint state the policy cannot act on; the message names the joints or values at fault."""


class NonFiniteState(RobotStateError):
    """A joint state with a NaN or infinite value on one of the task's joints."""


@dataclass
class JointLayout:
    """The task's joints as a robot names them: its state assembled by joint name, its command in the
    controller's joint order.

    ``state_joints``: the task's joints in the state's order (qpos then qvel, one each);
    ``actuated``: the task's actuated joints in the action's order; ``command_joints``: the
    controller's joints, in the order its command array lists them (a permutation of ``actuated``).
    """

    state_joints: tuple[str, ...]
    actuated: tuple[str, ...]
    command_joints: tuple[str, ...]
    # The last message's names and where the task's joints are in them; None until the first message, so
    # that a first message naming no joints is checked like any other (an empty cache would match it).
    _names: tuple[str, ...] | None = field(default=None, init=False, repr=False)
    _where: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.intp), init=False, repr=False)

    def __post_init__(self) -> None:
        if not self.state_joints:
            raise ValueError("a joint layout needs the task's joints; this one names none")
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
        return cls(tuple(plant.joint_names), actuated, tuple(command_joints) or actuated)

    def state(self, names: Sequence[str], positions: Sequence[float], velocities: Sequence[float]) -> FloatArray:
        """[positions, velocities] of the task's joints, whatever order and extra joints the message has; a
        RobotStateError naming what is wrong for a state the policy cannot act on."""
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
