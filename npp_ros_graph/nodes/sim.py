"""npp-sim: a registered task's plant stepped in lockstep with whoever answers its states.

It publishes a state, then waits: only an action stamped with that state's time moves the plant,
so a slow or restarted policy can never make it skip or double a step. Anything else arriving on
the action topic is ignored with a (throttled) warning. The plant description goes out latched so
that an expert started at any time models exactly this plant.

Under model uncertainty a reset names the episode's drawn robot (npp_ros.tasks.uncertainty): the plant's model is
that robot for the episode and nominal again after it, the policy reads the robot's noisy states and the plant
applies its delayed commands, through the same RobotEffects as the in-process rollout, so the return is the same.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from contextlib import ExitStack
from dataclasses import dataclass

import numpy as np
from builtin_interfaces.msg import Time
from npp_interfaces.msg import EpisodeResult, PlantDescription
from npp_interfaces.srv import ResetEpisode
from rclpy.node import Node
from sensor_msgs.msg import JointState

from npp_ros.policy.vectors import finite_vector
from npp_ros.tasks.registry import MAX_HORIZON, Plant, Task, check_horizon, describe_tasks, get_task
from npp_ros.tasks.rollout import episode_return
from npp_ros.tasks.uncertainty import Robot, RobotEffects, as_robot, supports_robots
from npp_ros_graph.runtime.diagnostics import DiagnosticsReporter, Health
from npp_ros_graph.runtime.node import ThrottledWarnings, publishers_of, run_node
from npp_ros_graph.transport.convert import (
    action_from_joint_state,
    float64_array,
    plant_description,
    robot_from_field,
    rollout_result,
    stamp,
    state_to_joint_state,
)
from npp_ros_graph.transport.message_seal import RunSeal, SealError
from npp_ros_graph.transport.parameters import Param, StartupError, declare_settings, parameter_help
from npp_ros_graph.transport.topics import (
    ACTION,
    CONTROL_QOS,
    LATCHED_QOS,
    PLANT,
    REPORT_QOS,
    RESET_SERVICE,
    ROLLOUT_DONE,
    SERVICE_QOS,
    STATE,
)

PARAMETERS = (
    Param("task", "lqr_2_1", "a registered task (listed below; plug-ins too) or a task file (path ending in .toml)"),
    Param("seed", 0, "task seed: the plant's stiffnesses depend on it; also seeds s0 ~ rho per episode", 0, 2**32 - 1),
    Param("horizon", 1000, "control steps per episode", 1, MAX_HORIZON),
    Param("resend_after", 1.0, "seconds without an answer before the current state is sent again (0 = never)", 0.0),
)


@dataclass(frozen=True)
class SimSettings:
    """The sim's parameters; the core checks the task's name and the horizon."""

    task: str
    seed: int
    horizon: int
    resend_after: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "task", get_task(self.task).name)  # a task file's name carries its content hash
        check_horizon(self.horizon)


USAGE = f"""npp-sim: a task's plant in lockstep (node "npp_sim").

After a reset it publishes the episode's first state, then steps once per action answering the
latest state, and publishes the next state; after `horizon` steps it reports the episode. A state
left unanswered for `resend_after` seconds is sent again with the same stamp, so a policy node
started or restarted mid-episode picks the episode up where it stopped.

publishes   /{PLANT} (npp_interfaces/msg/PlantDescription, latched)
            /{STATE} (sensor_msgs/JointState: position = qpos, velocity = qvel, stamp = simulated time)
            /{ROLLOUT_DONE} (npp_interfaces/msg/EpisodeResult: return and steps of the finished episode)
subscribes  /{ACTION} (sensor_msgs/JointState: effort = action, name = actuated joints or empty,
            stamp = the stamp of the state it answers; anything else is ignored with a warning)
serves      /{RESET_SERVICE} (npp_interfaces/srv/ResetEpisode: empty state = sample s0 ~ rho for
            the given episode index, else reset to the given state; asked again for the same run,
            episode, attempt and state it does not restart the episode but says where it stands,
            and sends a finished episode's result again, so a result lost in a pause is not lost;
            a robot names the drawn robot the episode runs on, '' the nominal model)

{parameter_help(PARAMETERS)}
"""


class SimNode(Node):
    def __init__(self) -> None:
        super().__init__("npp_sim")
        settings = declare_settings(self, PARAMETERS, SimSettings)
        self.task, self.seed, self.horizon, self.resend_after = (
            settings.task,
            settings.seed,
            settings.horizon,
            settings.resend_after,
        )
        self.spec: Task = get_task(self.task)
        self.plant: Plant | None = None
        self.dt_ns = 0
        # The running episode; `state_stamp` is the last published state's time, None when no episode runs.
        self.episode = 0
        self.steps = 0
        self.rewards: list[float] = []
        self.initial_state = np.zeros(0)
        self.state_stamp: Time | None = None
        # The episode's drawn robot (None: nominal): its model held for the episode, its delay and noise.
        self.robot: Robot | None = None
        self.effects: RobotEffects | None = None
        self._as_robot = ExitStack()
        # Which data the policy drove the running episode with ("trajectories held", from each action's seal).
        self.drivers: set[str] = set()
        self.run_seal = RunSeal.from_environment()
        self.plant_seal: RunSeal | None = None  # the run key's seal for this plant, once built
        self.seal: RunSeal | None = None  # the seal of the run the current episode belongs to (set by its reset)
        # The reset that started the current episode (run, episode, attempt, s0, robot), and its result once finished.
        self._started: tuple[str, int, int, tuple[float, ...], str] | None = None
        self._result: EpisodeResult | None = None
        self._last_state: JointState | None = None
        self._last_sent = 0.0
        self.ignored_actions = 0
        self._warn = ThrottledWarnings(self)
        self.plant_pub = self.create_publisher(PlantDescription, PLANT, LATCHED_QOS)
        self.state_pub = self.create_publisher(JointState, STATE, CONTROL_QOS)
        self.done_pub = self.create_publisher(EpisodeResult, ROLLOUT_DONE, REPORT_QOS)
        self.create_subscription(JointState, ACTION, self.on_action, CONTROL_QOS)
        self.create_service(ResetEpisode, RESET_SERVICE, self.on_reset, qos_profile=SERVICE_QOS)
        self._build_timer = self.create_timer(0.0, self._build)  # MuJoCo loads after init, not inside it
        if self.resend_after > 0:
            self.create_timer(min(self.resend_after, 0.25), self._resend_if_unanswered)
        self.diagnostics = DiagnosticsReporter(self, lambda: Health(
            f"episode {self.episode}, step {self.steps}" if self.state_stamp is not None else "waiting for a reset",
            {"ignored actions": self.ignored_actions}, error=self._warn.last))  # fmt: skip

    def _build(self) -> None:
        self._build_timer.cancel()
        self.destroy_timer(self._build_timer)
        try:
            plant = self.spec.make_plant(self.seed)
        except Exception as exc:  # run_node turns this into a clean exit with the reason
            raise StartupError(f"cannot build the plant {self.task} seed {self.seed}: {exc}") from exc
        self.plant_seal = self.run_seal.for_plant(plant.model_sha256())
        self.plant = plant
        self.dt_ns = round(plant.dt * 1e9)
        self.plant_pub.publish(self.run_seal.seal(plant_description(plant, self.seed, self.horizon)))
        self.get_logger().info(
            f"plant {self.task} seed {self.seed} ready: joints {plant.joint_names}, "
            f"actuated {plant.actuated_joint_names}, dt {plant.dt} s, horizon {self.horizon}"
        )

    # ------------------------------------------------------------------ reset
    def on_reset(self, request: ResetEpisode.Request, response: ResetEpisode.Response) -> ResetEpisode.Response:
        try:
            problem, news = self._reset(request)
        except Exception as exc:  # never let an exception escape into the executor
            self.get_logger().error(f"reset failed: {type(exc).__name__}: {exc}")
            problem, news = f"internal error during reset: {exc}", ""
        if problem is not None:
            self.get_logger().warning(f"refused a reset: {problem}", throttle_duration_sec=1.0)
            response.success, response.message = False, problem
        else:
            response.success = True
            response.message = news
            response.state = float64_array(self.initial_state)
        try:
            seal = self.plant_seal.for_run(request.run) if self.plant_seal is not None else None
        except SealError:
            seal = self.plant_seal
        return response if seal is None else seal.seal(response, answering=request)

    def _reset(self, request: ResetEpisode.Request) -> tuple[str | None, str]:
        """(why the reset is refused, or None; what it did). A repeat of the reset that started the current
        episode leaves the episode as it is: the supervisor asks again when it lost track (a pause)."""
        plant, plant_seal = self.plant, self.plant_seal
        if plant is None or plant_seal is None:
            return f"the plant {self.task} seed {self.seed} is still being built; retry shortly", ""
        try:
            seal = plant_seal.for_run(request.run)
            seal.check(request, "the reset request")
        except SealError as exc:
            return f"{exc}; only this run's supervisor resets the sim", ""
        started = (request.run, int(request.episode), int(request.attempt), tuple(request.state), request.robot)
        if started == self._started:
            if self.state_stamp is not None:
                return None, f"episode {self.episode} under way at step {self.steps}"
            if self._result is not None:
                self.done_pub.publish(self._result)
                return None, f"episode {self.episode} done; its result sent again"
        if len(request.state) == 0:
            s0 = self.spec.initial_state(self.seed, request.episode)
        else:
            layout = f"{self.spec.stored_state} of {self.task}, or none to sample s0"
            try:
                s0 = finite_vector(request.state, plant.state_dim, "state", layout)
            except ValueError as exc:
                return str(exc), ""
        try:
            robot = robot_from_field(request.robot)
        except ValueError as exc:
            return str(exc), ""
        if robot is not None and not supports_robots(plant):
            return f"the plant {self.task} cannot be made into a drawn robot (not a MuJoCo model)", ""
        if self.state_stamp is not None:
            self.get_logger().info(f"episode {self.episode} abandoned after {self.steps} steps by a reset")
        self._as_robot.close()  # the last episode's robot, if it was abandoned: nominal before the next one
        try:
            self._as_robot.enter_context(as_robot(plant, robot))
        except ValueError as exc:  # a robot of another model (an element this one lacks): nothing was changed
            self.state_stamp = None
            return f"robot: {exc}", ""
        self.robot = robot
        self.effects = None if robot is None else RobotEffects(robot, plant.action_dim)
        self.initial_state = plant.reset(s0)
        self.seal, self._started, self._result = seal, started, None
        self.episode = int(request.episode)
        self.steps = 0
        self.rewards.clear()
        self.drivers.clear()
        self._publish_state()
        return None, f"episode {self.episode} started" + ("" if robot is None else f" on the robot {robot.describe()}")

    # -------------------------------------------------------------- lockstep
    def on_action(self, msg: JointState) -> None:
        try:
            problem = self._step(msg)
        except Exception as exc:  # never let an exception escape into the executor
            self.get_logger().error(f"step failed: {type(exc).__name__}: {exc}")
            problem = f"internal error: {exc}"
        if problem is not None:
            self.ignored_actions += 1
            kind = problem.split(":")[0]
            if kind == "foreign":
                problem += f" (publishers of {self.resolve_topic_name(ACTION)}: {publishers_of(self, ACTION)})"
            self._warn(kind, f"ignored an action: {problem}")

    def _step(self, msg: JointState) -> str | None:
        """Apply the action if it answers the current state; else say why not."""
        plant, seal = self.plant, self.seal
        if plant is None or seal is None or self.state_stamp is None:
            return "no episode is running (reset the sim first)"
        try:
            episode, _, driver = seal.check_header(msg, "the action").partition("/")
        except SealError as exc:
            return f"foreign: {exc}"
        if episode != str(self.episode):
            return f"stale: it answers a state of episode {episode}, the current one is {self.episode}"
        got = (msg.header.stamp.sec, msg.header.stamp.nanosec)
        want = (self.state_stamp.sec, self.state_stamp.nanosec)
        if got != want:
            return (
                f"stale: it answers the state stamped {got[0]}.{got[1]:09d}, the current one is {want[0]}.{want[1]:09d}"
            )
        try:
            u = action_from_joint_state(msg, plant.actuated_joint_names)
        except ValueError as exc:
            return str(exc)
        self.rewards.append(plant.step(u if self.effects is None else self.effects.command(u)))
        self.drivers.add(driver)
        self.steps += 1
        if self.steps >= self.horizon:
            self._finish()
        else:
            self._publish_state()
        return None

    def _publish_state(self) -> None:
        assert self.plant is not None and self.seal is not None
        self.state_stamp = stamp(self.steps * self.dt_ns)
        state = self.plant.state() if self.effects is None else self.effects.observe(self.plant.state())
        msg = state_to_joint_state(state, self.plant.joint_names, self.state_stamp)
        self._send(self.seal.seal_header(msg, str(self.episode)))

    def _send(self, msg: JointState) -> None:
        self._last_state, self._last_sent = msg, time.monotonic()
        self.state_pub.publish(msg)

    def _resend_if_unanswered(self) -> None:
        """Lockstep watchdog: a policy that (re)joins mid-episode never saw the pending state."""
        if self.state_stamp is None or self._last_state is None:
            return
        if time.monotonic() - self._last_sent >= self.resend_after:
            self.get_logger().info(
                f"no answer to the state at step {self.steps} of episode {self.episode}; sending it again",
                throttle_duration_sec=10.0,
            )
            self._send(self._last_state)

    def _finish(self) -> None:
        total = episode_return(self.rewards)
        result = rollout_result(
            self.episode, total, self.steps, self.initial_state, stamp(self.steps * self.dt_ns), self.robot
        )
        self.state_stamp = None  # no more states until the next reset
        self._as_robot.close()  # the model is nominal again between episodes
        assert self.seal is not None
        # The context names the data the policy drove with: a return counts only for the policy it certifies.
        self._result = self.seal.seal_header(result, ",".join(sorted(self.drivers)))
        self.done_pub.publish(self._result)
        self.get_logger().info(
            f"episode {self.episode} done: {self.steps} steps, return {total:.3f}"
            + ("" if self.robot is None else f", on the robot {self.robot.describe()}")
            + (f", {self.ignored_actions} actions ignored so far" if self.ignored_actions else "")
        )


def main(argv: Sequence[str] | None = None) -> int:
    usage = lambda: f"{USAGE}\n{describe_tasks()}"  # noqa: E731  # --help only: it imports the plug-ins
    return run_node(SimNode, argv, usage, events=True)  # the control loop: no wait set to rebuild per action


if __name__ == "__main__":
    sys.exit(main())
