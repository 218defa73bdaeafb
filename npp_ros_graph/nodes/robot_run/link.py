"""The robot over ros2_control topics as the core's RobotLink (npp_ros.run.on_robot.link).

The node's callbacks put each /joint_states message in a StateInbox; the worker thread that runs the run waits on
it (a Condition, never a poll). A step publishes the command (std_msgs/Float64MultiArray, the controller's joint
order) and waits for the first state the robot stamps after the last one; the robot's clock is its stamps, so a
robot run faster than real time reads the same. A state more than a period after the last means the command
missed its period (the robot held the one before): a late command, counted. No state within ``state_timeout``
seconds is a fault; the safe command (zero) goes out at the end of every episode, cut short or not. A robot that
moves within SETTLE_S of its reset, before any command of the episode, was moved by a command from before it: that
reset is a fault too, and the robot is reset again.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np
from npp_interfaces.srv import ResetRobot
from rclpy.client import Client
from rclpy.impl.rcutils_logger import RcutilsLogger
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from npp_ros.deployment.joints import JointLayout, RobotStateError, stored_state
from npp_ros.policy.dataset import FloatArray
from npp_ros.run.loop import EpisodeInterrupted
from npp_ros.run.on_robot.link import Reading, RobotFault
from npp_ros.tasks.task import Plant
from npp_ros_graph.runtime.deadlines import call_with_deadline
from npp_ros_graph.transport.convert import float64_array

SETTLE_S = 0.05  # after a reset, how long the robot must hold its start before the first command


def stamp_seconds(msg: JointState) -> float:
    return float(msg.header.stamp.sec) + 1e-9 * float(msg.header.stamp.nanosec)


class StateInbox:
    """The newest joint state, handed from the executor's callback to the worker."""

    def __init__(self) -> None:
        self._changed = threading.Condition()
        self._latest: JointState | None = None
        self.received = 0

    def put(self, msg: JointState) -> None:
        with self._changed:
            self._latest = msg
            self.received += 1
            self._changed.notify_all()

    def after(self, stamp: float, timeout: float, stop: threading.Event) -> JointState | None:
        """The newest state stamped after ``stamp``; None when ``timeout`` seconds pass first (or the node stops)."""
        deadline = time.monotonic() + timeout

        def fresh() -> bool:
            return stop.is_set() or (self._latest is not None and stamp_seconds(self._latest) > stamp)

        with self._changed:
            self._changed.wait_for(fresh, max(deadline - time.monotonic(), 0.0))
            latest = self._latest
        if latest is None or stamp_seconds(latest) <= stamp:
            return None
        return latest


class RosRobotLink:
    """A ros2_control robot as a run's plant: ``publish`` sends a command message, ``reset`` is the robot's reset
    service client, ``states`` the node's inbox of joint states."""

    def __init__(
        self,
        plant: Plant,
        layout: JointLayout,
        publish: Callable[[Float64MultiArray], None],
        reset: Client,
        states: StateInbox,
        *,
        state_timeout: float,
        reset_timeout: float,
        stop: threading.Event,
        logger: RcutilsLogger,
        name: str,
    ) -> None:
        self.plant, self.layout, self.publish, self.reset_client = plant, layout, publish, reset
        self.states, self.stop, self.logger, self.name = states, stop, logger, name
        self.state_timeout, self.reset_timeout = float(state_timeout), float(reset_timeout)
        self.dt = float(plant.dt)
        self.late_commands = 0
        self._stamp = -np.inf  # the robot's stamp of the last state read
        self._held = False  # a reset's start is held: the next state is the first command's
        self._safe = Float64MultiArray(data=float64_array(np.zeros(len(layout.command_joints))))

    def describe(self) -> str:
        return f"the robot behind {self.name}"

    def _interrupted(self) -> None:
        if self.stop.is_set():
            raise EpisodeInterrupted("the node is stopping")

    def reset(self, requested: FloatArray | None) -> Reading:
        self._interrupted()
        if not self.reset_client.wait_for_service(timeout_sec=self.reset_timeout):
            raise RobotFault(f"the reset service {self.reset_client.srv_name} is not available")
        request = ResetRobot.Request(state=float64_array(np.zeros(0) if requested is None else requested))
        response = call_with_deadline(self.reset_client, request, self.reset_timeout, self.logger)
        self._interrupted()
        if response is None:
            raise RobotFault(f"no answer from the reset service within {self.reset_timeout:g} s")
        if not response.success:
            raise RobotFault(f"the robot refused the reset: {response.message}")
        if len(response.state) != self.plant.state_dim or not np.all(np.isfinite(response.state)):
            raise RobotFault(f"the reset reported a start of {len(response.state)} values, not a finite state")
        start = np.array(response.state, dtype=np.float64)
        self.layout.aim_as(start)  # a target the state holds is where the reset put it: no joint state reports it
        self._stamp = float(response.stamp.sec) + 1e-9 * float(response.stamp.nanosec)
        self._held = True  # the robot repeats this measurement, with its stamp, until the first command
        # A command still in flight from before the reset (a robot that paused, a controller's last word) would move
        # the robot before the episode's first command; the states then say so, and the reset is not a start.
        moved = self.states.after(self._stamp, SETTLE_S, self.stop)
        self._interrupted()
        if moved is not None:
            raise RobotFault("the robot moved after its reset before the episode's first command (a command in flight)")
        return Reading(stored_state(self.plant, start), self._stamp)

    def step(self, command: FloatArray) -> Reading:
        self._interrupted()
        self.publish(Float64MultiArray(data=float64_array(self.layout.command(command))))
        msg = self.states.after(self._stamp, self.state_timeout, self.stop)
        self._interrupted()
        if msg is None:
            raise RobotFault(f"no joint state for {self.state_timeout:g} s (state_timeout)")
        try:
            raw = self.layout.state(msg.name, msg.position, msg.velocity)
        except RobotStateError as exc:
            raise RobotFault(f"a joint state the policy cannot act on: {exc}") from None
        stamp = stamp_seconds(msg)
        if not self._held:  # the first step after a reset ends dt after the command came, whenever that was
            periods = round((stamp - self._stamp) / self.dt) if np.isfinite(self._stamp) else 1
            self.late_commands += max(periods - 1, 0)
        self._stamp, self._held = stamp, False
        return Reading(stored_state(self.plant, raw), stamp)

    def hold(self) -> None:
        self.publish(self._safe)
