"""What a robot is commanded: the interface the certified actions fit, their limits, and the safe command.

A certified action is an effort when the task's actuators are motors, a position when they are position
servos; :func:`check_command_interface` refuses the other. :class:`CommandLimits` clamps an action to the
model's control range, and :func:`safe_command` is what the robot gets when the policy stops.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from npp_ros.deployment.joints import JointLayout, RobotStateError
from npp_ros.policy.dataset import FloatArray
from npp_ros.tasks.registry import Plant

CommandInterface = Literal["effort", "position"]
COMMAND_INTERFACES: tuple[str, ...] = ("effort", "position")
# The safe effort: zero (a robot whose own controller holds it against gravity, as an arm's torque interface
# usually does), or the torques that hold the measured pose against the model's gravity (a robot that falls at
# zero effort, as npp-robot running an arm's model does: the certified torques carry gravity themselves).
SAFE_EFFORTS: tuple[str, ...] = ("zero", "gravity")
_MJ_BIAS_NONE = 0  # a motor: the control is a force or torque


def check_command_interface(plant: Plant, interface: str) -> None:
    """Refuse an interface the certified actions do not fit: an effort command needs motors, a position one
    position actuators (MuJoCo: a motor has no bias; a position servo an affine one)."""
    if interface not in COMMAND_INTERFACES:
        raise ValueError(f"command_interface must be one of {', '.join(COMMAND_INTERFACES)}, got {interface!r}")
    model = getattr(getattr(plant, "physics", None), "model", None)
    if model is None:
        return
    motors = [int(b) == _MJ_BIAS_NONE for b in model.actuator_biastype]
    if interface == "effort" and not all(motors):
        raise ValueError(f"{plant.task}'s actuators are position servos, not motors: use command_interface position")
    if interface == "position" and any(motors):
        raise ValueError(
            f"{plant.task}'s certified actions are efforts (its actuators on {', '.join(plant.actuated_joint_names)} "
            "are motors): use command_interface effort"
        )


def safe_command(
    interface: str,
    layout: JointLayout,
    raw_state: FloatArray | None,
    hold: Callable[[FloatArray], FloatArray] | None = None,
) -> FloatArray:
    """What a robot gets when the policy stops: zero effort, or with ``hold`` (the task's actuator order) the
    effort that holds its measured pose; or its present position held. Before any joint state, zero effort."""
    if interface == "position":
        if raw_state is None:
            raise RobotStateError("no joint state received yet: there is no position to hold")
        return layout.hold(raw_state)
    if hold is not None and raw_state is not None:
        return layout.command(hold(raw_state))
    return np.zeros(len(layout.command_joints))


def gravity_hold(plant: Plant) -> Callable[[FloatArray], FloatArray]:
    """The efforts that hold the plant's measured pose at rest under its model's gravity (the task file's
    GravityHold), for :func:`safe_command`; a plant without a MuJoCo model has none."""
    from npp_ros.tasks.task_file.loader import GravityHold

    model = getattr(getattr(plant, "physics", None), "model", None)
    if model is None:
        raise ValueError(f"{plant.task} has no MuJoCo model to compute the torques that hold it")
    low = np.asarray(getattr(plant, "action_low", np.full(plant.action_dim, -np.inf)), dtype=np.float64)
    high = np.asarray(getattr(plant, "action_high", np.full(plant.action_dim, np.inf)), dtype=np.float64)
    return GravityHold(model.ptr, low, high)


@dataclass(frozen=True)
class CommandLimits:
    """The actions a robot may receive: the model's actuator control range, tightened by ``effort_limit``."""

    low: FloatArray
    high: FloatArray

    @classmethod
    def of_plant(cls, plant: Plant, effort_limit: float = 0.0) -> CommandLimits:
        low, high = np.full(plant.action_dim, -np.inf), np.full(plant.action_dim, np.inf)
        model = getattr(getattr(plant, "physics", None), "model", None)
        if model is not None:
            limited = np.asarray(model.actuator_ctrllimited, dtype=bool)
            low[limited] = model.actuator_ctrlrange[limited, 0]
            high[limited] = model.actuator_ctrlrange[limited, 1]
        if effort_limit > 0:
            low, high = np.maximum(low, -effort_limit), np.minimum(high, effort_limit)
        return cls(low, high)

    def clamp(self, action: FloatArray) -> tuple[FloatArray, int]:
        """The action within the limits, and how many of its entries had to be clamped."""
        clamped = np.clip(action, self.low, self.high)
        return clamped, int(np.count_nonzero(clamped != action))

    def describe(self) -> str:
        if not np.isfinite(np.concatenate([self.low, self.high])).any():
            return "none (the model's actuators are not limited and no effort_limit was given)"
        return ", ".join(f"[{lo:g}, {hi:g}]" for lo, hi in zip(self.low, self.high, strict=True))
