"""npp-trial: a certified run deployed on the simulated robot in real time, episode by episode, against
the same policy in process.

Before a real robot, this is the rehearsal: npp-deploy (its own process) loads the run folder through
its gate exactly as it would for the robot (no override), and npp-robot (a new process per episode,
``start_on_command``) plays the task's MuJoCo plant in real time from a fresh s0, holding it there
until npp-deploy (activated once the robot holds s0, deactivated after the episode) sends its first
command, then stepping once per control period with the latest command held
(a command that misses its period leaves the previous one in force). For every episode it reports:

- the robot's return, recomputed by replaying the efforts the robot reported on the model (the
  replay must reproduce every joint state the robot published, bit for bit: the robot is the model);
- the in-process return of the certified policy from the same s0 (``rollout`` on the plant), the
  gap between the two, and the share of steps whose command was the policy's fresh answer to the
  state just before (the rest ran on a held command: real time, a busy machine);
- on the swing-up tasks, whether the pole ended upright (within 8 degrees over the last half of the
  horizon), on the robot and in process.

A reach whose state holds a target (a task file's ``state.target``): each episode's target is s0's, published on
npp-deploy's target topic (geometry_msgs/PointStamped in frame ``world``, ten times a second from before its
activation to the episode's end), and the episode is judged on the task's success criterion too, on the robot and
in process.

The s0 are draws from rho the run never made (episodes 10^6 + k of the run's own stream). A run certified on a
set of robots (``--uncertainty``) is tried on robots drawn from its set the same way (npp-robot's ``robot``
parameter; the in-process reference runs on the same robot), unless ``--robots nominal`` asks for its model; the
robot's return is its reported efforts replayed on that robot's model. Every run
of the tool gets its own ROS_DOMAIN_ID with localhost-only discovery. ``--out DIR`` writes
DIR/trial.json and DIR/trial.md with the command, the date and the load average.

``--outside SPEC`` tries such a run on one robot *outside* its set instead (SPEC: ``gear=3``, every actuator's
gear x3; ``mass[pole]=1.5``, one element; ``delay=2``, control steps; comma-separated; or a robot record), from
episode 10^6's s0, in three phases, each with its own npp-robot and npp-deploy (robot_model_fingerprint empty:
the gate reads the robot's description):

1. gate: npp-robot publishes its true description; npp-deploy's configure must refuse it, and the refusal (the
   parameter, its value, the range) is read from npp-deploy's /diagnostics;
2. warn: npp-robot publishes the nominal description (a robot that changed without saying so, past the gate),
   on_model_mismatch warn: when /diagnostics went WARN for the model mismatch after activation (seconds and the
   robot's control steps), and the episode's outcome over the horizon;
3. stop: the same with on_model_mismatch stop: when the safe command came after activation, and that no other
   command came after it and the robot's efforts went to zero.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Point, PointStamped
from lifecycle_msgs.srv import ChangeState
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from npp_ros.bench.measure import POLE_ANGLE, UPRIGHT_DEGREES, worst_angle_degrees
from npp_ros.bench.report import write_report
from npp_ros.deployment.gate import Acceptance, Deployment, load_deployment
from npp_ros.deployment.joints import JointLayout, stored_state
from npp_ros.tasks.rollout import rollout
from npp_ros.tasks.uncertainty import MAX_ACTION_DELAY, PARAMETERS, Robot, UncertaintySet, as_robot, model_elements
from npp_ros_graph.bench.deploy import transition
from npp_ros_graph.bench.ros_loop import reserved_domain, spawn, stop, wait_for
from npp_ros_graph.runtime.diagnostics import DIAGNOSTICS, DIAGNOSTICS_QOS, WARN, Health, health_of
from npp_ros_graph.transport.topics import CONTROL_QOS, FORWARD_COMMANDS, JOINT_STATES

MODEL = "the task's model"  # what the robot is when the run names no set or --robots nominal asks for it
TARGET, TARGET_FRAME = "/npp_deploy/target", "world"  # npp-deploy's target_topic and target_frame defaults
TARGET_PERIOD_S = 0.1  # a reach's target, sent again this often (npp-deploy takes the newest)
FIRST_TRIAL_EPISODE = 10**6  # s0 of episodes no run draws: fresh for the policy
START_TIMEOUT_S = 120.0  # a robot process importing rclpy and MuJoCo on a busy machine
# Every joint state of an episode is kept: the trial replays them all.
KEEP_ALL = QoSProfile(depth=100_000, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
# --outside: npp-deploy's words for what each phase waits for (npp_ros/deployment/state.py, nodes/deploy.py)
DEPLOY_NODE = "/npp_deploy"
REFUSED = "configure refused: "
LEAVES = "leave the certified set of robots"  # WARN while active
LEFT = "left the certified set of robots"  # the reason named while inactive after on_model_mismatch stop
MONITOR_WAIT_S = 60.0  # after the horizon's steps, how long a phase keeps the robot under npp-deploy for the monitor
STEPS_AFTER_STOP = 25  # the robot's steps watched after the safe command
MONITOR_LINE = "the robot's transitions leave the certified set of robots"  # npp-deploy's log, warn or stop
LOGGED = re.compile(r"^\[\w+\] \[(?P<at>\d+\.\d+)\]")  # a ROS log line's severity and wall-clock time
SPEC_PART = re.compile(r"^(?P<name>[a-z]+)(?:\[(?P<element>[^\]]+)\])?=(?P<value>[^=]+)$")


def log(text: str) -> None:
    sys.stderr.write(f"npp-trial: {text}\n")
    sys.stderr.flush()


@dataclass(frozen=True)
class TrialEpisode:
    """One episode on the robot and the same s0 in process."""

    episode: int
    robot_return: float
    in_process_return: float
    fresh_command_share: float  # steps whose command answered the state just before
    first_command_answers_s0: bool  # the robot waited at s0 for the policy's answer to it
    replay_mismatches: int  # published states the model's replay of the robot's efforts does not reproduce
    robot_upright: bool | None  # swing-up tasks: the pole within 8 degrees over the last half; else None
    in_process_upright: bool | None
    robot: str = ""  # the robot of a run certified on a set (Robot.record()); "" = the task's model
    robot_success: bool | None = None  # the task's success criterion on the robot's states (None: it states none)
    in_process_success: bool | None = None

    @property
    def gap(self) -> float:
        return self.in_process_return - self.robot_return


class TrialNode(Node):
    """This process's side: npp-deploy's lifecycle client, and the robot's joint states of one episode."""

    def __init__(self, layout: JointLayout) -> None:
        super().__init__("npp_trial")
        self.change = self.create_client(ChangeState, "/npp_deploy/change_state")
        self.layout = layout
        self.s0 = np.zeros(0)
        self.raws: list[np.ndarray] = []  # [qpos, qvel] from s0 on
        self.efforts: list[np.ndarray] = []  # efforts[k]: the command applied in step k
        self.create_subscription(JointState, JOINT_STATES, self.on_state, KEEP_ALL)
        self.target: PointStamped | None = None  # a reach: s0's target, sent to npp-deploy until the episode ends
        if layout.target is not None:
            self.target_pub = self.create_publisher(PointStamped, TARGET, CONTROL_QOS)
            self.create_timer(TARGET_PERIOD_S, self.send_target)

    def expect(self, s0: np.ndarray) -> None:
        """A new episode from s0: what came before is dropped; a reach aims at s0's target."""
        self.s0, self.raws, self.efforts = s0, [], []
        if self.layout.target is not None and s0.size:
            self.layout.aim_as(s0)  # the robot measures no target: its states hold s0's, as the task stores them
            point = self.layout.target.point(self.layout.aimed)
            self.target = PointStamped(point=Point(x=float(point[0]), y=float(point[1]), z=float(point[2])))
            self.target.header.frame_id = TARGET_FRAME
            self.send_target()
        elif not s0.size:
            self.target = None

    def send_target(self) -> None:
        if self.target is not None:
            self.target.header.stamp = self.get_clock().now().to_msg()
            self.target_pub.publish(self.target)

    def on_state(self, msg: JointState) -> None:
        """The robot publishes s0 while it waits for its first command; the episode starts with the
        last of those, and each message after it is the state after a step and that step's effort."""
        if self.s0.size == 0:
            return
        raw = self.layout.state(msg.name, msg.position, msg.velocity)
        if not self.efforts and np.array_equal(raw, self.s0):
            self.raws = [raw]
            return
        if not self.raws:
            return  # a message of the last episode's robot
        where = [list(msg.name).index(name) for name in self.layout.command_joints]
        self.raws.append(raw)
        self.efforts.append(np.array([msg.effort[i] for i in where]))


class WatchingNode(TrialNode):
    """TrialNode that also keeps npp-deploy's /diagnostics statuses and its commands, each with its arrival
    (monotonic) and the robot's steps by then (--outside)."""

    def __init__(self, layout: JointLayout) -> None:
        super().__init__(layout)
        self.statuses: list[tuple[float, int, Health]] = []
        self.commands: list[tuple[float, int, list[float]]] = []
        self.state_times: list[float] = []  # wall-clock arrival of each joint state after s0 (efforts[k]'s)
        self.since = 0.0
        self.create_subscription(DiagnosticArray, DIAGNOSTICS, self.on_diagnostics, DIAGNOSTICS_QOS)
        self.create_subscription(Float64MultiArray, FORWARD_COMMANDS, self.on_command, KEEP_ALL)

    def expect(self, s0: np.ndarray) -> None:
        """As TrialNode's; joint states and statuses stamped before now are an earlier phase's nodes' (the phases
        share s0: an earlier robot's s0, delivered late, would start the episode before this robot is heard)."""
        super().expect(s0)
        self.statuses, self.commands, self.state_times = [], [], []
        self.since = time.time()

    def on_state(self, msg: JointState) -> None:
        if _seconds(msg.header.stamp) < self.since:
            return
        before = len(self.efforts)
        super().on_state(msg)
        if len(self.efforts) > before:
            self.state_times.append(time.time())

    def on_diagnostics(self, msg: DiagnosticArray) -> None:
        if _seconds(msg.header.stamp) < self.since:
            return
        self.statuses += [(time.monotonic(), len(self.efforts), health_of(s)) for s in msg.status
                          if s.name == DEPLOY_NODE]  # fmt: skip

    def on_command(self, msg: Float64MultiArray) -> None:
        self.commands.append((time.monotonic(), len(self.efforts), list(msg.data)))

    def first_status(self, holds: Callable[[Health], bool]) -> tuple[float, int, Health] | None:
        return next((item for item in self.statuses if holds(item[2])), None)

    def steps_by(self, wall: float) -> int:
        """The robot's steps whose joint state had arrived by wall-clock time ``wall``."""
        return int(np.searchsorted(np.array(self.state_times), wall, side="right"))


def _seconds(stamp: Any) -> float:
    return stamp.sec + stamp.nanosec * 1e-9


def judge(deployment: Deployment, episode: int, s0: np.ndarray, raws: np.ndarray, efforts: np.ndarray,
          horizon: int, drawn: Robot | None = None) -> TrialEpisode:  # fmt: skip
    """The robot's episode against the model (the drawn robot's) and against the policy in process on it.

    The efforts are the commands the actuator applied (after the robot's delay), so they are replayed on the
    robot's model without a delay; the in-process reference meets the delay and the noise itself."""
    plant, policy = deployment.plant, deployment.policy
    layout = JointLayout.of_plant(plant)
    actions = np.array([layout.action(effort) for effort in efforts[:horizon]])
    model_only = None if drawn is None else Robot(drawn.scales)
    with as_robot(plant, model_only):
        replayed = _raw_states(plant, s0, actions)
    mismatches = int(np.sum(np.any(replayed[1:] != raws[1 : horizon + 1], axis=1)))
    robot = rollout(plant, _replayer(actions), s0, horizon, model_only)
    stored = np.array([stored_state(plant, raw) for raw in raws[:horizon]])
    answer = policy.controller()  # the robot's episode answered state by state, as npp-deploy's activation did
    fresh = float(
        np.mean([np.array_equal(answer(state), action) for state, action in zip(stored, actions, strict=True)])
    )
    reference = rollout(plant, policy.controller(), s0, horizon, drawn)
    first = bool(np.array_equal(actions[0], reference.actions[0]))
    criterion = deployment.task.success
    success = (None, None) if criterion is None else (criterion.met(stored), criterion.met(reference.states))
    angle = POLE_ANGLE.get(deployment.task.name)
    upright: tuple[bool | None, bool | None] = (None, None)
    if angle is not None:
        hold, acrobot = max(1, horizon // 2), deployment.task.name == "acrobot_swingup"
        upright = tuple(  # type: ignore[assignment]
            worst_angle_degrees(states, angle, hold, acrobot) <= UPRIGHT_DEGREES
            for states in (stored, reference.states)
        )
    record = "" if drawn is None else drawn.record()
    return TrialEpisode(
        episode, robot.total_return, reference.total_return, fresh, first, mismatches, *upright, robot=record,
        robot_success=success[0], in_process_success=success[1],
    )  # fmt: skip


def _replayer(actions: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    steps: Iterator[np.ndarray] = iter(actions)
    return lambda _state: next(steps)


def _raw_states(plant: Any, s0: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """[qpos, qvel] after each of ``actions`` from s0, as the robot publishes them (angles unwrapped)."""
    plant.reset(s0)
    data = plant.physics.data
    out = [np.concatenate([data.qpos, data.qvel])]
    for action in actions:
        plant.step(action)
        out.append(np.concatenate([data.qpos, data.qvel]))
    return np.array(out)


def ros_args(params: dict[str, str]) -> list[str]:
    return [arg for name, value in params.items() for arg in ("-p", f"{name}:={value}")]


def spawn_robot(deployment: Deployment, s0: np.ndarray, robot: Robot | None, extra: dict[str, str],
                env: dict[str, str], log_path: Path) -> Any:  # fmt: skip
    """npp-robot holding ``s0`` until its first command, as ``robot`` (None: the task's model), with ``extra``
    parameters."""
    params = {"task": deployment.task.name, "seed": str(deployment.metadata.seed),
              "initial_state": ",".join(repr(float(x)) for x in s0), "start_on_command": "true"}  # fmt: skip
    if robot is not None:
        params["robot"] = f"'{robot.record()}'"  # a YAML string: the record's JSON braces would read as a mapping
    return spawn(["npp_ros_graph.nodes.robot", "--ros-args", *ros_args(params | extra)], env, log_path)


def wait_for_s0(executor: SingleThreadedExecutor, node: TrialNode, episode: int, logs: Path) -> None:
    """npp-deploy is inactive while the robot starts: this node sees the robot hold s0 before any command."""
    if not wait_for(executor, lambda: len(node.raws) > 0, START_TIMEOUT_S):
        raise RuntimeError(f"no joint state at episode {episode}'s s0 within {START_TIMEOUT_S:.0f} s; see {logs}")


def run_episode(executor: SingleThreadedExecutor, node: TrialNode, deployment: Deployment, episode: int,
                horizon: int, env: dict[str, str], logs: Path, robots: UncertaintySet | None = None,
                ) -> TrialEpisode:  # fmt: skip
    """One robot process from the episode's s0 (and, given ``robots``, as the episode's robot drawn from them),
    for ``horizon`` real-time steps under npp-deploy."""
    task, seed = deployment.task, deployment.metadata.seed
    s0 = task.initial_state(seed, episode)
    drawn = None if robots is None else robots.draw(seed, episode)
    node.expect(s0)
    robot = spawn_robot(deployment, s0, drawn, {}, env, logs / f"robot-{episode}.log")
    limit = START_TIMEOUT_S + 4 * horizon * deployment.plant.dt  # real time: the episode's duration on top
    try:
        wait_for_s0(executor, node, episode, logs)
        transition(executor, node, "activate", 60.0)
        try:
            if not wait_for(executor, lambda: len(node.efforts) >= horizon, limit):
                raise RuntimeError(
                    f"the robot ran {len(node.efforts)} of {horizon} steps from episode {episode}'s s0 within "
                    f"{limit:.0f} s; see {logs}"
                )
        finally:
            transition(executor, node, "deactivate", 60.0)
    finally:
        stop(robot)
    raws, efforts = np.array(node.raws), np.array(node.efforts)
    node.expect(np.zeros(0))
    return judge(deployment, episode, s0, raws, efforts, horizon, drawn)


# ---------------------------------------------------------------------------------------------- --outside
def outside_robot(spec: str, plant: Any) -> Robot:
    """The robot ``--outside`` names: a robot record (JSON), or comma-separated PARAMETER=FACTOR (every element of
    its kind), PARAMETER[ELEMENT]=FACTOR (one element) and delay=STEPS; a ValueError says what is wrong."""
    text = spec.strip()
    if text.startswith("{"):
        robot = Robot.from_record(text)
    else:
        elements = model_elements(plant.physics.model)
        factors: dict[tuple[str, str], float] = {}
        delay = 0
        for part in (part.strip() for part in text.split(",")):
            match = SPEC_PART.match(part)
            if match is None:
                raise ValueError(f"{part!r} is not PARAMETER=FACTOR, PARAMETER[ELEMENT]=FACTOR or delay=STEPS")
            name, element, value = match["name"], match["element"], match["value"].strip()
            if name == "delay":
                if element is not None or not value.isdigit() or int(value) > MAX_ACTION_DELAY:
                    raise ValueError(f"{part!r}: a delay is a whole number of control steps, 0 to {MAX_ACTION_DELAY}")
                delay = int(value)
                continue
            if name not in PARAMETERS:
                raise ValueError(f"{part!r}: no parameter {name!r} (known: {', '.join(PARAMETERS)}, delay)")
            kind = PARAMETERS[name][0]
            if element is not None and element not in elements[kind]:
                raise ValueError(f"{part!r}: the model has no {kind} {element!r} (its {kind}s: "
                                 f"{', '.join(elements[kind])})")  # fmt: skip
            try:
                factor = float(value)
            except ValueError:
                factor = math.nan
            if not (math.isfinite(factor) and factor > 0):
                raise ValueError(f"{part!r}: a factor is a positive number")
            for target in elements[kind] if element is None else (element,):
                factors[(name, target)] = factor
        robot = Robot(tuple((p, n, f) for (p, n), f in factors.items()), delay)
    if robot.state_noise:
        raise ValueError("a robot with noise on its states is not tried: the trial replays the states it published")
    return robot


def configure(executor: SingleThreadedExecutor, node: WatchingNode, log_path: Path) -> str:
    """npp-deploy's configure: "" when it passed, else its refusal as its /diagnostics status states it (its log's
    line when no status says so within 30 s)."""
    try:
        transition(executor, node, "configure", 900.0)
        return ""
    except RuntimeError as exc:
        if "refused" not in str(exc):
            raise  # no lifecycle service: nothing was asked

    def refused() -> tuple[float, int, Health] | None:
        return node.first_status(lambda h: h.doing.startswith(REFUSED))

    if wait_for(executor, lambda: refused() is not None, 30.0):
        return refused()[2].doing[len(REFUSED) :]  # type: ignore[index]
    lines = [line for line in log_path.read_text(errors="replace").splitlines() if REFUSED in line]
    return lines[-1].split(REFUSED, 1)[1] if lines else f"(no reason on /diagnostics or in {log_path})"


def monitor_found(node: WatchingNode, log_path: Path, activated_wall: float) -> dict[str, Any]:
    """When the model monitor first found the mismatch: its first log line saying so (the ROS log's wall-clock time),
    in seconds after activation and the robot's steps by then ({} when the log has no such line)."""
    for line in log_path.read_text(errors="replace").splitlines():
        found = LOGGED.match(line)
        if found is not None and MONITOR_LINE in line:
            at = float(found["at"])
            return {"found_after_s": at - activated_wall, "found_after_steps": node.steps_by(at)}
    return {}


def outside_phase(executor: SingleThreadedExecutor, node: WatchingNode, deployment: Deployment, run_dir: Path,
                  outside: Robot, phase: str, horizon: int, env: dict[str, str], logs: Path,
                  ) -> dict[str, Any]:  # fmt: skip
    """One --outside phase, "gate", "warn" or "stop" (the module's doc), with its own npp-robot (as ``outside``)
    and npp-deploy, from episode 10^6's s0; what it found, as the report keeps it."""
    episode = FIRST_TRIAL_EPISODE
    s0 = deployment.task.initial_state(deployment.metadata.seed, episode)
    node.expect(s0)
    described = "robot" if phase == "gate" else "nominal"
    mismatch = "stop" if phase == "stop" else "warn"
    deploy_log = logs / f"deploy-{phase}.log"
    robot = spawn_robot(deployment, s0, outside, {"publish_description": described}, env, logs / f"robot-{phase}.log")
    # robot_model_fingerprint left empty: the gate reads the robot's description (waiting for it up to 60 s)
    params = {"run_dir": str(run_dir), "description_timeout": "60.0", "on_model_mismatch": mismatch}
    deploy = spawn(["npp_ros_graph.nodes.deploy", "--ros-args", *ros_args(params)], env, deploy_log)
    result: dict[str, Any] = {"publish_description": described, "on_model_mismatch": mismatch}
    limit = START_TIMEOUT_S + 4 * horizon * deployment.plant.dt
    activated_wall = math.nan
    try:
        wait_for_s0(executor, node, episode, logs)
        refusal = configure(executor, node, deploy_log)
        if phase == "gate":
            result |= {"refused": bool(refusal), "reason": refusal}
        elif refusal:
            raise RuntimeError(f"npp-deploy refused the nominal description ({phase} phase): {refusal}")
        else:
            transition(executor, node, "activate", 60.0)
            activated, activated_wall = time.monotonic(), time.time()
            if phase == "warn":
                result |= watch_warn(executor, node, horizon, limit, activated)
            else:
                result |= watch_stop(executor, node, outside, horizon, limit, activated)
    finally:
        stop(deploy)
        stop(robot)
    if phase != "gate":
        result |= monitor_found(node, deploy_log, activated_wall)  # its log is whole once it exited
    if phase == "warn":
        row = judge(deployment, episode, s0, np.array(node.raws), np.array(node.efforts), horizon, outside)
        result["episode"] = asdict(row) | {"gap": row.gap}
    node.expect(np.zeros(0))
    return result


def watch_warn(
    executor: SingleThreadedExecutor, node: WatchingNode, horizon: int, limit: float, activated: float
) -> dict[str, Any]:
    """on_model_mismatch warn: the horizon's steps, and npp-deploy kept active until /diagnostics says WARN for the
    mismatch (up to MONITOR_WAIT_S more); when it did."""

    def warned() -> tuple[float, int, Health] | None:
        return node.first_status(lambda h: h.level == WARN and LEAVES in h.doing)

    try:
        if not wait_for(executor, lambda: len(node.efforts) >= horizon, limit):
            raise RuntimeError(f"the robot ran {len(node.efforts)} of {horizon} steps within {limit:.0f} s")
        wait_for(executor, lambda: warned() is not None, MONITOR_WAIT_S)
    finally:
        transition(executor, node, "deactivate", 60.0)
    seen = warned()
    if seen is None:
        return {"warned": False, "steps_watched": len(node.efforts)}
    at, steps, health = seen
    return {
        "warned": True, "warn_after_s": at - activated, "warn_after_steps": steps, "status": health.doing,
        "error": health.error,  # the model monitor's figures
    }  # fmt: skip


def watch_stop(
    executor: SingleThreadedExecutor, node: WatchingNode, outside: Robot, horizon: int, limit: float, activated: float
) -> dict[str, Any]:
    """on_model_mismatch stop: until npp-deploy says it stopped for the mismatch (the horizon's steps and up to
    MONITOR_WAIT_S more); when the safe command came, what came after it, and the robot's efforts after it."""

    def stopped() -> tuple[float, int, Health] | None:
        return node.first_status(lambda h: h.values.get("lifecycle state") == "inactive" and LEFT in h.doing)

    if not wait_for(executor, lambda: stopped() is not None or len(node.efforts) >= horizon, limit):
        transition(executor, node, "deactivate", 60.0)
        raise RuntimeError(f"the robot ran {len(node.efforts)} of {horizon} steps within {limit:.0f} s")
    if not wait_for(executor, lambda: stopped() is not None, MONITOR_WAIT_S):
        transition(executor, node, "deactivate", 60.0)
        return {"stopped": False, "steps_watched": len(node.efforts)}
    # The safe command: the first of the zero commands that end the list (the status may come before it does).
    wait_for(executor, lambda: bool(node.commands) and not any(node.commands[-1][2]), 30.0)
    first_zero = len(node.commands)
    while first_zero > 0 and not any(node.commands[first_zero - 1][2]):
        first_zero -= 1
    if first_zero == len(node.commands):
        return {"stopped": True, "commands_zero": False, "last_command": node.commands[-1][2] if node.commands else []}
    at, steps, safe = node.commands[first_zero]
    wait_for(executor, lambda: len(node.efforts) >= steps + outside.action_delay + STEPS_AFTER_STOP, 60.0)
    # The robot's efforts are the commands it applied (after its delay): zero from some step on, once it held the safe
    # command; that step against the robot's steps when the safe command reached this node.
    efforts = np.array(node.efforts)
    nonzero = np.flatnonzero(np.any(efforts != 0, axis=1))
    zero_from = int(nonzero[-1]) + 1 if nonzero.size else 0
    health = stopped()[2]  # type: ignore[index]
    return {
        "stopped": True, "stop_after_s": at - activated, "stop_after_steps": steps, "safe_command": safe,
        "commands_zero": True, "commands_after_safe": len(node.commands) - first_zero - 1,
        "robot_zero_from_step": zero_from, "robot_steps_zero": len(efforts) - zero_from,
        "status": health.doing, "model_monitor": str(health.values.get("model monitor", "")),
    }  # fmt: skip


def try_outside(executor: SingleThreadedExecutor, node: WatchingNode, deployment: Deployment, run_dir: Path,
                outside: Robot, horizon: int, env: dict[str, str], logs: Path) -> dict[str, Any]:  # fmt: skip
    out: dict[str, Any] = {}
    for phase in ("gate", "warn", "stop"):
        out[phase] = outside_phase(executor, node, deployment, run_dir, outside, phase, horizon, env, logs)
        log(f"{phase}: {phase_words(phase, out[phase])}")
    return out


def phase_words(phase: str, r: dict[str, Any]) -> str:
    """A phase's finding in one sentence (the log and trial.md)."""
    if phase == "gate":
        if r["refused"]:
            return f"npp-deploy's configure refused the robot's true description: {r['reason']}"
        return "npp-deploy's configure accepted the robot's true description (a delay shows in no description)"
    if phase == "warn":
        if not r["warned"]:
            return f"no WARN for the model mismatch on /diagnostics in {r['steps_watched']} steps"
        found = (f" (the monitor found it {r['found_after_s']:.2f} s, {r['found_after_steps']} steps, after activation)"
                 if "found_after_s" in r else "")  # fmt: skip
        return (f"/diagnostics went WARN {r['warn_after_s']:.2f} s ({r['warn_after_steps']} control steps) after "
                f"activation{found}")  # fmt: skip
    if not r["stopped"]:
        return f"npp-deploy did not stop in {r['steps_watched']} steps"
    if not r["commands_zero"]:
        return f"npp-deploy stopped, but its last command was {r['last_command']}"
    found = (f" (the monitor found it {r['found_after_s']:.2f} s, {r['found_after_steps']} steps, after activation)"
             if "found_after_s" in r else "")  # fmt: skip
    return (
        f"npp-deploy deactivated and sent the safe command {r['safe_command']} {r['stop_after_s']:.2f} s "
        f"({r['stop_after_steps']} control steps) after activation{found}; {r['commands_after_safe']} commands after "
        f"it; the robot's efforts zero from its step {r['robot_zero_from_step']} on, over the {r['robot_steps_zero']} "
        "steps watched"
    )


def summary(rows: list[TrialEpisode], epsilon: float) -> dict[str, Any]:
    robot = np.array([r.robot_return for r in rows])
    ref = np.array([r.in_process_return for r in rows])
    gaps = ref - robot
    out: dict[str, Any] = {
        "episodes": len(rows),
        "robot_return_median": float(np.median(robot)),
        "in_process_return_median": float(np.median(ref)),
        "gap_median": float(np.median(gaps)),
        "gap_p90": float(np.percentile(gaps, 90)),
        "gap_max": float(gaps.max()),
        "within_epsilon_of_in_process": float(np.mean(gaps <= epsilon)),
        "fresh_command_share_median": float(np.median([r.fresh_command_share for r in rows])),
        "fresh_command_share_min": float(min(r.fresh_command_share for r in rows)),
        "replay_mismatches": int(sum(r.replay_mismatches for r in rows)),
    }
    if rows and rows[0].robot_upright is not None:
        out["robot_upright"] = int(sum(bool(r.robot_upright) for r in rows))
        out["in_process_upright"] = int(sum(bool(r.in_process_upright) for r in rows))
    if rows and rows[0].robot_success is not None:
        out["robot_success"] = int(sum(bool(r.robot_success) for r in rows))
        out["in_process_success"] = int(sum(bool(r.in_process_success) for r in rows))
    return out


def report_head(out: dict[str, Any], title: str, run_ends: str) -> list[str]:
    """A report's title, its command (date, load) and its run and certificate, the run's line ending ``run_ends``."""
    c = out["certificate"]
    return [
        f"# npp-trial: {title}",
        "",
        f"Command: `{out['command']}` ({out['date']}; load average {out['load_average_start'][0]:.2f} at the start, "
        f"{out['load_average_end'][0]:.2f} at the end; {os.cpu_count()} cores).",
        "",
        f"Run: {out['run']} ({out['task']} seed {out['seed']}, H {out['horizon']}); certificate: epsilon "
        f"{c['epsilon']:g}, p {c['p']:g}, delta {c['delta']:g}, certify={c['certify']}, rule={c['rule']}, "
        f"{c['policy_trajectories']} trajectories in the policy, acting {out.get('policy', 'open-loop')}{run_ends}",
        "",
    ]


def markdown(out: dict[str, Any]) -> str:
    s = out["summary"]
    lines = [
        *report_head(
            out,
            "the certified policy on the real-time robot",
            ". npp-deploy loaded it through its gate (no override); npp-robot ran each episode in real time "
            f"({out['control_period_ms']:g} ms period) from a fresh s0, on {out.get('robots', MODEL)}.",
        ),
        "| episodes | return robot / in process (median) | gap in process - robot: median / p90 / max "
        "| within epsilon of in process | fresh commands (median, min) | replay mismatches "
        "| upright robot / in process | success robot / in process |",
        "|---|---|---|---|---|---|---|---|",
        f"| {s['episodes']} | {s['robot_return_median']:.1f} / {s['in_process_return_median']:.1f} | "
        f"{s['gap_median']:.2f} / {s['gap_p90']:.2f} / {s['gap_max']:.2f} | {s['within_epsilon_of_in_process']:.0%} | "
        f"{s['fresh_command_share_median']:.1%}, {s['fresh_command_share_min']:.1%} | {s['replay_mismatches']} | "
        + (f"{s['robot_upright']} / {s['in_process_upright']} |" if "robot_upright" in s else "- |")
        + (f" {s['robot_success']} / {s['in_process_success']} |" if "robot_success" in s else " - |"),
        "",
        "- return robot: the efforts the robot reported, replayed on the model from s0 (replay mismatches: joint "
        "states the replay does not reproduce bit for bit; 0 means the robot moved exactly as the model does).",
        "- fresh commands: steps whose command was the policy's answer to the state just before; the others ran "
        "on a held command (the answer missed its control period).",
        "- upright: the pole within 8 degrees of upright over the last half of the horizon.",
        "- success: the task's own success criterion on the episode's states (a task that states one).",
    ]
    return "\n".join(lines) + "\n"


def trial_episodes(executor: SingleThreadedExecutor, node: TrialNode, deployment: Deployment,
                   args: argparse.Namespace, fingerprint: str, horizon: int, env: dict[str, str], logs: Path,
                   robots: UncertaintySet | None) -> list[TrialEpisode]:  # fmt: skip
    """npp-deploy through the gate once (the certified fingerprint), then ``args.episodes`` episodes on npp-robot."""
    params = {"run_dir": str(args.run_dir), "robot_model_fingerprint": fingerprint}
    deploy = spawn(["npp_ros_graph.nodes.deploy", "--ros-args", *ros_args(params)], env, logs / "deploy.log")
    rows: list[TrialEpisode] = []
    started = time.monotonic()
    try:
        transition(executor, node, "configure", 900.0)  # the gate; each episode activates and deactivates
        for k in range(args.episodes):
            episode = FIRST_TRIAL_EPISODE + k
            rows.append(run_episode(executor, node, deployment, episode, horizon, env, logs, robots))
            r = rows[-1]
            log(f"episode {k + 1}/{args.episodes} ({time.monotonic() - started:.0f} s): return robot "
                f"{r.robot_return:.1f}, in process {r.in_process_return:.1f}, fresh commands "
                f"{r.fresh_command_share:.1%}")  # fmt: skip
    finally:
        stop(deploy)
    return rows


def outside_markdown(out: dict[str, Any]) -> str:
    o = out["outside"]
    lines = [
        *report_head(out, "the certified policy on a robot outside its set", f"; certified on {out['robots']}."),
        f"The robot tried: {o['robot_words']}, outside the set ({'; '.join(o['outside_reasons'])}). Each phase ran "
        "its own npp-robot (this robot, in real time, "
        f"{out['control_period_ms']:g} ms period, from the s0 of episode {FIRST_TRIAL_EPISODE:,d}) and its own "
        "npp-deploy (through the gate, no override, robot_model_fingerprint empty: the gate reads the robot's "
        "description).",
        "",
        "| phase | npp-robot publishes | on_model_mismatch | what happened |",
        "|---|---|---|---|",
    ]
    said = {"robot": "its true description", "nominal": "the nominal description"}
    for phase in ("gate", "warn", "stop"):
        r = o[phase]
        mismatch = "-" if phase == "gate" else r["on_model_mismatch"]
        lines.append(f"| {phase} | {said[r['publish_description']]} | {mismatch} | {phase_words(phase, r)} |")
    warn, stopped = o["warn"], o["stop"]
    lines.append("")
    if "episode" in warn:
        e = warn["episode"]
        upright = (f"; upright robot / in process: {e['robot_upright']} / {e['in_process_upright']}"
                   if e["robot_upright"] is not None else "")  # fmt: skip
        lines.append(
            f"- The warn phase's episode ({out['horizon']} steps, npp-deploy commanding throughout): return robot "
            f"{e['robot_return']:.1f}, in process on the same robot {e['in_process_return']:.1f}, fresh commands "
            f"{e['fresh_command_share']:.1%}, replay mismatches {e['replay_mismatches']}{upright}."
        )
    if warn.get("warned"):
        lines.append(f"- The WARN status: `{warn['status']}`; its error: `{warn['error']}`.")
    if stopped.get("status"):
        lines.append(f"- The stop phase's status while inactive: `{stopped['status']}`.")
    lines += [
        "- Times are from npp-deploy's activate answer to the status (/diagnostics, published every second and at "
        "each transition) or the command reaching npp-trial; control steps are the robot's steps by then. The "
        "monitor's own finding is the time of npp-deploy's first log line saying so.",
        "- return robot: the efforts the robot reported, replayed on this robot's model from s0 (replay mismatches: "
        "joint states the replay does not reproduce bit for bit).",
    ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="npp-trial", description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path, help="a certified run folder (its run.sqlite)")
    parser.add_argument("--episodes", type=int, default=100, help="episodes on the robot, each from a fresh s0")
    parser.add_argument("--horizon", type=int, default=0, help="steps per episode (0: the run's H)")
    parser.add_argument("--logs", type=Path, default=None, help="folder for the nodes' logs (default: OUT/logs)")
    parser.add_argument("--out", type=Path, default=Path("runs/trial"), help="write OUT/trial.json and OUT/trial.md")
    parser.add_argument(
        "--robots",
        choices=("drawn", "nominal"),
        default="drawn",
        help="a run certified on a set of robots: each episode's robot drawn from the set (drawn, the default) or "
        "the task's model (nominal); a run on the exact model is always tried on it",
    )
    parser.add_argument(
        "--outside",
        metavar="SPEC",
        default="",
        help="a run certified on a set of robots: try it instead on one robot outside the set, in three phases "
        "(the gate refusing the robot's true description; past the gate on the nominal description with "
        "on_model_mismatch warn, then stop: when /diagnostics warned, when the safe command came). SPEC: "
        "PARAMETER=FACTOR scales every element of its kind (gear=3), PARAMETER[ELEMENT]=FACTOR one "
        "(mass[pole]=1.5), delay=STEPS delays each command; comma-separated; or a robot record (JSON). Parameters: "
        f"{', '.join(PARAMETERS)}. --episodes and --robots do not apply; --horizon is the warn phase's episode",
    )
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.error(f"--episodes must be at least 1, got {args.episodes}")
    from npp_ros.run.setup import plant_fingerprint
    from npp_ros.run.store import RunStore

    run_file = args.run_dir / "run.sqlite"
    if not run_file.exists():
        parser.error(f"{args.run_dir} holds no run.sqlite")
    with RunStore.open(run_file) as store:
        meta = store.metadata
    fingerprint = plant_fingerprint(meta.task, meta.seed)
    deployment = load_deployment(args.run_dir, Acceptance(model_fingerprint=fingerprint))
    certificate = deployment.certificate
    assert certificate is not None  # the gate passed without an override: the run's own certificate
    horizon = args.horizon or meta.horizon
    uncertainty = str(getattr(meta, "uncertainty", ""))
    robots = UncertaintySet.from_record(uncertainty) if uncertainty and args.robots == "drawn" else None
    outside: Robot | None = None
    if args.outside:
        certified = UncertaintySet.from_record(uncertainty)
        if certified.empty:
            parser.error(f"--outside tries a run certified on a set of robots; {args.run_dir} is on the exact model")
        try:
            outside = outside_robot(args.outside, deployment.plant)
        except ValueError as exc:
            parser.error(f"--outside {args.outside}: {exc}")
        reasons = certified.contains(outside)
        if not reasons:
            parser.error(f"--outside {args.outside} ({outside.describe()}) lies inside the certified set: "
                         f"{certified.describe()}")  # fmt: skip
        robots = certified
    logs = args.logs or args.out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    out: dict[str, Any] = {
        "command": "npp-trial " + " ".join(sys.argv[1:] if argv is None else argv),
        "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
        "load_average_start": list(os.getloadavg()),
        "run": str(args.run_dir), "task": meta.task, "seed": meta.seed, "horizon": horizon,
        "control_period_ms": deployment.plant.dt * 1e3,
        "certificate": {k: certificate.record()[k] for k in ("epsilon", "p", "delta", "certify", "rule",
                                                             "policy_trajectories")},
        "policy": deployment.policy.kind,
        "robots": robots.describe() if robots is not None else MODEL,
    }  # fmt: skip
    if outside is not None:
        out["outside"] = {"spec": args.outside, "robot": outside.record(), "robot_words": outside.describe(),
                          "outside_reasons": reasons}  # fmt: skip
    rows: list[TrialEpisode] = []
    with reserved_domain() as env:
        executor = SingleThreadedExecutor()
        layout = JointLayout.of_plant(deployment.plant)
        node = TrialNode(layout) if outside is None else WatchingNode(layout)
        executor.add_node(node)
        try:
            if outside is not None:
                out["outside"] |= try_outside(executor, node, deployment, args.run_dir, outside, horizon, env, logs)
            else:
                rows = trial_episodes(executor, node, deployment, args, fingerprint, horizon, env, logs, robots)
        finally:
            executor.remove_node(node)
            node.destroy_node()
            executor.shutdown()
    out["load_average_end"] = list(os.getloadavg())
    if outside is not None:
        figures, tables = write_report(args.out, "trial", out, outside_markdown(out))
        log(f"wrote {figures} and {tables}")
        return 0
    out["summary"] = summary(rows, certificate.spec.epsilon)
    out["episodes"] = [asdict(r) | {"gap": r.gap} for r in rows]
    figures, tables = write_report(args.out, "trial", out, markdown(out))
    log(f"wrote {figures} and {tables}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
