"""npp-deploy: a managed (lifecycle) node that drives a robot with one certified run's policy, on ros2_control topics.

`configure` passes the run folder through the gate (npp_ros.deploy.load_deployment: checksums, the
certificate, what the operator accepts, the robot's model) and builds exactly the policy the
certificate names; `activate` starts commanding; `deactivate` sends the safe command and stops;
`cleanup` lets the run go. A refused transition returns failure, logs the reason and shows it on
/diagnostics. The robot's messages come from outside any run, so they carry no seal: they are
checked by shape (joint names, counts, finite values) instead.

Every new joint state is answered in its callback: the task's state assembled by joint name, the
greedy action, clamped to the actuator limits, in the controller's joint order. A watchdog thread
sends the safe command when no new joint state arrived for `state_timeout` seconds, and commanding
resumes when states flow again.
"""

from __future__ import annotations

import functools
import math
import signal
import sys
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import rclpy
from rcl_interfaces.msg import SetParametersResult
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from npp_ros.run.deploy import (
    COMMAND_INTERFACES,
    Acceptance,
    CommandLimits,
    Coverage,
    Deployment,
    GateRefusal,
    JointLayout,
    NonFiniteState,
    RobotStateError,
    Watchdog,
    check_command_interface,
    load_deployment,
    parse_names,
    percentiles,
    safe_command,
    stored_state,
)
from npp_ros_graph.runtime.diagnostics import ERROR, OK, WARN, DiagnosticsReporter, Health
from npp_ros_graph.runtime.node import ThrottledWarnings, run_node
from npp_ros_graph.transport.convert import float64_array
from npp_ros_graph.transport.parameters import Param, declare_settings, parameter_help
from npp_ros_graph.transport.topics import CONTROL_QOS, FORWARD_COMMANDS, JOINT_STATES

STOP_SERVICE = "~/stop"
LATENCY_WINDOW = 1000  # the diagnostics' latency percentiles are over this many latest answers

# Read at configure, so an operator may change them while the node is unconfigured.
Changeable = functools.partial(Param, read_only=False)

PARAMETERS = (
    Changeable("run_dir", "", "the run folder to deploy (holds run.sqlite)"),
    Changeable("robot_model_fingerprint", "", "the robot's model fingerprint (npp-robot logs it); must be the "
               "certified plant's"),
    Changeable("max_epsilon", math.inf, "largest certified epsilon this deployment accepts", 0.0),
    Changeable("min_p", 0.0, "smallest certified p (share of s0 ~ rho within epsilon) accepted", 0.0, 1.0),
    Changeable("max_delta", 1.0, "largest certified delta (the claim's failure probability) accepted", 0.0, 1.0),
    Changeable("override_gate", False, "deploy even when the gate refuses (each reason logged as an error and kept on "
               "/diagnostics); never for a run file whose data fail their checksums"),
    Changeable("joint_states_topic", JOINT_STATES, "the robot's sensor_msgs/JointState topic"),
    Changeable("command_topic", FORWARD_COMMANDS, "the controller's std_msgs/Float64MultiArray command topic"),
    Changeable("command_joints", "", "the controller's joints in command order, comma-separated; empty = the task's "
               "actuated joints in the task's order"),
    Changeable("command_interface", "effort", "what the controller commands; the safe command is zero effort, or "
               "the present position held", choices=COMMAND_INTERFACES),
    Changeable("effort_limit", 0.0, "largest |command| on top of the model's actuator limits; 0 = the model's only",
               0.0),
    Changeable("state_timeout", 0.1, "seconds without a new joint state before the safe command is sent", 1e-3),
    Changeable("coverage_radius", 0.0, "distance from the policy's data beyond which a state is reported as outside "
               "the certificate's coverage; 0 = the farthest a checked s0 of the run lay from it", 0.0),
    Changeable("stop_outside_coverage", False, "deactivate at the first state outside the coverage (or non-finite)"),
)  # fmt: skip


@dataclass(frozen=True)
class DeploySettings:
    """npp-deploy's parameters; the gate's limits are checked by Acceptance, the joints once the task is known."""

    run_dir: str
    robot_model_fingerprint: str
    max_epsilon: float
    min_p: float
    max_delta: float
    override_gate: bool
    joint_states_topic: str
    command_topic: str
    command_joints: str
    command_interface: str
    effort_limit: float
    state_timeout: float
    coverage_radius: float
    stop_outside_coverage: bool

    def __post_init__(self) -> None:
        self.acceptance()
        if not self.joint_states_topic.strip() or not self.command_topic.strip():
            raise ValueError("joint_states_topic and command_topic must name topics")

    def acceptance(self) -> Acceptance:
        return Acceptance(
            self.max_epsilon, self.min_p, self.max_delta, self.robot_model_fingerprint, self.override_gate
        )


USAGE = f"""npp-deploy: one certified run's policy drives a robot over ros2_control topics (lifecycle node
"npp_deploy").

Managed: parameters are read at configure (change them while unconfigured); drive it with the standard
lifecycle services (npp-deploy-ctl configure|activate|deactivate|
cleanup|shutdown|stop|state, or `ros2 lifecycle set`). configure checks the run (checksums, a proven
certificate, the operator's limits, the robot's model fingerprint) and fails with the reason; activate
starts commanding; deactivate sends the safe command and stops.

subscribes  joint_states_topic (sensor_msgs/JointState: names in any order, extra joints ignored)
publishes   command_topic (std_msgs/Float64MultiArray, one entry per command joint, in their order)
            /diagnostics (diagnostic_msgs/DiagnosticArray: lifecycle state, gate, watchdog, clamps,
            coverage, latency)
serves      /<node>/stop (std_srvs/Trigger): deactivate at once
            /<node>/change_state, get_state, ... (lifecycle_msgs)

{parameter_help(PARAMETERS)}
"""


class DeployNode(LifecycleNode):
    def __init__(self) -> None:
        super().__init__("npp_deploy")
        self.settings = declare_settings(self, PARAMETERS, DeploySettings)
        self.lifecycle = "unconfigured"
        self.deployment: Deployment | None = None
        self.layout: JointLayout | None = None
        self.limits: CommandLimits | None = None
        self.coverage: Coverage | None = None
        self.refusal = ""  # the gate's last reason, shown until a configure passes
        self.last_error = ""
        self.active = False
        self._raw: np.ndarray | None = None  # the last joint state taken, [positions, velocities]
        self._last_answered: tuple[int, int] | None = None  # the stamp of the last state answered
        self._command = Float64MultiArray()
        self._latencies: deque[float] = deque(maxlen=LATENCY_WINDOW)
        self.counts = dict.fromkeys(
            ("answered", "refused states", "overtaken states", "repeated stamps", "clamped entries",
             "outside coverage", "watchdog expiries"), 0,
        )  # fmt: skip
        self._warn = ThrottledWarnings(self)
        self._state_sub = None
        self.command_pub: Publisher | None = None  # created at configure, on the configured topic
        self.create_service(Trigger, STOP_SERVICE, self.on_stop)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.watchdog = Watchdog(self.settings.state_timeout, self.on_states_stopped)
        self.diagnostics = DiagnosticsReporter(self, self.health)
        self.get_logger().info(f"unconfigured; run_dir {self.settings.run_dir or '(none given)'}")

    # ---------------------------------------------------------------- lifecycle
    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        """Parameters take effect at configure, so they may change only while unconfigured."""
        if self.lifecycle == "unconfigured":
            return SetParametersResult(successful=True)
        names = ", ".join(p.name for p in params)
        return SetParametersResult(successful=False, reason=f"{names}: read at configure; clean up first")

    def _read_settings(self) -> DeploySettings:
        return DeploySettings(**{param.name: self.get_parameter(param.name).value for param in PARAMETERS})

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self.settings = settings = self._read_settings()
            deployment = load_deployment(settings.run_dir, settings.acceptance())
            plant = deployment.plant
            check_command_interface(plant, settings.command_interface)
            layout = JointLayout.of_plant(plant, parse_names(settings.command_joints))
            coverage = Coverage.of_deployment(deployment, settings.coverage_radius)
        except (GateRefusal, ValueError) as exc:
            return self._refuse("configure", str(exc))
        except Exception as exc:  # whatever it is, configure fails with its reason, never silently
            return self._refuse("configure", f"{type(exc).__name__}: {exc}")
        for reason in deployment.overridden:
            self.get_logger().error(f"GATE OVERRIDDEN (override_gate is true): {reason}")
        self.deployment, self.layout, self.coverage = deployment, layout, coverage
        self.limits = CommandLimits.of_plant(plant, settings.effort_limit)
        self.refusal = ""
        self.watchdog.timeout = settings.state_timeout
        self.command_pub = self.create_publisher(Float64MultiArray, settings.command_topic, CONTROL_QOS)
        self._state_sub = self.create_subscription(
            JointState, settings.joint_states_topic, self.on_joint_state, CONTROL_QOS
        )
        self.get_logger().info(
            f"configured: {deployment.describe()}; state joints {list(layout.state_joints)} from "
            f"{self._state_sub.topic_name}, commands for {list(layout.command_joints)} on "
            f"{self.command_pub.topic_name} ({settings.command_interface}), limits {self.limits.describe()}, "
            f"coverage radius {coverage.radius:.4g}"
        )
        if math.isinf(coverage.radius):
            self.get_logger().warning(
                "no checked s0 outside the policy's data calibrates the coverage radius: set coverage_radius"
            )
        return self._became("inactive")

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        if self.deployment is None:
            return self._refuse("activate", "not configured")
        self.active = True
        self.watchdog.arm()
        self.get_logger().info("active: commanding the robot")
        if self.command_pub is not None and self.command_pub.get_subscription_count() == 0:
            self.get_logger().warning(
                f"nothing subscribes to {self.command_pub.topic_name} yet: is the controller loaded and active?"
            )
        return self._became("active")

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.stop_commanding("deactivated")
        return self._became("inactive")

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return self._became("unconfigured")

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.stop_commanding("shutting down")
        self._release()
        return self._became("finalized")

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.stop_commanding("error")
        self._release()
        return self._became("unconfigured")

    def _became(self, label: str) -> TransitionCallbackReturn:
        self.lifecycle = label
        self.diagnostics.publish()
        return TransitionCallbackReturn.SUCCESS

    def _refuse(self, transition: str, reason: str) -> TransitionCallbackReturn:
        self.refusal = f"{transition} refused: {reason}"
        self.get_logger().error(self.refusal)
        self.diagnostics.publish()
        return TransitionCallbackReturn.FAILURE

    def _release(self) -> None:
        if self._state_sub is not None:
            self.destroy_subscription(self._state_sub)
            self._state_sub = None
        if self.command_pub is not None:
            self.destroy_publisher(self.command_pub)
            self.command_pub = None
        self.deployment = self.layout = self.limits = self.coverage = None
        self._raw, self._last_answered = None, None

    def stop_commanding(self, why: str) -> None:
        was_active, self.active = self.active, False
        self.watchdog.disarm()
        if was_active:
            sent = self.send_safe_command()
            self.get_logger().info(f"{why}: {sent}; commanding stopped")

    def send_safe_command(self) -> str:
        """Publish the safe command (zero effort, or the present position held); say what was sent."""
        layout, publisher = self.layout, self.command_pub
        if layout is None or publisher is None:
            return "no safe command (not configured)"
        try:
            command = safe_command(self.settings.command_interface, layout, self._raw)
        except RobotStateError as exc:
            return f"no safe command: {exc}"
        publisher.publish(Float64MultiArray(data=float64_array(command)))
        return f"safe command {command.tolist()} sent"

    def on_stop(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """The stop service: deactivate at once."""
        if self.lifecycle != "active":
            response.success, response.message = True, f"not commanding ({self.lifecycle})"
            return response
        self.get_logger().warning("stop requested: deactivating")
        self.trigger_deactivate()
        response.success = self.lifecycle == "inactive"
        response.message = "stopped: safe command sent, inactive" if response.success else "could not deactivate"
        return response

    # ---------------------------------------------------------------- control
    def on_joint_state(self, msg: JointState) -> None:
        """Answer the newest joint state: those already behind this one on the wire are checked too, and a
        state overtaken by a newer one is dropped (counted), so a slow answer never builds a queue."""
        started = time.perf_counter()
        layout, deployment, subscription = self.layout, self.deployment, self._state_sub
        if layout is None or deployment is None or subscription is None:
            return
        newest: tuple[np.ndarray, JointState] | None = None
        while msg is not None:
            try:
                raw = layout.state(msg.name, msg.position, msg.velocity)
            except RobotStateError as exc:
                self._refused_state(exc)
            else:
                self.counts["overtaken states"] += int(newest is not None)
                newest = (raw, msg)
            with subscription.handle:
                taken = subscription.handle.take_message(subscription.msg_type, subscription.raw)
            msg = None if taken is None else taken[0]
        if newest is None:
            return
        raw, msg = newest
        self._raw = raw
        if not self.active:
            return
        stamp = (msg.header.stamp.sec, msg.header.stamp.nanosec)
        if stamp == self._last_answered:
            self.counts["repeated stamps"] += 1  # the same state again: not new, not answered twice
            return
        self._last_answered = stamp
        if self.watchdog.feed():
            self.get_logger().info("joint states flow again: commanding resumes")
        try:
            self._answer(raw, deployment, layout, started)
        except Exception as exc:  # a single state must never take the node down
            if not rclpy.ok():
                return  # interrupted while answering: the safe command went out, nothing more can
            self.last_error = f"could not answer a joint state: {type(exc).__name__}: {exc}"
            self.get_logger().error(self.last_error)

    def _answer(self, raw: np.ndarray, deployment: Deployment, layout: JointLayout, started: float) -> None:
        state = stored_state(deployment.plant, raw)
        assert self.coverage is not None and self.limits is not None
        policy = deployment.policy
        chosen = policy.greedy_index(state)  # pi(s) = a_{i*}; s_{i*} spares the coverage check a search
        inside, distance = self.coverage.covers(state, policy.dataset.states[chosen])
        if not inside:
            self.counts["outside coverage"] += 1
            problem = (
                f"state {np.round(state, 4).tolist()} is {distance:.4g} from the certified policy's data, beyond "
                f"the coverage radius {self.coverage.radius:.4g}: the certificate says nothing about it"
            )
            if self._outside(problem):
                return
        action, clamped = self.limits.clamp(policy.dataset.actions[chosen])
        if clamped:
            self.counts["clamped entries"] += clamped
            self._warn("clamped", f"command clamped to the actuator limits {self.limits.describe()}")
        self._command.data = float64_array(layout.command(action))
        assert self.command_pub is not None
        self.command_pub.publish(self._command)
        self.counts["answered"] += 1
        self._latencies.append(time.perf_counter() - started)

    def _refused_state(self, exc: RobotStateError) -> None:
        self.counts["refused states"] += 1
        self.last_error = f"joint state refused: {exc}"
        self._warn(type(exc).__name__, self.last_error)
        if isinstance(exc, NonFiniteState) and self.active:
            self.counts["outside coverage"] += 1
            self._outside(str(exc))

    def _outside(self, problem: str) -> bool:
        """Report a state the certificate does not cover; True when the node stops for it."""
        self.last_error = problem
        if self.settings.stop_outside_coverage and self.active:
            self.get_logger().error(f"{problem}; stop_outside_coverage is true: deactivating")
            self.trigger_deactivate()
            return True
        self._warn("outside coverage", problem)
        return False

    def on_states_stopped(self, age: float) -> None:
        """Watchdog thread: no new joint state for state_timeout seconds."""
        sent = self.send_safe_command()
        self.counts["watchdog expiries"] += 1
        self.last_error = (
            f"no new joint state for {age * 1e3:.0f} ms (state_timeout {self.settings.state_timeout * 1e3:.0f} ms): "
            f"{sent}; no commanding until states flow again"
        )
        self.get_logger().error(self.last_error)
        self.diagnostics.publish()

    # ---------------------------------------------------------------- health
    def health(self) -> Health:
        values: dict[str, object] = {"lifecycle state": self.lifecycle, "run_dir": self.settings.run_dir}
        deployment = self.deployment
        if deployment is not None:
            values["policy"] = deployment.describe()
            if deployment.overridden:
                values["gate overridden"] = "; ".join(deployment.overridden)
        values.update(self.counts)
        p50, p99 = percentiles(self._latencies)
        if self._latencies:
            values["answer time p50 / p99 (us)"] = f"{p50 * 1e6:.0f} / {p99 * 1e6:.0f}"
        if self.refusal:
            return Health(self.refusal, values, ERROR, self.last_error)
        if self.active and self.watchdog.expired:
            return Health("active, joint states stopped: safe command sent", values, ERROR, self.last_error)
        if self.active:
            level = WARN if deployment is not None and deployment.overridden else OK
            return Health("active: commanding the robot", values, level, self.last_error)
        return Health(f"{self.lifecycle}: not commanding", values, OK, self.last_error)

    def destroy_node(self) -> None:
        if self.active:
            self.stop_commanding("exiting")
        self.watchdog.close()
        super().destroy_node()


def make_node() -> DeployNode:
    """The node, with Ctrl-C and SIGTERM handled so that the safe command goes out before the context shuts
    down (rclpy's own handler shuts it down at once, and a shut-down context cannot publish)."""
    node = DeployNode()

    def stop(signum: int, frame: object) -> None:
        for each in (signal.SIGINT, signal.SIGTERM):
            signal.signal(each, signal.SIG_IGN)  # once: a second signal must not interrupt the teardown
        node.stop_commanding(signal.Signals(signum).name)
        rclpy.try_shutdown()  # what rclpy's handler does: run_node's spin loop ends and tears down

    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, stop)  # after rclpy.init, which installed its own
    return node


def main(argv: Sequence[str] | None = None) -> int:
    return run_node(make_node, argv, USAGE, events=True)


if __name__ == "__main__":
    sys.exit(main())
