"""A MuJoCo robot behind the RobotLink: the task's plant made into a robot the run is not told about.

Its physical parameters, command delay and read noise are a Robot record (npp_ros.tasks.uncertainty) given to it,
not to the run; its reset places it at the requested start, or at its own when none is asked (the task's s0 of the
robot's own stream), off by ``reset_spread`` per entry as a real reset would be, and the start it reports is read as
every state is (with its noise). ``faults`` cuts an episode as a real robot's dropped states would: for a reset
count and a step, the step raises RobotFault. It is what the in-process tests and trials certify on; npp-robot is
the same plant over ros2_control topics.
"""

from __future__ import annotations

from collections.abc import Collection

import numpy as np

from npp_ros.policy.dataset import FloatArray
from npp_ros.run.on_robot.link import Reading, RobotFault
from npp_ros.tasks.task import Plant
from npp_ros.tasks.uncertainty import ModelParameters, Robot, RobotEffects


class SimulatedRobot:
    """A plant that answers as a robot does: reset, then one step per command, its clock advancing by dt."""

    def __init__(
        self,
        plant: Plant,
        robot: Robot | None = None,
        *,
        own_start: FloatArray | None = None,
        reset_spread: float = 0.0,
        seed: int = 0,
        faults: Collection[tuple[int, int]] = (),
    ) -> None:
        self.plant = plant
        self.robot = robot if robot is not None else Robot()
        ModelParameters(plant.physics.model).apply(self.robot)  # type: ignore[attr-defined]  # its own model, for good
        self.dt = float(plant.dt)
        self.own_start = None if own_start is None else np.asarray(own_start, dtype=np.float64)
        self.reset_spread = float(reset_spread)
        self.faults = set(faults)
        self._rng = np.random.default_rng(seed)
        self._effects = RobotEffects(self.robot, plant.action_dim)
        self.resets = 0
        self.steps = 0  # in the current episode
        self.clock = 0.0
        self.late_commands = 0

    def describe(self) -> str:
        return f"a simulated {type(self.plant).__name__} (its parameters are not given to the run)"

    def _read(self) -> Reading:
        return Reading(self._effects.observe(self.plant.state()), self.clock)

    def reset(self, requested: FloatArray | None) -> Reading:
        start = requested if requested is not None else self.own_start
        if start is None:
            raise RobotFault("this robot has no start of its own: ask for one")
        start = np.asarray(start, dtype=np.float64)
        if self.reset_spread > 0:
            start = start + self._rng.uniform(-self.reset_spread, self.reset_spread, size=start.shape)
        self.plant.reset(start)
        self._effects = RobotEffects(self.robot, self.plant.action_dim)
        self.resets += 1
        self.steps = 0
        return self._read()

    def step(self, command: FloatArray) -> Reading:
        if (self.resets, self.steps) in self.faults:
            raise RobotFault(f"no joint state for 1 s at step {self.steps} (a simulated dropout)")
        self.plant.step(self._effects.command(np.asarray(command, dtype=np.float64)))
        self.steps += 1
        self.clock += self.dt
        return self._read()

    def hold(self) -> None:
        """The safe command: nothing moves the simulated robot between episodes."""
