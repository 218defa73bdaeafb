"""npp-deploy: a managed (lifecycle) node that drives a robot with one certified run's policy, on ros2_control topics.

`configure` passes the run folder through the gate (npp_ros.deployment.gate.load_deployment: checksums, the
certificate, what the operator accepts, the robot's model) and builds exactly the policy the
certificate names; `activate` starts commanding; `deactivate` sends the safe command and stops;
`cleanup` lets the run go. A refused transition returns failure, logs the reason and shows it on
/diagnostics. The robot's messages come from outside any run, so they carry no seal: they are
checked by shape (joint names, counts, finite values) instead. The robot's model fingerprint is
computed from the MJCF the robot publishes on /robot_description (latched, as robot_state_publisher
publishes its URDF), unless the operator gives one.

Every new joint state is answered in its callback: the task's state assembled by joint name, the
greedy action, clamped to the actuator limits, in the controller's joint order. A state the policy
cannot act on is refused with its reason and does not count as fresh. A watchdog thread sends the
safe command when no fresh command went out for `state_timeout` seconds, and commanding resumes when
usable states flow again; its decision and the fresh commands are serialized, so a safe command never
follows a fresh answer. For a run certified on a set of robots, the model monitor (npp_ros.deployment.model_monitor)
checks each transition against the set after the command went out: WARN while the robot's transitions leave
it, and with on_model_mismatch stop, a stop.

A task whose state holds a target (a task file's ``state.target``) has joints no robot measures: the target is a
point a user publishes on ``target_topic`` (geometry_msgs/PointStamped in ``target_frame``), whose coordinates
(the point less the target's origin, at rest) complete the state. Until one comes nothing is commanded but the
watchdog's safe command, and the node says it waits for a target; a point in another frame, not finite, or
outside the box rho draws targets from (the certificate covers those only) is refused with its reason, never
clamped, and the target before it (or none) is kept. A new target starts the model monitor's chain afresh: the
target moves between two states, which no transition of the model does.

/diagnostics says what is true now: OK while states flow and commands go out (or while the robot has
not published yet), WARN while states are stale or refused, ERROR for a refused configure; the last
event (a watchdog expiry, a stop, a refusal) is named with its time among the values. All of that is the
node's DeploymentState (npp_ros.deployment.state): the node tells it what happened (a stop with its StopReason),
and publishes its status. Beside the node in this package: its parameters (settings), the robot's description and
the fingerprint the gate checks (description), the check at an identified robot (robot_check) and the model monitor
(model_watch).
"""

from __future__ import annotations

import functools
import math
import re
import signal
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

import numpy as np
import rclpy
from geometry_msgs.msg import PointStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String
from std_srvs.srv import Trigger

from npp_ros.deployment.commands import CommandLimits, check_command_interface, gravity_hold, safe_command
from npp_ros.deployment.coverage import Coverage
from npp_ros.deployment.gate import Deployment, GateRefusal, load_deployment
from npp_ros.deployment.joints import (
    JointLayout,
    NonFiniteState,
    NoTarget,
    RobotStateError,
    describe_point,
    parse_names,
    stored_state,
)
from npp_ros.deployment.model_monitor import ModelMonitor
from npp_ros.deployment.robot_model import DescriptionError, mjcf_fingerprint
from npp_ros.deployment.robot_set import robots_of
from npp_ros.deployment.state import DeploymentState, Lifecycle, StopReason
from npp_ros.deployment.timing import Watchdog
from npp_ros.identification.window import window_seconds
from npp_ros.policy.bounds import NonparametricPolicy, PathEpisode
from npp_ros_graph.nodes.deploy.description import RobotDescription
from npp_ros_graph.nodes.deploy.model_watch import ModelWatch
from npp_ros_graph.nodes.deploy.robot_check import check_robot, progress
from npp_ros_graph.nodes.deploy.settings import PARAMETERS, DeploySettings
from npp_ros_graph.runtime.diagnostics import DiagnosticsReporter, Health, health_of_state
from npp_ros_graph.runtime.node import ThrottledWarnings, request_stop, run_node
from npp_ros_graph.transport.convert import float64_array, point_from_msg
from npp_ros_graph.transport.parameters import declare_settings, parameter_help
from npp_ros_graph.transport.topics import CONTROL_QOS

STOP_SERVICE = "~/stop"
CLEAR_MISMATCH_SERVICE = "~/clear_model_mismatch"
NUMBERS = re.compile(r"[-+]?\d+(?:\.\d*)?(?:e[-+]?\d+)?")

USAGE = f"""npp-deploy: one certified run's policy drives a robot over ros2_control topics (lifecycle node
"npp_deploy").

Managed: parameters are read at configure (change them while unconfigured); drive it with the standard
lifecycle services (npp-deploy-ctl configure|activate|deactivate|cleanup|shutdown|stop|clear-mismatch|state,
or `ros2 lifecycle set`). configure is the gate: it fails, with the reason, on
  - a run file that does not read (checksums of every trajectory, types of every stored value);
  - a run file whose seal does not match it (an edit after the run), or that has no seal (unless allow_unsealed);
  - with trusted_keys: a run not signed by one of them over its seal (the key that verifies is the signer);
  - a run that does not follow from its own seed and stored expert answers (rederive: s0 and robots drawn again,
    each check re-run, the certificate issued again, the first episode that differs named);
  - no certificate, one that does not follow from the run's log, one not proven, or one weaker than max_epsilon,
    min_p, max_delta;
  - a robot whose model fingerprint is not the certified plant's or, for a run on a set of robots, whose
    description lies outside the set;
  - with identified_robot: a robot at which the certified policy, simulated at the robot identified from its own
    motion, has a lower confidence bound on its success below robot_min_success (default the certificate's p).
A seal is a checksum anyone with this code can recompute; a signature is the proof of who certified.
activate starts commanding; while active the watchdog (state_timeout), the command limits, the coverage check
and, for a run on a set of robots, the model monitor watch the robot: each transition checked against the set's
corners, and the set's parameters fitted to its last seconds of motion (monitor_window); a robot found outside
stays WARN until cleared and, by default, is stopped (on_model_mismatch). deactivate sends the safe command and
stops. A certificate on a set of robots is an average over the set: it promises nothing for one
robot of it.

subscribes  joint_states_topic (sensor_msgs/JointState: names in any order, extra joints ignored)
            robot_description_topic (std_msgs/String, transient local: the robot's MJCF, for its fingerprint)
            target_topic, a task whose state holds a target (geometry_msgs/PointStamped in target_frame: the
            point to reach, from configure on); nothing is commanded before the first; one in another frame, not
            finite or outside the box rho draws targets from is refused (not clamped), the target before kept
publishes   command_topic (std_msgs/Float64MultiArray, one entry per command joint, in their order)
            /diagnostics (diagnostic_msgs/DiagnosticArray: lifecycle state, gate, what it does now, the last
            event and its time, refusals, watchdog, clamps, coverage, answer time, state period)
serves      /<node>/stop (std_srvs/Trigger): deactivate at once
            /<node>/clear_model_mismatch (std_srvs/Trigger): the operator clears the model monitor's finding,
            which stays WARN on /diagnostics until then
            /<node>/change_state, get_state, ... (lifecycle_msgs)

{parameter_help(PARAMETERS)}
"""


class DeployNode(LifecycleNode):
    def __init__(self) -> None:
        super().__init__("npp_deploy")
        self.settings = declare_settings(self, PARAMETERS, DeploySettings)
        self.state = DeploymentState()  # what it does and did: /diagnostics publishes its status
        self.deployment: Deployment | None = None
        self.actor: NonparametricPolicy | PathEpisode | None = None  # the policy over this activation (policy.episode)
        self.layout: JointLayout | None = None
        self.limits: CommandLimits | None = None
        self.coverage: Coverage | None = None
        self.robot_check = ""  # the check at the identified robot, in words ("" on the exact model)
        self._raw: np.ndarray | None = None  # the last joint state taken, [positions, velocities]
        self.hold: Callable[[np.ndarray], np.ndarray] | None = None  # safe_effort gravity: the torques that hold
        self._last_answered: tuple[int, int] | None = None  # the stamp of the last state answered
        self._command = Float64MultiArray()
        self.stopped_by: StopReason | None = None  # the signal that stops the process (SIGINT, SIGTERM)
        self._warn = ThrottledWarnings(self)
        # A run certified on a set of robots: its transitions and its latest motion are watched (nothing otherwise).
        self.model_watch = ModelWatch(
            self.state, logger=self.get_logger(), warn=self._warn, publish=lambda: self.diagnostics.publish(),
            deactivate=self.trigger_deactivate,
        )  # fmt: skip
        self._state_sub = None
        self._target_sub = None
        self.command_pub: Publisher | None = None  # created at configure, on the configured topic
        self.create_service(Trigger, STOP_SERVICE, self.on_stop)
        self.create_service(Trigger, CLEAR_MISMATCH_SERVICE, self.on_clear_mismatch)
        # From the start, not at configure: the description is latched, and configure must find it there.
        self.robot_description = RobotDescription(self, self.settings.robot_description_topic, self.on_description)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.watchdog = Watchdog(self.settings.state_timeout, self.on_states_stopped, self.after_states_stopped)
        self.diagnostics = DiagnosticsReporter(self, self.health)
        self.get_logger().info(f"unconfigured; run_dir {self.settings.run_dir or '(none given)'}")

    @property
    def lifecycle(self) -> str:
        return self.state.lifecycle

    @property
    def refusal(self) -> str:
        """The last refused transition or changed model, "" once a configure passed."""
        return self.state.refusal

    @property
    def active(self) -> bool:
        """Commanding: activated and not stopped since."""
        return self.state.commanding

    # ---------------------------------------------------------------- the robot's model
    def on_description(self, msg: String) -> None:
        """The robot's MJCF: read at configure; a different model while configured stops the deployment."""
        self.robot_description.received(msg)
        deployment = self.deployment
        if deployment is None or self.state.fingerprint_source != self.robot_description.source:
            return
        try:
            fingerprint = mjcf_fingerprint(deployment.plant, msg.data)
        except DescriptionError as exc:
            fingerprint = f"none ({exc})"
        if fingerprint == self.state.fingerprint:
            return
        problem = (
            f"the robot published a different model on {self.robot_description.topic} (fingerprint "
            f"{fingerprint[:12]}...) than the one configure checked ({self.state.fingerprint[:12]}...)"
        )
        self.state.model_changed(problem)  # ERROR until configure checks the model again
        if self.active:
            self.get_logger().error(f"{problem}: deactivating")
            self.state.stop_requested(StopReason.MODEL_CHANGED)
            self.trigger_deactivate()
        else:
            self.get_logger().error(f"{problem}: configure again (cleanup, configure) before activating")
            self.diagnostics.publish()

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
        # Three steps, each refusing with its reason; a ValueError is a refusal only where the settings are
        # checked: from the gate (which refuses with GateRefusal) it is unexpected, and named by its type.
        try:
            self.settings = settings = self._read_settings()
            self.robot_description.wait(settings)
            fingerprint, source = self.robot_description.fingerprint(settings)
            acceptance = settings.acceptance(fingerprint)
            description = self.robot_description.latest
            if description is not None and source == self.robot_description.source:  # a run on a set of robots
                acceptance = replace(acceptance, robot_description=description.text)  # compares the MJCF itself
        except ValueError as exc:
            return self._refuse("configure", str(exc))
        except Exception as exc:  # whatever it is, configure fails with its reason, never silently
            return self._refuse("configure", f"{type(exc).__name__}: {exc}")
        try:
            deriving = progress(self.get_logger(), "gate: deriving the run again, episode {done} of {total}")
            deployment = load_deployment(settings.run_dir, acceptance, deriving)
        except GateRefusal as exc:
            reason = str(exc)
            if source and "fingerprint" in reason:
                reason += f" (the robot's fingerprint came from {source})"
            return self._refuse("configure", reason)
        except Exception as exc:
            return self._refuse("configure", f"{type(exc).__name__}: {exc}")
        try:
            plant = deployment.plant
            check_command_interface(plant, settings.command_interface)
            holding = settings.command_interface == "effort" and settings.safe_effort == "gravity"
            hold = gravity_hold(plant) if holding else None
            layout = JointLayout.of_plant(plant, parse_names(settings.command_joints))
            coverage = Coverage.of_deployment(deployment, settings.coverage_radius)
            robots = robots_of(deployment.metadata)
            monitor = None if robots.empty else ModelMonitor.of_plant(plant, robots)
        except ValueError as exc:  # a setting the run's plant cannot take
            return self._refuse("configure", str(exc))
        except Exception as exc:
            return self._refuse("configure", f"{type(exc).__name__}: {exc}")
        try:
            robot_check = check_robot(settings, deployment, robots, self.get_logger())
        except ValueError as exc:  # an identification that does not fit this run, or a robot it must not move
            return self._refuse("configure", str(exc))
        except Exception as exc:
            return self._refuse("configure", f"{type(exc).__name__}: {exc}")
        self.robot_check = robot_check
        for reason in deployment.overridden:
            self.get_logger().error(f"GATE OVERRIDDEN (override_gate is true): {reason}")
        provenance = f"run file {deployment.seal.describe()}; run {deployment.signed}; {deployment.derived}"
        if deployment.signed.startswith("signed by") and settings.trusted_keys.strip():
            self.get_logger().info(provenance)
        else:  # unsigned, or a signature nobody asked to check: the operator should know
            self.get_logger().warning(provenance)
        self.deployment, self.layout, self.coverage = deployment, layout, coverage
        self.hold = hold
        seconds = window_seconds(settings.monitor_window, robots)
        self.model_watch.configure(monitor, seconds, plant.dt, deployment.metadata, settings.on_model_mismatch)
        self.state.configured(fingerprint, source)
        self.limits = CommandLimits.of_plant(plant, settings.effort_limit)
        self.watchdog.timeout = settings.state_timeout
        self.command_pub = self.create_publisher(Float64MultiArray, settings.command_topic, CONTROL_QOS)
        self._state_sub = self.create_subscription(
            JointState, settings.joint_states_topic, self.on_joint_state, CONTROL_QOS
        )
        if layout.target is not None:
            self._target_sub = self.create_subscription(
                PointStamped, settings.target_topic, self.on_target, CONTROL_QOS
            )
            self.state.awaits_target(self._target_sub.topic_name)
            self.get_logger().info(
                f"the state holds a target ({', '.join(layout.target.joints)}): waiting for a target on "
                f"{self._target_sub.topic_name} (geometry_msgs/PointStamped in frame {settings.target_frame!r}) "
                f"inside the box rho draws targets from, {layout.target.describe()}"
            )
        self.get_logger().info(
            f"configured: {deployment.describe()}; robot model fingerprint {fingerprint[:12]}... from {source}; "
            f"state joints {list(layout.measured)} from {self._state_sub.topic_name}, commands for "
            f"{list(layout.command_joints)} on {self.command_pub.topic_name} ({settings.command_interface}), "
            f"limits {self.limits.describe()}, coverage radius {coverage.radius:.4g}"
        )
        if monitor is not None:
            self.get_logger().info(
                f"model monitor: {len(monitor.corners)} corners of the certified set ({robots.describe()}); "
                f"on_model_mismatch {settings.on_model_mismatch}"
            )
        if math.isinf(coverage.radius):
            self.get_logger().warning(
                "no checked s0 outside the policy's data calibrates the coverage radius: set coverage_radius"
            )
        return self._became("inactive")

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        if self.deployment is None:
            return self._refuse("activate", "not configured")
        if self.state.refusal:  # the robot's model changed since configure
            return self._refuse("activate", self.state.refusal)
        self.model_watch.activated()
        self.actor = self.deployment.policy.episode()  # a path policy's path is this activation's, from its state
        self.state.activated()
        self.watchdog.arm()
        self.get_logger().info("active: commanding the robot from its next usable joint state")
        if self.state.waiting_for_target:
            self.get_logger().info(f"waiting for a target on {self.state.target_topic}: nothing is commanded before")
        if self.command_pub is not None and self.command_pub.get_subscription_count() == 0:
            self.get_logger().warning(
                f"nothing subscribes to {self.command_pub.topic_name} yet: is the controller loaded and active?"
            )
        return self._became("active")

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.stop_commanding(self.state.deactivating())
        return self._became("inactive")

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        self.state.cleaned_up()
        return self._became("unconfigured")

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.stop_commanding(StopReason.SHUTDOWN)
        self._release()
        return self._became("finalized")

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.stop_commanding(StopReason.ERROR)
        self._release()
        return self._became("unconfigured")

    def _became(self, label: Lifecycle) -> TransitionCallbackReturn:
        self.state.became(label)
        self.diagnostics.publish()
        return TransitionCallbackReturn.SUCCESS

    def _refuse(self, transition: str, reason: str) -> TransitionCallbackReturn:
        self.get_logger().error(self.state.refuse(transition, reason))
        self.diagnostics.publish()
        return TransitionCallbackReturn.FAILURE

    def _release(self) -> None:
        if self._state_sub is not None:
            self.destroy_subscription(self._state_sub)
            self._state_sub = None
        if self._target_sub is not None:
            self.destroy_subscription(self._target_sub)
            self._target_sub = None
        if self.command_pub is not None:
            self.destroy_publisher(self.command_pub)
            self.command_pub = None
        self.deployment = self.layout = self.limits = self.coverage = None
        self.model_watch.released()
        self.state.released()
        self._raw, self._last_answered = None, None

    def stop_commanding(self, why: StopReason) -> None:
        """Stop commanding; the safe command goes out in the watchdog's step, so no fresh command follows it."""
        was_active = self.state.stop_commanding()
        sent = self.watchdog.disarm(self.send_safe_command if was_active else None)
        if was_active:
            self.state.stopped(why, sent)
            self.get_logger().info(f"{why.words}: {sent}; commanding stopped")

    def send_safe_command(self) -> str:
        """Publish the safe command (zero effort or the effort that holds the pose, or the present position held);
        say what was sent."""
        layout, publisher = self.layout, self.command_pub
        if layout is None or publisher is None:
            return "no safe command (not configured)"
        try:
            command = safe_command(self.settings.command_interface, layout, self._raw, self.hold)
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
        self.state.note(StopReason.STOP_REQUESTED.words)
        self.state.stop_requested(StopReason.STOP_REQUESTED)
        self.trigger_deactivate()
        response.success = self.lifecycle == "inactive"
        response.message = "stopped: safe command sent, inactive" if response.success else "could not deactivate"
        return response

    def on_clear_mismatch(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """The operator has seen the model monitor's finding: /diagnostics is OK again until the next one."""
        cleared = self.state.mismatch_cleared()
        self.model_watch.cleared()
        response.success = True
        response.message = f"cleared: {cleared}" if cleared else "no model mismatch to clear"
        if cleared:
            self.get_logger().warning(f"the operator cleared the model monitor's finding: {cleared}")
            self.diagnostics.publish()
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
            self.state.arrived(time.monotonic())
            try:
                raw = layout.state(msg.name, msg.position, msg.velocity)
            except NoTarget as exc:
                self._raw = exc.raw  # nothing to act on yet (the node waits): the pose a safe command may hold
            except RobotStateError as exc:
                self._refused_state(exc)
            else:
                self.state.overtaken(int(newest is not None))
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
            self.state.repeated_stamp()
            return
        self._last_answered = stamp
        try:
            self._answer(raw, deployment, layout, started, msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec)
        except Exception as exc:  # a single state must never take the node down
            if not rclpy.ok():
                return  # the context is gone (the process is ending): nothing more can be sent
            self._refused_state(RobotStateError(f"could not answer it: {type(exc).__name__}: {exc}"))

    def _answer(
        self, raw: np.ndarray, deployment: Deployment, layout: JointLayout, started: float, stamp: float
    ) -> None:
        state = stored_state(deployment.plant, raw)
        assert self.coverage is not None and self.limits is not None
        policy = deployment.policy
        assert self.actor is not None  # made at activation
        wanted, chosen = self.actor.act_at(state)  # the certified policy's own action; s_{i*} spares coverage a search
        inside, distance = self.coverage.covers(state, policy.dataset.states[chosen])
        if not inside:
            problem = (
                f"state {np.round(state, 4).tolist()} is {distance:.4g} from the certified policy's data, beyond "
                f"the coverage radius {self.coverage.radius:.4g}: the certificate says nothing about it"
            )
            if self._outside(problem):
                return
        action, clamped = self.limits.clamp(wanted)
        if clamped:
            self.state.clamped(clamped)
            self._warn("clamped", f"command clamped to the actuator limits {self.limits.describe()}")
        self._command.data = float64_array(layout.command(action))
        publisher = self.command_pub
        assert publisher is not None
        # Sent in the watchdog's step: its safe command cannot follow this fresh one.
        outcome = self.watchdog.send_fresh(functools.partial(publisher.publish, self._command))
        if outcome == "disarmed":
            return  # stopped meanwhile (the safe command went out): nothing more
        self.state.answered(time.perf_counter() - started, time.monotonic(), resumed=outcome == "resumed")
        if outcome == "resumed":
            self.get_logger().info("joint states flow again: commanding resumes")
            self.diagnostics.publish()
        self.model_watch.after_command(raw, action, outcome == "resumed", stamp)

    def _refused_state(self, exc: RobotStateError) -> None:
        """A state the policy cannot act on: counted, named in the log and on /diagnostics, never fresh."""
        reason = self.state.state_refused(str(exc), time.monotonic())
        # Throttled per kind of reason (its numbers aside): a flood of one fault stays one line a second,
        # and each other fault is still printed.
        self._warn(NUMBERS.sub("#", reason), reason)
        if isinstance(exc, NonFiniteState) and self.active:
            self._outside(str(exc))

    def _outside(self, problem: str) -> bool:
        """Report a state the certificate does not cover (counted); True when the node stops for it."""
        self.state.outside_coverage(problem)
        if self.settings.stop_outside_coverage and self.active:
            self.get_logger().error(f"{problem}; stop_outside_coverage is true: deactivating")
            self.state.stop_requested(StopReason.OUTSIDE_COVERAGE)
            self.trigger_deactivate()
            return True
        self._warn("outside coverage", problem)
        return False

    def on_target(self, msg: PointStamped) -> None:
        """A target: taken from the next joint state on, or refused with its reason (the target before kept)."""
        layout = self.layout
        if layout is None or layout.target is None:
            return
        try:
            coordinates = layout.aim(point_from_msg(msg, self.settings.target_frame))
        except ValueError as exc:  # another frame (MessageError), not finite or outside the box (TargetRefused)
            reason = self.state.target_refused(str(exc))
            self._warn(NUMBERS.sub("#", reason), reason)
            self.diagnostics.publish()
            return
        self.model_watch.target_moved()
        words = f"{describe_point(layout.target.point(coordinates))} in {self.settings.target_frame}"
        self.state.target_taken(words)
        self.get_logger().info(f"target {words} taken (its joints at {describe_point(coordinates)})")
        self.diagnostics.publish()

    def on_states_stopped(self, age: float) -> None:
        """Watchdog thread, in its step: no fresh command for state_timeout seconds; send the safe command."""
        self.state.watchdog_expired(age, self.settings.state_timeout, self.send_safe_command())

    def after_states_stopped(self, age: float) -> None:
        """Watchdog thread, after its step: say so."""
        stale = self.state.stale
        self.state.note(f"watchdog expiry: {stale}")
        if self.state.waiting_for_target:
            self.get_logger().info(f"waiting for a target on {self.state.target_topic}: {stale}")
        elif self.state.waiting_for_first_state:
            self.get_logger().info(f"waiting for the robot's first joint state: {stale}")
        else:
            self.get_logger().error(stale)
        self.diagnostics.publish()

    # ---------------------------------------------------------------- health
    def health(self) -> Health:
        """What the node does now (its DeploymentState's status): what it runs and on which robot, then the
        state's counters, timing and last event."""
        values: dict[str, object] = {"lifecycle state": self.state.lifecycle, "run_dir": self.settings.run_dir}
        deployment = self.deployment
        if deployment is not None:
            values["policy"] = deployment.describe()
            values["run provenance"] = f"{deployment.seal.describe()}; {deployment.signed}; {deployment.derived}"
            if self.robot_check:
                values["robot check"] = self.robot_check
            values["robot model fingerprint"] = f"{self.state.fingerprint[:12]}... from {self.state.fingerprint_source}"
            values.update(self.model_watch.values())
            if deployment.overridden:
                values["gate overridden"] = "; ".join(deployment.overridden)
        values["robot description"] = self.robot_description.describe()
        values.update(self.state.values())
        status = self.state.status(
            values,
            overridden=deployment is not None and bool(deployment.overridden),
            watchdog_expired=self.watchdog.expired,
            model_mismatch=self.state.model_mismatch,
        )
        return health_of_state(status)

    def destroy_node(self) -> None:
        if self.active:
            self.stop_commanding(self.stopped_by or StopReason.EXITING)
        self.watchdog.close()
        self.model_watch.close()
        super().destroy_node()


def make_node() -> DeployNode:
    """The node; Ctrl-C and SIGTERM are named in its log when it stops commanding.

    run_node turns both signals into a stop request and tears the node down before the context shuts
    down, so destroy_node sends the safe command after any answer in progress (never before it, as a
    safe command sent from the signal handler itself could be, interrupting an answer) and while the
    context can still publish. This handler only names the signal and passes it on to run_node's.
    """
    node = DeployNode()
    for signum in (signal.SIGINT, signal.SIGTERM):
        passed_on = signal.getsignal(signum)

        def stop(signum: int, frame: object, passed_on: Any = passed_on) -> None:
            node.stopped_by = node.stopped_by or StopReason[signal.Signals(signum).name]
            if callable(passed_on):
                passed_on(signum, frame)
            else:
                request_stop()

        signal.signal(signum, stop)  # after run_node took both signals for itself
    return node


def main(argv: Sequence[str] | None = None) -> int:
    return run_node(make_node, argv, USAGE, events=True)


if __name__ == "__main__":
    sys.exit(main())
