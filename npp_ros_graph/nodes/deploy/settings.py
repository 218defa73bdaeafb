"""npp-deploy's parameters: their declarations (name, default, help, range), read at configure while unconfigured,
and the settings they make, checked as a whole."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

from npp_ros.deployment.commands import COMMAND_INTERFACES, SAFE_EFFORTS
from npp_ros.deployment.gate import Acceptance
from npp_ros.deployment.joints import parse_names
from npp_ros.deployment.signing import load_public_keys
from npp_ros.identification.window import AUTO, EVERY_S, IN_A_ROW, WINDOW_S
from npp_ros_graph.transport.parameters import Param
from npp_ros_graph.transport.topics import FORWARD_COMMANDS, JOINT_STATES

ROBOT_DESCRIPTION = "/robot_description"  # robot_state_publisher's topic (std_msgs/String, transient local)
TARGET_TOPIC = "~/target"  # a task whose state holds a target: the point to reach (geometry_msgs/PointStamped)
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
