"""npp-robot: a MuJoCo plant that behaves as a ros2_control robot does, to test npp-deploy against.

Real time (default): a thread steps the task's plant once per control period (its dt) on the wall
clock, or every dt / ``time_scale`` wall seconds (faster than real time for a learning run), and
publishes /joint_states after every step, as joint_state_broadcaster does; the command
applied is the latest std_msgs/Float64MultiArray from the controller's topic, held until the next
arrives (a zero-order hold, no lockstep: a late command leaves the previous one in force, as
forward_command_controller does). Before the first command it applies zero, or, with
``start_on_command:=true``, holds the plant at s0 and starts its clock with the first command.

Lockstep (``lockstep:=true``, for exact comparisons): once a controller publishes on the command
topic, it publishes a state, then steps only when a command answers it, and publishes the next; a
state left unanswered for ``resend_after`` seconds is published again with the same stamp (so a
controller activated later picks it up).

Joint states: every joint of the model but a target's, position = qpos, velocity = qvel, effort = the control
applied to its actuator (0 for a joint without one), stamped with the robot's clock. A task whose state holds a
target (a task file's ``state.target``) simulates the target as a body of the model that nothing moves, but a
real arm measures no such joints: they are left out, as a robot's joint_state_broadcaster would, and npp-deploy
reads the target from a topic of its own. Real time: the
clock starts at the wall clock's time when the robot is built, each stepped state is stamped dt after
the state before it (so its stamps follow the steps taken: with ``time_scale`` 1 and no overrun they
stay with the wall clock; a skipped period, an overrun, leaves them behind it by that period), and
while the plant is held (start_on_command, or after a reset until the next command) the clock runs
at ``time_scale`` times the wall clock, the first step after a hold stamped dt after the command
came. Lockstep: the simulated time, dt per step from 0, and one dt per reset. Stamps never go back.

Episodes (a learning run): the reset service (``reset_service``, npp_interfaces/srv/ResetRobot,
docs/reference/robot-reset.md) puts the plant at the requested state (qpos then qvel; none: its own
start, ``initial_state`` or the task's s0 for the seed and ``episode``), empties its action delay,
forgets the held command and applies zero; in real time it then holds the plant there, publishing it
every HOLD_REPUBLISH_S, until the first command after the reset, which it applies at once; in lockstep
it publishes the start and steps on commands. It answers with the start as it measures it (its state
noise included, as in its joint states) and that state's stamp. A state of the wrong length or with
non-finite entries is refused with the reason, changing nothing. The requested state is the whole stored
state: for a task whose state holds a target, its target entries put the simulated target there (a body
nothing moves, which changes no motion of the robot and is in no joint state), and the answer holds them.

Its model: the MJCF it runs, published once on /robot_description (std_msgs/String, transient local
and reliable, as robot_state_publisher publishes a URDF), from which npp-deploy computes the model
fingerprint its gate checks.

Another robot than the task's model, for tests and for trying a deployment on a set of robots: ``robot`` (a
robot record, npp_ros.tasks.uncertainty) and the per-parameter scales (``mass_scale``, ``gear_scale``, ...,
each multiplying every element of its kind, on top of the record) change its model, and its description
with it; ``action_delay`` holds each command that many control steps, ``state_noise`` adds noise to the
joint states it publishes. ``publish_description:=nominal`` publishes the task's own MJCF whatever it runs:
a robot that changed without saying so. The robot it runs is said only on /robot_description (its model) and
in its start log line: the node serves none of its parameters (no parameter services) and announces none on
/parameter_events, where rclpy would publish every declared parameter with its value.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import rclpy
from builtin_interfaces.msg import Time
from npp_interfaces.srv import ResetRobot
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String

from npp_ros.deployment.joints import JointLayout, parse_names, parse_vector
from npp_ros.deployment.robot_model import mjcf_fingerprint, model_mjcf
from npp_ros.deployment.robot_set import robot_mjcf
from npp_ros.policy.vectors import finite_vector
from npp_ros.tasks.registry import Plant, get_task
from npp_ros.tasks.uncertainty import PARAMETERS as UNCERTAIN
from npp_ros.tasks.uncertainty import ModelParameters, Robot, RobotEffects, model_elements
from npp_ros_graph.runtime.diagnostics import DiagnosticsReporter, Health
from npp_ros_graph.runtime.node import ThrottledWarnings, run_node
from npp_ros_graph.transport.convert import float64_array, stamp
from npp_ros_graph.transport.parameters import Param, StartupError, declare_settings, parameter_help
from npp_ros_graph.transport.topics import CONTROL_QOS, FORWARD_COMMANDS, JOINT_STATES, LATCHED_QOS, SERVICE_QOS

HOLD_REPUBLISH_S = 0.05  # holding (start_on_command, after a reset): how often the start goes out again, wall seconds

PARAMETERS = (
    Param("task", "lqr_2_1", "the task whose plant this robot is: a registered task (plug-ins too) or a task file "
          "(path ending in .toml)"),
    Param("seed", 0, "task seed (the plant's model depends on it)", 0, 2**32 - 1),
    Param("initial_state", "", "the state to start in, comma-separated qpos then qvel; empty = s0 ~ rho of "
          "`episode`"),
    Param("episode", 0, "which s0 ~ rho to start in when initial_state is empty (the run's stream for this seed)", 0),
    Param("lockstep", False, "step only when a command answers the latest state (tests); else real time"),
    Param("resend_after", 0.5, "lockstep: seconds before an unanswered state is published again", 1e-3),
    Param("start_on_command", False, "real time: hold the plant at s0, publishing it every 50 ms, until the first "
          "command; then the clock starts (an episode that starts exactly at s0, as npp-trial needs)"),
    Param("time_scale", 1.0, "real time: how many times faster than the wall clock the robot runs (one step every "
          "dt / time_scale wall seconds; its joint states are stamped with its own clock, dt per step)", 0.01, 1000.0),
    Param("reset_service", "~/reset", "the reset service (npp_interfaces/srv/ResetRobot): to a given state or its own "
          "start, then held until the next command"),
    Param("joint_states_topic", JOINT_STATES, "where the joint states go"),
    Param("command_topic", FORWARD_COMMANDS, "the controller's command topic"),
    Param("robot_description_topic", "/robot_description", "where its model goes, as MJCF text (latched)"),
    Param("command_joints", "", "the controller's joints in command order, comma-separated; empty = the model's "
          "actuated joints"),
    Param("robot", "", "the robot it is, as a robot record (JSON, npp_ros.tasks.uncertainty.Robot.record: scales "
          "per element, action delay, state noise); empty = the task's model"),
    *(Param(f"{name}_scale", 1.0, f"multiplies every {kind}'s {name} (on top of `robot`): {what}", 1e-6)
      for name, (kind, what) in UNCERTAIN.items()),
    Param("action_delay", 0, "control steps each command is held back before the actuator applies it (on top of "
          "`robot`'s)", 0, 50),
    Param("state_noise", 0.0, "standard deviation of the noise added to each published position and velocity "
          "(instead of `robot`'s when > 0)", 0.0),
    Param("publish_description", "robot", "what goes on robot_description_topic: the MJCF of the model it runs "
          "(robot), or the task's own whatever it runs (nominal: a changed robot that does not say so)",
          choices=("robot", "nominal")),
)  # fmt: skip


@dataclass(frozen=True)
class RobotSettings:
    """npp-robot's parameters; the task's registry checks the name."""

    task: str
    seed: int
    initial_state: str
    episode: int
    lockstep: bool
    resend_after: float
    start_on_command: bool
    time_scale: float
    reset_service: str
    joint_states_topic: str
    command_topic: str
    robot_description_topic: str
    command_joints: str
    robot: str
    mass_scale: float
    gear_scale: float
    damping_scale: float
    frictionloss_scale: float
    armature_scale: float
    action_delay: int
    state_noise: float
    publish_description: str

    def __post_init__(self) -> None:
        task = get_task(self.task)
        if self.initial_state.strip():
            parse_vector(self.initial_state, task.state_dim, "initial_state")
        if self.robot.strip():
            Robot.from_record(self.robot)  # a ValueError saying what is wrong with it

    def robot_of(self, plant: Plant) -> Robot:
        """The robot it runs: the record's, with every per-parameter scale multiplied in."""
        given = Robot.from_record(self.robot) if self.robot.strip() else Robot()
        factors = {(p, n): f for p, n, f in given.scales}
        elements = model_elements(plant.physics.model)  # type: ignore[attr-defined]
        for name, (kind, _) in UNCERTAIN.items():
            scale = float(getattr(self, f"{name}_scale"))
            if scale != 1.0:
                for element in elements[kind]:
                    factors[(name, element)] = factors.get((name, element), 1.0) * scale
        noise = self.state_noise if self.state_noise > 0 else given.state_noise
        scales = tuple((p, n, f) for (p, n), f in factors.items())
        return Robot(scales, given.action_delay + self.action_delay, noise, given.noise_seed)


class RobotClock:
    """The robot's time, in nanoseconds, that its joint states are stamped with: dt per step taken, and while the
    plant is held, the wall time passed scaled by time_scale. Its stamps only go forward: a controller told a
    state by its stamp (npp-deploy answers a stamp once) must never see an old one again."""

    def __init__(self, dt: float, time_scale: float, start_ns: int) -> None:
        self.dt, self.time_scale = dt, time_scale
        self.last_ns = start_ns  # the stamp of the latest state
        self._anchor_ns, self._steps = start_ns, 0  # stepped stamps are the anchor plus a whole number of dt
        self._wall = time.monotonic()  # when the latest stamp was taken

    def _anchor(self, ns: int) -> int:
        self.last_ns = self._anchor_ns = max(ns, self.last_ns + 1)
        self._steps, self._wall = 0, time.monotonic()
        return self.last_ns

    def stepped(self) -> int:
        """The stamp of the state one step after the latest: exactly dt later (to the nanosecond)."""
        self._steps += 1
        self.last_ns = self._anchor_ns + round(self._steps * self.dt * 1e9)
        self._wall = time.monotonic()
        return self.last_ns

    def held(self) -> int:
        """The robot's time now while it holds the plant: the wall time since the latest stamp, times time_scale."""
        return self._anchor(self.last_ns + round((time.monotonic() - self._wall) * self.time_scale * 1e9))

    def skipped(self) -> int:
        """One period past the latest stamp (lockstep's reset: its start is a new state, with a stamp of its own)."""
        return self._anchor(self.last_ns + round(self.dt * 1e9))


USAGE = f"""npp-robot: a task's MuJoCo plant as a ros2_control robot (node "npp_robot").

publishes   joint_states_topic (sensor_msgs/JointState) every control period (real time), or after each
            answered command (lockstep)
subscribes  command_topic (std_msgs/Float64MultiArray, one entry per command joint; held until the next)
            a command of the wrong length or with non-finite entries is ignored with a warning
publishes   robot_description_topic (std_msgs/String, transient local: the MJCF of its model, once)
serves      reset_service (npp_interfaces/srv/ResetRobot): state = qpos then qvel, or empty for its own start
            (initial_state, else s0 of `episode`); answers the start as measured (with its state noise) and the
            stamp of that joint state; real time: holds the start until the next command, applied at once;
            a task whose state holds a target (state.target): the target's entries put the simulated target,
            which moves nothing and is not in joint_states_topic (a real arm measures no target)
publishes   /diagnostics (steps, overruns, resets and refused resets among its values)

Stamps follow the robot's clock: real time, the wall clock's time at start plus dt per step taken (with
time_scale 1 and no overrun, close to the wall clock), running at time_scale x the wall clock while it holds
a start; lockstep, dt per step from 0. They never go back, across resets too. The robot it runs is said
only on robot_description_topic and in its start log line: no parameter services, no /parameter_events.

npp-deploy computes the robot's model fingerprint from its description; it is logged at start too (for
npp-deploy's robot_model_fingerprint, where a description cannot be used).

{parameter_help(PARAMETERS)}
"""


class _Unannounced:
    """Stands in for rclpy's /parameter_events publisher: a declared parameter goes out there with its value,
    and the robot's (its record, its scales, its delay and noise) are what a run on it must not be told."""

    def publish(self, msg: object) -> None:
        pass


class RobotNode(Node):
    def __init__(self) -> None:
        super().__init__("npp_robot", start_parameter_services=False)  # its parameters name the robot it runs
        self.destroy_publisher(self._parameter_event_publisher)
        self._parameter_event_publisher = _Unannounced()  # type: ignore[assignment]
        self.settings = settings = declare_settings(self, PARAMETERS, RobotSettings)
        self.plant: Plant | None = None
        self.layout: JointLayout | None = None
        self._lock = threading.Lock()  # the plant: stepped by the clock thread or the command callback
        self._command: np.ndarray | None = None  # the latest command, in the task's actuator order
        self._fresh = False  # a command arrived since the last step
        self._applied = np.zeros(0)
        self.robot = Robot()
        self._effects: RobotEffects | None = None
        self._start = np.zeros(0)  # its own start: initial_state, else s0 of `episode`
        self.clock = RobotClock(1.0, 1.0, 0)  # replaced at the build, with the plant's dt
        self._holding = False  # real time: the plant stays at its start until a command comes
        self._repeat_start = False  # holding after a reset: the start is sent again as measured (same stamp)
        self._commanded = threading.Event()  # a command arrived (or the node stops): wakes a hold at once
        self.steps = 0
        self.held_steps = 0  # real time: steps taken with a command that was already applied before
        self.ignored_commands = 0
        self.overruns = 0
        self.resets = 0
        self.refused_resets = 0
        self._state_msg = JointState()
        self._last_sent = 0.0
        self._warn = ThrottledWarnings(self)
        self._stopping = threading.Event()
        self._clock_thread: threading.Thread | None = None
        self.state_pub = self.create_publisher(JointState, settings.joint_states_topic, CONTROL_QOS)
        self.description_pub = self.create_publisher(String, settings.robot_description_topic, LATCHED_QOS)
        self._command_sub = self.create_subscription(
            Float64MultiArray, settings.command_topic, self.on_command, CONTROL_QOS
        )
        self.diagnostics = DiagnosticsReporter(self, self.health)
        self._build_timer = self.create_timer(0.0, self._build)  # MuJoCo loads after init, not inside it

    def _build(self) -> None:
        self._build_timer.cancel()
        self.destroy_timer(self._build_timer)
        settings = self.settings
        task = get_task(settings.task)
        try:
            plant = task.make_plant(settings.seed)
            layout = JointLayout.of_plant(plant, parse_names(settings.command_joints))
            nominal_mjcf = model_mjcf(plant)
            robot = settings.robot_of(plant)
            # Written from the nominal model, before the robot is applied to it (robot_mjcf scales its values)
            mjcf = nominal_mjcf if settings.publish_description == "nominal" else robot_mjcf(plant, robot)
            ModelParameters(plant.physics.model).apply(robot)  # its own model: nothing else holds it
        except Exception as exc:  # run_node turns this into a clean exit with the reason
            raise StartupError(f"cannot build the robot {settings.task} seed {settings.seed}: {exc}") from exc
        if settings.initial_state.strip():
            s0 = parse_vector(settings.initial_state, task.state_dim, "initial_state")
        else:
            s0 = task.initial_state(settings.seed, settings.episode)
        plant.reset(s0)
        self._start = s0
        model = plant.physics.model
        self._qpos = np.array([model.jnt_qposadr[model.joint(n).id] for n in plant.joint_names], dtype=np.intp)
        self._qvel = np.array([model.jnt_dofadr[model.joint(n).id] for n in plant.joint_names], dtype=np.intp)
        # What a joint state reports: the robot's own joints, never a target's (which the reset puts, and no robot
        # measures); the whole state is still what a reset answers.
        self._measured = np.array([plant.joint_names.index(n) for n in layout.measured], dtype=np.intp)
        self._effort_of = np.array(
            [plant.actuated_joint_names.index(n) if n in plant.actuated_joint_names else -1 for n in layout.measured]
        )
        self._state_msg = JointState(name=list(layout.measured))
        self._applied = np.zeros(plant.action_dim)
        self.plant, self.layout, self.robot = plant, layout, robot
        self._effects = RobotEffects(robot, plant.action_dim)
        if settings.publish_description == "nominal" and mjcf is not None:
            self.description_pub.publish(String(data=mjcf))
            described = f"the task's own MJCF on {settings.robot_description_topic}, not the model it runs"
        elif mjcf is None:
            described = f"no description on {settings.robot_description_topic} (its plant names no MJCF)"
        elif mjcf_fingerprint(plant, mjcf) != plant.model_sha256():  # published, it must be the model it runs
            described = f"no description on {settings.robot_description_topic} (its MJCF compiles to another model)"
        else:
            self.description_pub.publish(String(data=mjcf))
            described = f"its MJCF on {settings.robot_description_topic}"
        mode = "lockstep" if settings.lockstep else f"real time, every {plant.dt * 1e3:g} ms"
        target = [] if layout.target is None else list(layout.target.joints)
        unmeasured = f" ({target} the target's: not in its joint states)" if target else ""
        if not settings.lockstep and settings.time_scale != 1.0:
            mode += f" of robot time, {settings.time_scale:g}x the wall clock"
        self.get_logger().info(
            f"robot {settings.task} seed {settings.seed} ready ({mode}), {robot.describe()}: joints "
            f"{plant.joint_names}{unmeasured}, commands for "
            f"{list(layout.command_joints)} on {settings.command_topic}, s0 {np.round(s0, 6).tolist()}; "
            f"model fingerprint {plant.model_sha256()}, {described}"
        )
        if settings.lockstep:
            self.clock = RobotClock(plant.dt, 1.0, 0)
            self._started = False  # the first state waits for a controller, whose answer it could otherwise miss
            self.create_timer(min(settings.resend_after, 0.05), self._resend_if_unanswered)
        else:
            self.clock = RobotClock(plant.dt, settings.time_scale, self.get_clock().now().nanoseconds)
            self._holding = settings.start_on_command
            with self._lock:
                self._publish(stamp(self.clock.last_ns))
            self._clock_thread = threading.Thread(target=self._run_clock, name="npp-robot-clock", daemon=True)
            self._clock_thread.start()
        self.create_service(ResetRobot, settings.reset_service, self.on_reset, qos_profile=SERVICE_QOS)

    # ---------------------------------------------------------------- commands
    def on_command(self, msg: Float64MultiArray) -> None:
        layout, plant = self.layout, self.plant
        if layout is None or plant is None:
            return
        try:
            command = finite_vector(msg.data, len(layout.command_joints), "command", f"one per joint of "
                                    f"{list(layout.command_joints)}")  # fmt: skip
        except ValueError as exc:
            self.ignored_commands += 1
            self._warn("command", f"ignored a command: {exc}")
            return
        action = layout.action(command)
        if self.settings.lockstep:
            with self._lock:
                self._step(action)
                self._publish(stamp(self.clock.stepped()))  # as before: steps * dt, plus a dt per reset
        else:
            self._command, self._fresh = action, True
            self._commanded.set()

    # ---------------------------------------------------------------- resets
    def on_reset(self, request: ResetRobot.Request, response: ResetRobot.Response) -> ResetRobot.Response:
        """Bring the plant to a start and hold it; answer the start as measured and its stamp, or why not."""
        try:
            problem, measured, when = self._reset(request.state)
        except Exception as exc:  # never into the executor: a caller gets the reason
            problem, measured, when = f"the reset failed: {type(exc).__name__}: {exc}", np.zeros(0), Time()
            self.get_logger().error(problem)
        if problem is not None:
            self.refused_resets += 1
            self._warn("reset", f"refused a reset: {problem}")
            response.success, response.message = False, problem
            return response
        self.resets += 1
        hold = "steps on the next command" if self.settings.lockstep else "held until the next command"
        response.success, response.message = True, f"reset {self.resets}: at the start, {hold}"
        response.state, response.stamp = float64_array(measured), when
        return response

    def _reset(self, requested: Sequence[float]) -> tuple[str | None, np.ndarray, Time]:
        """(why the reset is refused, or None; the start as published; its stamp). A refusal changes nothing."""
        plant, layout = self.plant, self.layout
        if plant is None or layout is None:
            return "the robot is still being built; retry shortly", np.zeros(0), Time()
        if len(requested) == 0:
            start = self._start
        else:
            joints = ", ".join(plant.joint_names)
            try:
                start = finite_vector(requested, len(self._start), "state", f"qpos then qvel of {joints}; "
                                      "empty for the robot's own start")  # fmt: skip
            except ValueError as exc:
                return str(exc), np.zeros(0), Time()
        with self._lock:
            plant.reset(start)
            self._effects = RobotEffects(self.robot, plant.action_dim)  # its delay queue starts empty
            self._command, self._fresh = None, False
            self._commanded.clear()
            self._applied = np.zeros(plant.action_dim)
            if self.settings.lockstep:
                when = stamp(self.clock.skipped())
            else:
                self._holding = True  # the clock thread holds it from its next tick on
                self._repeat_start = True  # the held start goes out again as measured: its values, its stamp
                when = stamp(self.clock.held())
            measured = self._publish(when)
        return None, measured, when

    # ---------------------------------------------------------------- stepping
    def _step(self, action: np.ndarray) -> None:
        assert self.plant is not None and self._effects is not None
        action = self._effects.command(action)  # after the robot's delay, if it has one
        self.plant.step(action)
        self._applied = action
        self.steps += 1

    def _run_clock(self) -> None:
        """Real time: one step per robot period (dt / time_scale wall seconds) on the monotonic clock, the latest
        command held; while holding a start, no step until a command comes, which is applied at once."""
        assert self.plant is not None
        period = self.plant.dt / self.settings.time_scale
        next_tick = time.monotonic() + period
        while not self._stopping.is_set():
            if self._holding:
                if not self._hold():
                    return
                next_tick = time.monotonic()  # the first command answers the start: it is applied at once
            delay = next_tick - time.monotonic()
            if delay > 0:
                self._stopping.wait(delay)
            elif delay < -period:  # more than a period late (a stalled machine): count it, keep the period
                self.overruns += 1
                next_tick += math.floor(-delay / period) * period
            next_tick += period
            with self._lock:
                if self._holding:
                    continue  # reset while this thread waited: hold the start from now on
                command, fresh = self._command, self._fresh
                self._fresh = False
                if command is None:
                    command = np.zeros(self.plant.action_dim)
                elif not fresh:
                    self.held_steps += 1
                self._step(command)
                if not rclpy.ok():
                    return  # shutting down: nobody to publish to
                self._publish(stamp(self.clock.stepped()))

    def _hold(self) -> bool:
        """Keep the plant at its start, publishing it every HOLD_REPUBLISH_S, until a command comes (True) or the
        node stops (False)."""
        while True:
            self._commanded.wait(max(self._last_sent + HOLD_REPUBLISH_S - time.monotonic(), 0.0))
            if self._stopping.is_set():
                return False
            with self._lock:
                if self._command is not None:
                    self._holding = self._repeat_start = False
                    self.clock.held()  # the robot's time when the command came: the first step ends dt after it
                    return True
                self._commanded.clear()
                if time.monotonic() >= self._last_sent + HOLD_REPUBLISH_S:
                    if not rclpy.ok():
                        return False
                    if self._repeat_start:  # after a reset: the measurement it answered, again, so the first
                        self._last_sent = time.monotonic()  # state stamped after it is the first step's
                        self.state_pub.publish(self._state_msg)
                    else:
                        self._publish(stamp(self.clock.held()))

    def _publish(self, when: Time) -> np.ndarray:
        """Send the plant's state as measured (with the robot's noise), stamped ``when``; returns what it sent."""
        assert self.plant is not None
        data = self.plant.physics.data
        msg = self._state_msg
        msg.header.stamp = when
        raw = np.concatenate([data.qpos[self._qpos], data.qvel[self._qvel]])
        if self._effects is not None:
            raw = self._effects.observe(raw)  # the robot's noise on what it reports, if it has some
        msg.position = float64_array(raw[: len(self._qpos)][self._measured])
        msg.velocity = float64_array(raw[len(self._qpos) :][self._measured])
        msg.effort = float64_array(np.where(self._effort_of >= 0, self._applied[self._effort_of], 0.0))
        self._last_sent = time.monotonic()
        self.state_pub.publish(msg)
        return raw

    def _resend_if_unanswered(self) -> None:
        if not self._started:
            if self._command_sub.get_publisher_count() > 0:
                self._started = True
                self.get_logger().info("a controller publishes commands: lockstep starts")
                with self._lock:
                    self._publish(stamp(self.clock.last_ns))
            return
        if time.monotonic() - self._last_sent >= self.settings.resend_after:
            with self._lock:
                self.state_pub.publish(self._state_msg)
                self._last_sent = time.monotonic()

    # ---------------------------------------------------------------- health
    def health(self) -> Health:
        mode = "lockstep" if self.settings.lockstep else "real time"
        if not self.settings.lockstep and self.settings.time_scale != 1.0:
            mode += f" x{self.settings.time_scale:g}"
        values = {
            "steps": self.steps,
            "steps on a held command": self.held_steps,
            "ignored commands": self.ignored_commands,
            "overruns": self.overruns,
            "resets": self.resets,
            "refused resets": self.refused_resets,
        }
        holding = ", holding the start until a command comes" if self._holding else ""
        return Health(f"{mode}: {self.steps} steps{holding}", values)

    def destroy_node(self) -> None:
        self._stopping.set()
        self._commanded.set()
        if self._clock_thread is not None:
            self._clock_thread.join(timeout=2.0)
        super().destroy_node()


def main(argv: Sequence[str] | None = None) -> int:
    return run_node(RobotNode, argv, USAGE)


if __name__ == "__main__":
    sys.exit(main())
