"""What a run needs of a robot: a reset that reports the measured start, and one command per control period.

The link's clock is the robot's: a reading's ``time`` is the robot's stamp of the state, in seconds, so a robot run
faster than real time (npp-robot's time_scale) and a real one read the same. A command that reached the robot after
its period had passed (the robot stepped on the command before) is counted in ``late_commands``; it is not a fault:
the robot held its last command, as a ros2_control forward controller does.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from npp_ros.policy.dataset import FloatArray


class RobotFault(RuntimeError):
    """The robot could not carry an episode on: its states stopped past the watchdog, its reset failed, it went
    away. The episode is cut short, stored with this reason, and run again from a new reset; it is never a check."""


class RobotGone(RuntimeError):
    """The robot faulted on every try in a row: the run stops, keeping everything stored, and resumes where it was."""


@dataclass(frozen=True)
class Reading:
    """One measured state of the robot and the robot's clock when it was measured (seconds)."""

    state: FloatArray
    time: float


class RobotLink(Protocol):
    """A robot as a run drives it. ``reset`` brings it to a start (``requested``, or its own when None) and holds it
    there; ``step`` commands one control period and returns the next measured state; ``hold`` sends the safe
    command (zero) at the end of an episode. Both raise RobotFault when the robot cannot go on."""

    dt: float  # the control period, seconds of the robot's clock
    late_commands: int  # commands that reached the robot after its period had passed, so far

    def reset(self, requested: FloatArray | None) -> Reading: ...

    def step(self, command: FloatArray) -> Reading: ...

    def hold(self) -> None: ...

    def describe(self) -> str:
        """The robot in words, for logs and refusals (never its hidden parameters)."""
        ...
