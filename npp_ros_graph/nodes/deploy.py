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
node's DeploymentState (npp_ros.deployment.state): the node tells it what happened, and publishes its status.
"""

from __future__ import annotations

import functools
import math
import multiprocessing
import re
import signal
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
from geometry_msgs.msg import PointStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String
from std_srvs.srv import Trigger

from npp_ros.deployment.commands import (
    COMMAND_INTERFACES,
    SAFE_EFFORTS,
    CommandLimits,
    check_command_interface,
    gravity_hold,
    safe_command,
)
from npp_ros.deployment.coverage import Coverage
from npp_ros.deployment.gate import Acceptance, Deployment, GateRefusal, load_deployment
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
from npp_ros.deployment.robot_model import DescriptionError, described_fingerprint, mjcf_fingerprint
from npp_ros.deployment.robot_set import robots_of
from npp_ros.deployment.signing import load_public_keys
from npp_ros.deployment.state import (
    MODEL_CHANGED,
    MODEL_MISMATCH,
    STOPPED_OUTSIDE,
    DeploymentState,
    Lifecycle,
    wall_time,
)
from npp_ros.deployment.timing import Watchdog
from npp_ros.identification.identified import check_identified_robot
from npp_ros.identification.window import (
    AUTO,
    EVERY_S,
    IN_A_ROW,
    WINDOW_S,
    MotionWindow,
    WindowVerdict,
    judge,
    prepare,
    window_seconds,
)
from npp_ros.policy.bounds import NonparametricPolicy, PathEpisode
from npp_ros.run.read import read_run
from npp_ros.tasks.uncertainty import UncertaintySet
from npp_ros_graph.runtime.diagnostics import DiagnosticsReporter, Health, health_of_state
from npp_ros_graph.runtime.node import ThrottledWarnings, publishers_of, request_stop, run_node, stop_requested
from npp_ros_graph.transport.convert import float64_array, point_from_msg
from npp_ros_graph.transport.parameters import Param, declare_settings, parameter_help
from npp_ros_graph.transport.topics import CONTROL_QOS, FORWARD_COMMANDS, JOINT_STATES, LATCHED_QOS

STOP_SERVICE = "~/stop"
CLEAR_MISMATCH_SERVICE = "~/clear_model_mismatch"
LATE_SHARE = 0.5  # of a control step: a command whose lag exceeds the window's least by this is left out of it
ROBOT_DESCRIPTION = "/robot_description"  # robot_state_publisher's topic (std_msgs/String, transient local)
TARGET_TOPIC = "~/target"  # a task whose state holds a target: the point to reach (geometry_msgs/PointStamped)
WAIT_SLICE_S = 0.1  # configure's wait for the description looks again at least this often (and for a stop)
NUMBERS = re.compile(r"[-+]?\d+(?:\.\d*)?(?:e[-+]?\d+)?")
MISMATCH_ACTIONS = ("warn", "stop")

# Read at configure, so an operator may change them while the node is unconfigured.
Changeable = functools.partial(Param, read_only=False)

PARAMETERS = (
    Changeable("run_dir", "", "the run folder to deploy (holds run.sqlite)"),
    Changeable("robot_model_fingerprint", "", "the robot's model fingerprint, which must be the certified plant's; "
               "empty = computed from the MJCF the robot publishes on robot_description_topic; given, it overrides "
               "that (a robot that publishes no MJCF, e.g. a URDF; npp-robot logs its fingerprint)"),
    Param("robot_description_topic", ROBOT_DESCRIPTION, "where the robot publishes its model as MJCF "
          "(std_msgs/String, transient local, as robot_state_publisher does)"),
    Changeable("description_timeout", 5.0, "seconds configure waits for the robot's latched description when it "
               "needs one (robot_model_fingerprint empty and none received yet): a node started just before "
               "configure may not have discovered the robot; 0 = do not wait", 0.0, 120.0),
    Changeable("max_epsilon", math.inf, "largest certified epsilon this deployment accepts", 0.0),
    Changeable("min_p", 0.0, "smallest certified p (share of s0 ~ rho within epsilon) accepted", 0.0, 1.0),
    Changeable("max_delta", 1.0, "largest certified delta (the claim's failure probability) accepted", 0.0, 1.0),
    Changeable("trusted_keys", "", "public keys (npp-sign keygen's NAME.pub files, comma-separated) whose "
               "signature a run must carry; empty = any run, signed or not (the log says which)"),
    Changeable("allow_unsealed", False, "accept a run file without a seal (one from before seals, or whose seal was "
               "removed): nothing then shows it unchanged since its run; /diagnostics says so while it runs"),
    Changeable("rederive", True, "derive the run again at configure from its seed and stored expert answers (each "
               "episode's s0 and robot drawn again, each check re-run, the certificate issued again) and refuse a run "
               "that differs; seconds to minutes, no expert call; false only for a run made by another npp_ros whose "
               "policy acts otherwise"),
    Changeable("monitor_window", AUTO, "a run on a set of robots: seconds of the robot's latest motion the set's "
               f"parameters are fitted to, every {EVERY_S:g} s in a worker process (finds a gear of x0.6 or a "
               f"delay of 2 the transition check misses); {IN_A_ROW} windows in a row with no robot of the set "
               "inside the fit's 95% intervals are a model mismatch (on_model_mismatch); 0 = off; -1, the default: "
               f"{WINDOW_S:g} s where the set's robots read exact states, off where the set declares noise on the "
               "reads (that noise biases the fit while a policy holds the robot still, and robots of the set are "
               "then found outside)", -1.0, 60.0),
    Changeable("identified_robot", "", "this robot identified from its own motion (the JSON npp-identify --out "
               "writes of a recording of it): configure simulates the certified policy at the identified robot and "
               "refuses when the lower bound on its success there is below robot_min_success; empty = no check at "
               "this robot (the set's certificate is an average over the set)"),
    Changeable("robot_check_starts", 60, "s0 ~ rho per point of the identified region in that check", 1, 100000),
    Changeable("robot_min_success", 0.0, "the success the policy must have at the identified robot (a lower "
               "confidence bound); 0 = the certificate's p", 0.0, 1.0),
    Changeable("robot_check_delta", 0.05, "the check's level: every point's bound holds at once with probability "
               ">= 1 - this", 1e-6, 0.5),
    Changeable("override_gate", False, "deploy even when the gate refuses (each reason logged as an error and kept on "
               "/diagnostics); never for a run file whose data fail their checksums"),
    Changeable("joint_states_topic", JOINT_STATES, "the robot's sensor_msgs/JointState topic"),
    Changeable("target_topic", TARGET_TOPIC, "a task whose state holds a target (state.target): where the point to "
               "reach comes (geometry_msgs/PointStamped); nothing is commanded before the first, and a point outside "
               "the box rho draws targets from is refused, the target before it kept; unused for other tasks"),
    Changeable("target_frame", "world", "the frame a target must be given in, the model's world frame: a point in "
               "another frame is refused (no transform is looked up)"),
    Changeable("command_topic", FORWARD_COMMANDS, "the controller's std_msgs/Float64MultiArray command topic"),
    Changeable("command_joints", "", "the controller's joints in command order, comma-separated; empty = the task's "
               "actuated joints in the task's order"),
    Changeable("command_interface", "effort", "what the controller commands; the safe command is zero effort, or "
               "the present position held", choices=COMMAND_INTERFACES),
    Changeable("safe_effort", "zero", "an effort interface's safe command: zero (a robot whose controller holds it "
               "against gravity), or gravity (the torques that hold the measured pose under the model's gravity: a "
               "robot that falls at zero effort, as npp-robot running an arm does)", choices=SAFE_EFFORTS),
    Changeable("effort_limit", 0.0, "largest |command| on top of the model's actuator limits; 0 = the model's only",
               0.0),
    Changeable("state_timeout", 0.1, "seconds without a fresh answer to a usable joint state before the safe "
               "command is sent; a multiple of the robot's state period above its worst jitter (see "
               "'state period' on /diagnostics)", 1e-3),
    Changeable("coverage_radius", 0.0, "distance from the policy's data beyond which a state is reported as outside "
               "the certificate's coverage; 0 = the farthest a checked s0 of the run lay from it", 0.0),
    Changeable("stop_outside_coverage", False, "deactivate at the first state outside the coverage (or non-finite)"),
    Changeable("on_model_mismatch", "stop", "a run certified on a set of robots: what to do when the robot's "
               "transitions leave what the set explains (the model monitor): stop (deactivate, the safe command "
               "sent; the default: nothing was certified for such a robot), or warn on /diagnostics and go on "
               "commanding; either way WARN stays until clear_model_mismatch", choices=MISMATCH_ACTIONS),
)  # fmt: skip


@dataclass(frozen=True)
class DeploySettings:
    """npp-deploy's parameters; the gate's limits are checked by Acceptance, the joints once the task is known."""

    run_dir: str
    robot_model_fingerprint: str
    robot_description_topic: str
    description_timeout: float
    max_epsilon: float
    min_p: float
    max_delta: float
    trusted_keys: str
    allow_unsealed: bool
    rederive: bool
    monitor_window: float
    identified_robot: str
    robot_check_starts: int
    robot_min_success: float
    robot_check_delta: float
    override_gate: bool
    joint_states_topic: str
    target_topic: str
    target_frame: str
    command_topic: str
    command_joints: str
    command_interface: str
    safe_effort: str
    effort_limit: float
    state_timeout: float
    coverage_radius: float
    stop_outside_coverage: bool
    on_model_mismatch: str

    def __post_init__(self) -> None:
        # The limits are checked now; the key files are read at configure, where a bad one is configure's refusal
        # with its reason (at start it would stop the node, and npp-deploy-ctl could only say it is not found).
        Acceptance(self.max_epsilon, self.min_p, self.max_delta)
        topics = (self.joint_states_topic, self.command_topic, self.robot_description_topic, self.target_topic)
        if not all(t.strip() for t in topics):
            raise ValueError(
                "joint_states_topic, command_topic, robot_description_topic and target_topic must name topics"
            )
        if not self.target_frame.strip():
            raise ValueError("target_frame must name a frame (the model's world frame: world)")

    def acceptance(self, model_fingerprint: str | None = None) -> Acceptance:
        fingerprint = self.robot_model_fingerprint if model_fingerprint is None else model_fingerprint
        keys = load_public_keys(parse_names(self.trusted_keys))  # a SigningError (a ValueError) names the file
        return Acceptance(
            self.max_epsilon, self.min_p, self.max_delta, fingerprint, self.override_gate, keys,
            allow_unsealed=self.allow_unsealed, rederive=self.rederive,
        )  # fmt: skip


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


@dataclass(frozen=True)
class Description:
    """The robot's latest MJCF on robot_description_topic: its text, who published it and when."""

    text: str
    publishers: str
    at: str


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
        self.monitor: ModelMonitor | None = None  # a run certified on a set of robots: its transitions are watched
        self.robot_check = ""  # the check at the identified robot, in words ("" on the exact model)
        # The window identification (npp_ros.identification.window): its motion, its worker and the fit under way.
        self.window: MotionWindow | None = None
        self._judges: ProcessPoolExecutor | None = None
        self._judging: Future[WindowVerdict] | None = None
        self._window_said = ""
        self._monitor_arrival = -1  # the arrival count of the last state the monitor took
        self.description: Description | None = None
        self._raw: np.ndarray | None = None  # the last joint state taken, [positions, velocities]
        self.hold: Callable[[np.ndarray], np.ndarray] | None = None  # safe_effort gravity: the torques that hold
        self._last_answered: tuple[int, int] | None = None  # the stamp of the last state answered
        self._command = Float64MultiArray()
        self.stopped_by = ""  # the signal that stops the process (SIGINT, SIGTERM)
        self._warn = ThrottledWarnings(self)
        self._state_sub = None
        self._target_sub = None
        self._target_moved = False  # a new target since the model monitor's last state: its chain starts again
        self.command_pub: Publisher | None = None  # created at configure, on the configured topic
        self.create_service(Trigger, STOP_SERVICE, self.on_stop)
        self.create_service(Trigger, CLEAR_MISMATCH_SERVICE, self.on_clear_mismatch)
        # From the start, not at configure: the description is latched, and configure must find it there.
        self._description_sub = self.create_subscription(
            String, self.settings.robot_description_topic, self.on_description, LATCHED_QOS
        )
        self._description_wait = ""  # what configure's last wait for the description saw, for its refusal
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
        topic = self.settings.robot_description_topic
        self.description = Description(msg.data, publishers_of(self, topic), wall_time())
        self.get_logger().info(
            f"robot description received on {topic} ({len(msg.data)} characters, from {self.description.publishers})"
        )
        deployment = self.deployment
        if deployment is None or self.state.fingerprint_source != self._described_source():
            return
        try:
            fingerprint = mjcf_fingerprint(deployment.plant, msg.data)
        except DescriptionError as exc:
            fingerprint = f"none ({exc})"
        if fingerprint == self.state.fingerprint:
            return
        problem = (
            f"the robot published a different model on {topic} (fingerprint {fingerprint[:12]}...) than the one "
            f"configure checked ({self.state.fingerprint[:12]}...)"
        )
        self.state.model_changed(problem)  # ERROR until configure checks the model again
        if self.active:
            self.get_logger().error(f"{problem}: deactivating")
            self.state.stop_requested(MODEL_CHANGED)
            self.trigger_deactivate()
        else:
            self.get_logger().error(f"{problem}: configure again (cleanup, configure) before activating")
            self.diagnostics.publish()

    def _await_description(self, settings: DeploySettings) -> None:
        """Wait up to description_timeout for the robot's latched description when configure needs it.

        A node started just before configure may not have discovered the robot yet (0.3-0.9 s here). This runs
        in the executor's one thread, so the description cannot come through on_description meanwhile: the
        wait is on the subscription itself (a wait set of its own, looked at again every WAIT_SLICE_S), and a
        description that comes is taken from it and handed to on_description, as the executor would.
        """
        self._description_wait = ""
        if self.description is not None or settings.robot_model_fingerprint.strip():
            return
        topic, subscription = settings.robot_description_topic, self._description_sub
        started = time.monotonic()
        seen = 0
        wait_set = _rclpy.WaitSet(1, 0, 0, 0, 0, 0, self.context.handle)
        waited = False
        while True:
            seen = max(seen, self.count_publishers(topic))
            with subscription.handle:
                taken = subscription.handle.take_message(subscription.msg_type, subscription.raw)
            if taken is not None:
                self.on_description(taken[0])
                if waited:  # one already there (not yet handed over by the executor) is not news
                    self.get_logger().info(
                        f"configure waited {time.monotonic() - started:.2f} s for the robot's description"
                    )
                return
            left = started + settings.description_timeout - time.monotonic()
            if left <= 0 or stop_requested() or not rclpy.ok():
                break
            with subscription.handle:
                wait_set.clear_entities()
                wait_set.add_subscription(subscription.handle)
                wait_set.wait(int(min(left, WAIT_SLICE_S) * 1e9))
            waited = True
        publishers = "no publisher" if seen == 0 else f"{seen} publisher{'s' if seen > 1 else ''}"
        self._description_wait = (
            f"waited {time.monotonic() - started:.1f} s (description_timeout {settings.description_timeout:g}); "
            f"{publishers} of it seen"
        )

    def _described_source(self) -> str:
        return f"the MJCF the robot published on {self.settings.robot_description_topic}"

    def _robot_fingerprint(self, settings: DeploySettings) -> tuple[str, str]:
        """The fingerprint the gate checks and where it came from: the operator's parameter if given, else the
        robot's own description; ("", why) when there is neither (the gate then refuses)."""
        topic, description = settings.robot_description_topic, self.description
        described = ""
        if description is not None:
            try:
                described = described_fingerprint(settings.run_dir, description.text) or ""
            except DescriptionError as exc:
                if not settings.robot_model_fingerprint.strip():
                    raise DescriptionError(f"the robot's description on {topic}: {exc}") from None
                self.get_logger().warning(f"the robot's description on {topic} is not used: {exc}")
        explicit = settings.robot_model_fingerprint.strip()
        if explicit:
            if described and described != explicit:
                self.get_logger().warning(
                    f"robot_model_fingerprint {explicit[:12]}... overrides the fingerprint of the robot's own "
                    f"description on {topic} ({described[:12]}...)"
                )
            return explicit, "the robot_model_fingerprint parameter"
        if description is None:
            waited = f" ({self._description_wait})" if self._description_wait else ""
            return "", (
                f"nowhere: no robot description was received on {topic}{waited} and robot_model_fingerprint is empty"
            )
        return described, self._described_source()

    # ---------------------------------------------------------------- lifecycle
    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        """Parameters take effect at configure, so they may change only while unconfigured."""
        if self.lifecycle == "unconfigured":
            return SetParametersResult(successful=True)
        names = ", ".join(p.name for p in params)
        return SetParametersResult(successful=False, reason=f"{names}: read at configure; clean up first")

    def _progress(self, what: str) -> Callable[[int, int], None]:
        """A ``progress(done, total)`` that logs ``what`` (formatted with done and total) every few seconds and at the
        end: a configure that takes a minute says why."""
        last = [time.monotonic()]

        def report(done: int, total: int) -> None:
            if done == total or time.monotonic() - last[0] >= 5.0:
                last[0] = time.monotonic()
                self.get_logger().info(what.format(done=done, total=total))

        return report

    def _check_robot(self, settings: DeploySettings, deployment: Deployment, robots: UncertaintySet) -> str:
        """The check before the robot moves, at the robot identified_robot names (npp_ros.identification.identified):
        its verdict in words, or a ValueError with the reason it must not move. Without one, on a set: a warning
        that nothing is known of this robot beyond the set's average."""
        if not settings.identified_robot.strip():
            if robots.empty:
                return ""
            self.get_logger().warning(
                "the certificate on the set of robots is an average over the set and promises nothing for this one "
                "robot: give identified_robot (npp-identify --out of its recorded motion) to check the policy at it"
            )
            return "not checked at this robot (no identified_robot)"
        run = read_run(deployment.run_file)
        report = self._progress("robot check: point {done} of {total} of the identified region simulated")
        move, words = check_identified_robot(
            run, Path(settings.identified_robot), n=settings.robot_check_starts,
            p=settings.robot_min_success or None, delta_g=settings.robot_check_delta, progress=report,
        )  # fmt: skip
        verdict = move.summary().splitlines()[0]
        if not move.accepted:
            raise ValueError(f"the robot identified from its own motion ({words}): {verdict}; not commanded")
        self.get_logger().info(f"robot check ({words}): {verdict}")
        return verdict

    def _read_settings(self) -> DeploySettings:
        return DeploySettings(**{param.name: self.get_parameter(param.name).value for param in PARAMETERS})

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        # Three steps, each refusing with its reason; a ValueError is a refusal only where the settings are
        # checked: from the gate (which refuses with GateRefusal) it is unexpected, and named by its type.
        try:
            self.settings = settings = self._read_settings()
            self._await_description(settings)
            fingerprint, source = self._robot_fingerprint(settings)
            acceptance = settings.acceptance(fingerprint)
            if self.description is not None and source == self._described_source():  # a run on a set of robots
                acceptance = replace(acceptance, robot_description=self.description.text)  # compares the MJCF itself
        except ValueError as exc:
            return self._refuse("configure", str(exc))
        except Exception as exc:  # whatever it is, configure fails with its reason, never silently
            return self._refuse("configure", f"{type(exc).__name__}: {exc}")
        try:
            deployment = load_deployment(
                settings.run_dir, acceptance, self._progress("gate: deriving the run again, episode {done} of {total}")
            )
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
            robot_check = self._check_robot(settings, deployment, robots)
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
        self.deployment, self.layout, self.coverage, self.monitor = deployment, layout, coverage, monitor
        self.hold = hold
        seconds = window_seconds(settings.monitor_window, robots)
        late_after = LATE_SHARE * plant.dt  # a command later than this missed the robot's step it answers
        self.window = MotionWindow(seconds, late_after=late_after) if monitor is not None and seconds > 0 else None
        if self.window is not None:  # the fits' worker started and loaded now, not at the first window
            meta = deployment.metadata
            self._window_judges().submit(prepare, str(meta.task), int(meta.seed))
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
        self._monitor_arrival = -1
        if self.monitor is not None:
            self.monitor.reset()
        if self.window is not None:
            self.window.restart()
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
        self.stop_commanding("shutting down")
        self._release()
        return self._became("finalized")

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.stop_commanding("error")
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
        self.deployment = self.layout = self.limits = self.coverage = self.monitor = None
        self.window, self._judging, self._window_said = None, None, ""
        if self._judges is not None:
            self._judges.shutdown(wait=False, cancel_futures=True)
            self._judges = None
        self.state.released()
        self._raw, self._last_answered = None, None

    def stop_commanding(self, why: str) -> None:
        """Stop commanding; the safe command goes out in the watchdog's step, so no fresh command follows it."""
        was_active = self.state.stop_commanding()
        sent = self.watchdog.disarm(self.send_safe_command if was_active else None)
        if was_active:
            self.state.stopped(why, sent)
            self.get_logger().info(f"{why}: {sent}; commanding stopped")

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
        self.state.note("stop requested")
        self.state.stop_requested("stop requested")
        self.trigger_deactivate()
        response.success = self.lifecycle == "inactive"
        response.message = "stopped: safe command sent, inactive" if response.success else "could not deactivate"
        return response

    def on_clear_mismatch(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """The operator has seen the model monitor's finding: /diagnostics is OK again until the next one."""
        cleared = self.state.mismatch_cleared()
        if self.monitor is not None:
            self.monitor.reset()  # a new window: the finding cleared is not found again from the same transitions
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
        self._watch_model(raw, action, outcome == "resumed", stamp)

    def _watch_model(self, raw: np.ndarray, action: np.ndarray, resumed: bool, stamp: float) -> None:
        """After the command went out: check the transition into this state against the certified set, and the
        latest seconds of motion by identification (in a worker: a fit never holds up a command)."""
        monitor = self.monitor
        if monitor is None:
            return
        arrived = self.state.arrived_since_activation
        if resumed or arrived != self._monitor_arrival + 1 or self._target_moved:
            # A state skipped (overtaken, refused), a stale spell or a new target: no one-step transition
            monitor.restart()
        if self.window is not None and (resumed or self._target_moved):
            # After a stale spell (the safe command went out, unrecorded) or a new target the window starts afresh;
            # a skipped state alone does not: the fit takes only rows one control step apart by their stamps.
            self.window.restart()
        self._monitor_arrival, self._target_moved = arrived, False
        self._watch_window(raw, action, stamp)
        was_outside = monitor.outside
        monitor.observe(raw, action)
        if not monitor.outside:
            return
        problem = f"the robot's transitions leave the certified set of robots: {monitor.summary()}"
        self._mismatch(problem, newly=self.state.mismatch_found(problem) and not was_outside)

    def _watch_window(self, raw: np.ndarray, action: np.ndarray, stamp: float) -> None:
        """Feed the motion window; take a finished fit's verdict; hand the next due window to the worker."""
        window, deployment = self.window, self.deployment
        if window is None or deployment is None:
            return
        window.add(stamp, raw, action, time.time())  # sent just now: the wall clock the robot's stamps follow
        judging = self._judging
        if judging is not None and judging.done():
            self._judging = None
            try:
                verdict = judging.result()
            except Exception as exc:  # a worker that died or a fit that failed: said, and the window goes on
                self._warn("window identification", f"a window's identification failed: {type(exc).__name__}: {exc}")
            else:
                late = f"; late commands left out: {window.late}" if window.late else ""
                self._window_said = f"last window (ending {verdict.end:.2f} s{late}): {verdict.said}"
                if window.found(verdict):
                    problem = (
                        f"the robot identified from its last {window.in_a_row} windows of {window.seconds:g} s of "
                        f"motion lies outside the certified set of robots: {verdict.said}"
                    )
                    self._mismatch(problem, newly=self.state.mismatch_found(problem))
                    return
        due = window.due() if self._judging is None else None
        if due is None:
            return
        meta = deployment.metadata
        self._judging = self._window_judges().submit(judge, str(meta.task), int(meta.seed), str(meta.uncertainty), *due)

    def _window_judges(self) -> ProcessPoolExecutor:
        """The window fits' worker: spawned, not forked, a process of its own apart from the ROS context."""
        if self._judges is None:
            self._judges = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"))
        return self._judges

    def _mismatch(self, problem: str, *, newly: bool) -> None:
        """The robot was found outside the certified set (by either monitor): stop or warn, as the operator chose."""
        if self.settings.on_model_mismatch == "stop" and self.active:
            self.get_logger().error(f"{problem}; on_model_mismatch is stop: deactivating")
            self.state.stop_requested(MODEL_MISMATCH)
            self.trigger_deactivate()
            return
        self._warn("model mismatch", problem)
        if newly:  # said on /diagnostics when found, not at its next status a second later
            self.diagnostics.publish()

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
            self.state.stop_requested(STOPPED_OUTSIDE)
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
        self._target_moved = True
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
        deployment, monitor = self.deployment, self.monitor
        if deployment is not None:
            values["policy"] = deployment.describe()
            values["run provenance"] = f"{deployment.seal.describe()}; {deployment.signed}; {deployment.derived}"
            if self.robot_check:
                values["robot check"] = self.robot_check
            values["robot model fingerprint"] = f"{self.state.fingerprint[:12]}... from {self.state.fingerprint_source}"
            if monitor is not None:
                values["model monitor"] = monitor.summary()
            if self._window_said:
                values["window identification"] = self._window_said
            if deployment.overridden:
                values["gate overridden"] = "; ".join(deployment.overridden)
        description = self.description
        values["robot description"] = (
            f"{len(description.text)} characters from {description.publishers}, received {description.at}"
            if description is not None
            else f"none received on {self.settings.robot_description_topic}"
        )
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
            self.stop_commanding(self.stopped_by or "exiting")
        self.watchdog.close()
        if self._judges is not None:
            self._judges.shutdown(wait=False, cancel_futures=True)
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
            node.stopped_by = node.stopped_by or signal.Signals(signum).name
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
