"""npp-deploy-ctl: drives npp-deploy's lifecycle (configure, activate, deactivate, cleanup, shutdown), its stop
service and its state, for a user without the ros2 command line.

Each command calls the node's standard lifecycle_msgs services (what `ros2 lifecycle set` calls) and
prints the state it ends in. A refused transition prints the node's reason, read from its
/diagnostics status, and exits with 1; so does a transition the node's state does not allow, with
why (activate on an unconfigured node names the configure refusal that left it there); a node that
cannot be reached exits with 2.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.task import Future
from std_srvs.srv import Trigger

from npp_ros_graph.runtime.diagnostics import DIAGNOSTICS, DIAGNOSTICS_QOS, LEVEL_NAMES, Health, health_of
from npp_ros_graph.runtime.node import release
from npp_ros_graph.transport.topics import SERVICE_QOS

TRANSITIONS = ("configure", "activate", "deactivate", "cleanup", "shutdown")
COMMANDS = (*TRANSITIONS, "stop", "clear-mismatch", "state")
SERVICES = {"stop": "stop", "clear-mismatch": "clear_model_mismatch"}  # commands that call a Trigger service
REASON_WAIT_S = 3.0  # the node publishes its diagnostics at once on a refusal, and every second
RESEND_S = 5.0  # a question (get_state) is asked again after this long without an answer
# The lifecycle states each transition starts from (the standard managed-node state machine).
STARTS_FROM = {
    "configure": ("unconfigured",),
    "activate": ("inactive",),
    "deactivate": ("active",),
    "cleanup": ("inactive",),
    "shutdown": ("unconfigured", "inactive", "active"),
}
WHAT_INSTEAD = {
    "configure": "it is configured already (cleanup first to configure it again)",
    "activate": "configure it first",
    "deactivate": "it is not commanding",
    "cleanup": "only an inactive node is cleaned up",
}


class Unreachable(RuntimeError):
    """The node's service did not answer in time."""


class DeployControl:
    """A short-lived client node for one npp-deploy node."""

    def __init__(self, target: str, timeout: float) -> None:
        self.target = "/" + target.strip("/")
        self.timeout = timeout
        self.node = Node("npp_deploy_ctl")
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.statuses: dict[str, Any] = {}
        self.node.create_subscription(DiagnosticArray, DIAGNOSTICS, self._on_diagnostics, DIAGNOSTICS_QOS)

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name == self.target:
                self.statuses["latest"] = status

    def _wait(self, future: Future, what: str, again: Callable[[], Future] | None = None) -> Any:
        """The answer within the timeout; ``again`` re-sends a request that may be asked twice (a question, not a
        transition) every RESEND_S: a response DDS loses (seen under load: the node answered, the client never
        heard) is then answered again."""
        deadline = time.monotonic() + self.timeout
        resend = time.monotonic() + RESEND_S
        while not future.done():
            now = time.monotonic()
            if now > deadline:
                raise Unreachable(f"no answer from {what} within {self.timeout:g} s")
            if again is not None and now > resend:
                future, resend = again(), now + RESEND_S
            self.executor.spin_once(timeout_sec=0.05)
        return future.result()

    def call(self, srv_type: Any, name: str, request: Any, idempotent: bool = False) -> Any:
        service = f"{self.target}/{name}"
        client = self.node.create_client(srv_type, service, qos_profile=SERVICE_QOS)
        deadline = time.monotonic() + self.timeout
        while not client.service_is_ready():
            if time.monotonic() > deadline:
                raise Unreachable(
                    f"{service} not found within {self.timeout:g} s (is npp-deploy running, same domain?)"
                )
            self.executor.spin_once(timeout_sec=0.05)
        again = (lambda: client.call_async(request)) if idempotent else None
        return self._wait(client.call_async(request), service, again)

    def state(self) -> str:
        return str(self.call(GetState, "get_state", GetState.Request(), idempotent=True).current_state.label)

    def transition(self, label: str) -> bool:
        request = ChangeState.Request()
        request.transition.label = label
        return bool(self.call(ChangeState, "change_state", request).success)

    def status(self) -> Health | None:
        """The node's next /diagnostics status (None if none comes within REASON_WAIT_S)."""
        self.statuses.clear()
        deadline = time.monotonic() + REASON_WAIT_S
        while "latest" not in self.statuses and time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.05)
        status = self.statuses.get("latest")
        return None if status is None else health_of(status)

    def reason(self) -> str:
        """The node's latest /diagnostics status in words (its refusal, after a failed transition)."""
        health = self.status()
        if health is None:
            return "(no /diagnostics from the node to say why)"
        extra = f"; last error: {health.error}" if health.error else ""
        return f"[{LEVEL_NAMES.get(health.level, health.level)}] {health.doing}{extra}"

    def why_not(self, command: str, state: str) -> str:
        """Why ``command`` cannot start from ``state``: for an unconfigured node, the configure refusal that
        left it there, as its /diagnostics status says."""
        text = f"cannot {command}: the node is {state}"
        if state == "finalized":
            return f"{text} (shut down: start it again)"
        if state == "unconfigured":
            health = self.status()
            refused = "configure refused: "
            if health is not None and health.doing.startswith(refused):
                return f"{text} because configure was refused: {health.doing[len(refused) :]}"
        return f"{text}: {WHAT_INSTEAD.get(command, 'not a transition from this state')}"

    def close(self) -> None:
        release(self.executor, self.node)


def run(command: str, control: DeployControl) -> int:
    if command == "state":
        print(f"{control.target}: {control.state()}")
        return 0
    if command in SERVICES:
        answer = control.call(Trigger, SERVICES[command], Trigger.Request())
        print(f"{control.target}: {answer.message}")
        return 0 if answer.success else 1
    before = control.state()
    if before not in STARTS_FROM[command]:
        print(f"{control.target}: {control.why_not(command, before)}", file=sys.stderr)
        return 1
    if control.transition(command):
        print(f"{control.target}: {command} done ({before} -> {control.state()})")
        return 0
    print(f"{control.target}: {command} failed in state {before}, now {control.state()}", file=sys.stderr)
    print(f"  reason: {control.reason()}", file=sys.stderr)
    return 1


def main(argv: list[str] | None = None) -> int:
    args_in = list(sys.argv[1:] if argv is None else argv)
    ros_args = args_in[args_in.index("--ros-args") :] if "--ros-args" in args_in else []
    own = args_in[: len(args_in) - len(ros_args)]
    ap = argparse.ArgumentParser(prog="npp-deploy-ctl", description=__doc__)
    ap.add_argument(
        "command",
        choices=COMMANDS,
        help="a lifecycle transition, stop (deactivate at once), clear-mismatch (clear the model monitor's finding, "
        "WARN until then) or state",
    )
    ap.add_argument("--node", default="/npp_deploy", help="the npp-deploy node's full name")
    ap.add_argument("--timeout", type=float, default=60.0, help="seconds to wait for the node and for each answer")
    args = ap.parse_args(own)
    rclpy.init(args=["npp-deploy-ctl", *ros_args])
    control = DeployControl(args.node, args.timeout)
    try:
        return run(args.command, control)
    except Unreachable as exc:
        print(f"npp-deploy-ctl: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    finally:
        control.close()


if __name__ == "__main__":
    sys.exit(main())
