"""npp-deploy as a test drives it over DDS: its lifecycle, its parameters, its /diagnostics and its commands
(tests/ros/test_deploy_robot.py, test_deploy_target_graph.py)."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from deploy_runs import FINGERPRINT
from diagnostic_msgs.msg import DiagnosticArray
from lifecycle_msgs.srv import ChangeState, GetState
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from npp_ros_graph.runtime.diagnostics import DIAGNOSTICS, DIAGNOSTICS_QOS, Health, health_of
from npp_ros_graph.transport.topics import FORWARD_COMMANDS

START_TIMEOUT_S = 120.0  # processes importing rclpy and MuJoCo on a shared, busy machine
STATUS_TIMEOUT_S = 60.0  # for a status that must come: generous, so that a busy machine only makes it slower
# The test's own subscriptions keep everything: a lockstep loop outpaces a test spinning between checks,
# and a shallow reader history would drop states (the robot and npp-deploy themselves use CONTROL_QOS).
KEEP_ALL = QoSProfile(depth=100_000, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)


class Deploy:
    """A test's handle on one npp-deploy process: its lifecycle, its parameters, its diagnostics, the commands."""

    def __init__(self, client: Any, node: str = "/npp_deploy", command_topic: str = FORWARD_COMMANDS) -> None:
        self.client, self.node = client, node
        self.change = client.client(ChangeState, f"{node}/change_state", START_TIMEOUT_S)
        self.get = client.client(GetState, f"{node}/get_state")
        self.params = client.client(SetParameters, f"{node}/set_parameters")
        self.stopper = client.client(Trigger, f"{node}/stop")
        self.clearer = client.client(Trigger, f"{node}/clear_model_mismatch")
        self.statuses: list[Any] = []
        self.commands: list[tuple[float, list[float]]] = []
        client.node.create_subscription(DiagnosticArray, DIAGNOSTICS, self._on_diagnostics, DIAGNOSTICS_QOS)
        self.command_sub = client.node.create_subscription(Float64MultiArray, command_topic, self._on_command, KEEP_ALL)

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        self.statuses += [status for status in msg.status if status.name == self.node]

    def _on_command(self, msg: Float64MultiArray) -> None:
        self.commands.append((time.monotonic(), list(msg.data)))

    def set(self, **values: Any) -> None:
        request = SetParameters.Request(
            parameters=[Parameter(k, value=v).to_parameter_msg() for k, v in values.items()]
        )
        answer = self.client.call(self.params, request)
        assert all(result.successful for result in answer.results), [r.reason for r in answer.results]

    def transition(self, label: str) -> bool:
        request = ChangeState.Request()
        request.transition.label = label
        return bool(self.client.call(self.change, request, timeout=120.0, attempt_timeout=120.0).success)

    def state(self) -> str:
        return str(self.client.call(self.get, GetState.Request()).current_state.label)

    def health_where(
        self, holds: Callable[[Health], bool], label: str, since: int | None = None, timeout: float = STATUS_TIMEOUT_S
    ) -> Health:
        """The first status published after the first ``since`` ones (default: those already here) for which
        ``holds`` is true: the status that reflects what a test checks, not one published just before it."""
        index = len(self.statuses) if since is None else since
        last: Health | None = None

        def seen() -> bool:
            nonlocal index, last
            while index < len(self.statuses):
                last, index = health_of(self.statuses[index]), index + 1
                if holds(last):
                    return True
            return False

        try:
            self.client.wait_for(seen, timeout, f"a status of {self.node} where {label}")
        except TimeoutError as exc:
            raise AssertionError(f"{exc}; the last status: {last}") from None
        assert last is not None
        return last

    def health(self) -> Health:
        """The node's next status, whatever it says."""
        return self.health_where(lambda _: True, "any")

    def has_description(self) -> Health:
        return self.health_where(lambda h: "characters from" in str(h.values.get("robot description")),
                                 "the robot's description was received", since=0)  # fmt: skip

    def deploy(self, run: Path, fingerprint: str | None = FINGERPRINT, **params: Any) -> None:
        """Configure and activate; ``fingerprint`` None: the one the robot's description gives."""
        if fingerprint is None:
            self.has_description()
        self.set(run_dir=str(run), robot_model_fingerprint=fingerprint or "", **params)
        assert self.transition("configure"), self.health().doing
        # The command publisher exists from configure on: see it before the first command goes out.
        self.client.wait_for(lambda: self.command_sub.get_publisher_count() > 0, 30.0, "npp-deploy's commands")
        assert self.transition("activate")


def count(health: Health, name: str) -> int:
    return int(str(health.values.get(name, -1)))
