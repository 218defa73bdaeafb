"""The certified Panda policy reaching targets over ros2_control, measured: npp-robot and npp-deploy as processes.

A certificate speaks of the policy's rollouts on the model; a deployment runs it through DDS in real time, where a
late command leaves the one before in force. This script measures both on the same starts:

- over DDS: ``npp-robot`` (examples/panda_reach/task.toml, real time, ``start_on_command``, its own description on
  /robot_description) and ``npp-deploy`` (the run, ``safe_effort:=gravity``, every other parameter its default: the
  gate, the watchdog, the coverage report) on a ROS_DOMAIN_ID of their own with localhost discovery. npp-deploy is
  configured and activated, and must say on /diagnostics that it waits for a target. Per reach: s0 from the run's
  held-out stream (npp-learn's, which no run drew from), npp-robot reset there (it holds the arm until the next
  command), s0's target on /npp_deploy/target (geometry_msgs/PointStamped in frame world), then /joint_states for
  the episode's 150 control steps of the robot's clock (by stamp), judged with the task's own success criterion on
  the states assembled as the task stores them;
- in process: the same starts rolled out on the model with the same certified policy (what the certificate is
  about).

Between reaches (``--between``): ``deactivate`` (default) deactivates npp-deploy before the reset and activates it
once the new target is taken, so the first command of a reach is the policy's answer to its s0 and its target;
``active`` keeps npp-deploy active and gives the new target before the reset (the arm moves toward it from where the
last reach ended until the reset; a command in flight at the reset may become the reach's first).

    .venv/bin/python scripts/panda_deploy_trial.py --run runs/panda/success-s3 --reaches 20 \\
        --out results/panda-reach/reach

Writes OUT/trial.json and OUT/trial.md; progress lines go to stdout, the nodes' logs to --logs.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Point, PointStamped
from lifecycle_msgs.srv import ChangeState
from npp_interfaces.srv import ResetRobot
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from npp_ros.bench.report import write_report
from npp_ros.deployment.joints import describe_point, stored_state
from npp_ros.run.held_out import LEARN_HELD_OUT_STREAM, held_out_states
from npp_ros.run.read import read_run
from npp_ros.tasks.rollout import rollout
from npp_ros.tasks.task_file.loader import target_origin
from npp_ros_graph.bench.ros_loop import interrupt_on_signals, reserved_domain, spawn, stop, wait_for
from npp_ros_graph.graph.description import parameter_args
from npp_ros_graph.runtime.diagnostics import DIAGNOSTICS, DIAGNOSTICS_QOS, Health, health_of
from npp_ros_graph.transport.topics import CONTROL_QOS, JOINT_STATES, SERVICE_QOS

TASK = "examples/panda_reach/task.toml"
DEPLOY, ROBOT = "/npp_deploy", "/npp_robot"
TARGET_TOPIC, TARGET_FRAME = "/npp_deploy/target", "world"  # npp-deploy's defaults
WAITING = f"active: waiting for a target on {TARGET_TOPIC}"
ANSWER_TIME = "answer time p50 / p99 (us)"
DEPLOY_COUNTS = ("answered", "refused states", "overtaken states", "repeated stamps", "clamped entries",
                 "outside coverage", "watchdog expiries")  # fmt: skip
ROBOT_COUNTS = ("steps", "steps on a held command", "overruns", "ignored commands", "resets", "refused resets")
START_TIMEOUT_S = 180.0  # processes importing rclpy and MuJoCo on a busy 2-core machine
CONFIGURE_TIMEOUT_S = 900.0  # the gate derives the run again at configure
STATUS_TIMEOUT_S = 30.0
WAIT_DRIFT_S = 1.0  # robot seconds watched while npp-deploy waits for its first target (safe_effort gravity)
# Every joint state of a reach is kept: the reach is judged on all of them.
KEEP_ALL = QoSProfile(depth=100_000, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)


def ns_of(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


@dataclass
class Reach:
    """One reach over DDS and the same start in process."""

    reach: int
    start: list[float]  # the stored s0 (the arm's 7 joints, the target, the velocities)
    target: list[float]  # the world point given to npp-deploy
    success: bool
    final_distance_m: float  # the hand's distance to the target in the episode's last stored state
    max_speed_last_s: float  # the hand's largest speed over the success window (m/s)
    in_process_success: bool
    in_process_final_distance_m: float
    first_command_answers_s0: bool  # the first applied command is the policy's answer to (s0, target)
    fresh_share: float  # steps whose applied command answered the state just before (the rest ran on a held one)
    steps: int  # the episode's steps judged: H - 1, after s0
    late_steps: int  # the episode's steps whose applied command was not the answer to the state before: late
    late_at: list[int]  # which steps (1 = the first command's)
    max_state_gap: float  # largest |robot state - in-process state| over the episode (rad, rad/s)
    answer_time_us: str  # npp-deploy's answer time p50 / p99 over this activation, from /diagnostics
    deploy_counts: dict[str, int] = field(default_factory=dict)  # npp-deploy's counters over the reach
    robot_counts: dict[str, int] = field(default_factory=dict)  # npp-robot's counters over the reach
    wall_s: float = 0.0  # from the reset's request to the episode's last state received


class TrialNode(Node):
    """This process's side: npp-deploy's lifecycle, npp-robot's reset, the target, the joint states, both nodes'
    /diagnostics."""

    def __init__(self) -> None:
        super().__init__("npp_panda_deploy_trial")
        self.change = self.create_client(ChangeState, f"{DEPLOY}/change_state", qos_profile=SERVICE_QOS)
        self.reset = self.create_client(ResetRobot, f"{ROBOT}/reset", qos_profile=SERVICE_QOS)
        self.target_pub = self.create_publisher(PointStamped, TARGET_TOPIC, CONTROL_QOS)
        self.states: list[tuple[int, JointState]] = []  # (stamp ns, message), in arrival order
        self.status: dict[str, tuple[int, Health]] = {}  # node -> (statuses seen, its latest)
        self.state_sub = self.create_subscription(JointState, JOINT_STATES, self.on_state, KEEP_ALL)
        self.create_subscription(DiagnosticArray, DIAGNOSTICS, self.on_diagnostics, DIAGNOSTICS_QOS)

    def on_state(self, msg: JointState) -> None:
        self.states.append((ns_of(msg.header.stamp), msg))

    def on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name in (DEPLOY, ROBOT):
                seen = self.status.get(status.name, (0, None))[0]
                self.status[status.name] = (seen + 1, health_of(status))

    def seen(self, name: str) -> int:
        return self.status.get(name, (0, None))[0]

    def latest(self, name: str) -> Health | None:
        return self.status.get(name, (0, None))[1]


class Trial:
    """The two processes and this process's node, driven reach by reach."""

    def __init__(self, args: argparse.Namespace, env: dict[str, str]) -> None:
        self.args, self.env = args, env
        self.executor = SingleThreadedExecutor()
        self.node = TrialNode()
        self.executor.add_node(self.node)
        self.procs: dict[str, Any] = {}

    # ------------------------------------------------------------------ processes
    def start(self, run_dir: Path) -> None:
        """npp-robot and npp-deploy as processes; npp-deploy configured (the gate) and activated, waiting."""
        logs = self.args.logs
        logs.mkdir(parents=True, exist_ok=True)
        robot = {"task": TASK, "start_on_command": True}
        deploy = {"run_dir": str(run_dir), "safe_effort": "gravity"}
        self.procs["npp-robot"] = spawn(["npp_ros_graph.nodes.robot", "--ros-args", *parameter_args(robot)], self.env,
                                        logs / "npp-robot.log")  # fmt: skip
        deploy_argv = ["npp_ros_graph.nodes.deploy.node", "--ros-args", *parameter_args(deploy)]
        self.procs["npp-deploy"] = spawn(deploy_argv, self.env, logs / "npp-deploy.log")
        self.wait(lambda: self.node.reset.service_is_ready(), START_TIMEOUT_S, "npp-robot's reset service")
        self.wait(lambda: self.node.change.service_is_ready(), START_TIMEOUT_S, "npp-deploy's lifecycle services")
        started = time.monotonic()
        self.transition("configure", CONFIGURE_TIMEOUT_S)
        self.configure_s = time.monotonic() - started
        self.wait(lambda: self.node.target_pub.get_subscription_count() > 0, 60.0, "npp-deploy's target subscription")
        self.transition("activate")

    def wait(self, done: Any, timeout: float, what: str) -> None:
        for name, proc in self.procs.items():
            if proc.poll() is not None:
                raise RuntimeError(f"{name} stopped (exit {proc.returncode}); see {self.args.logs / (name + '.log')}")
        if not wait_for(self.executor, lambda: done() or any(p.poll() is not None for p in self.procs.values()),
                        timeout):  # fmt: skip
            raise RuntimeError(f"no {what} within {timeout:.0f} s; see {self.args.logs}")
        for name, proc in self.procs.items():
            if proc.poll() is not None:
                raise RuntimeError(f"{name} stopped (exit {proc.returncode}); see {self.args.logs / (name + '.log')}")

    def transition(self, label: str, timeout: float = 60.0) -> None:
        request = ChangeState.Request()
        request.transition.label = label
        future = self.node.change.call_async(request)
        self.wait(future.done, timeout, f"answer to npp-deploy's {label}")
        if not future.result().success:
            health = self.node.latest(DEPLOY)
            raise RuntimeError(f"npp-deploy refused {label}: {health.doing if health else '?'}")

    def status(self, name: str, holds: Any, what: str, timeout: float = STATUS_TIMEOUT_S) -> Health:
        """The first status of ``name`` published from now on for which ``holds`` is true."""
        since = self.node.seen(name)
        found: list[Health] = []

        def seen() -> bool:
            health = self.node.latest(name)
            if self.node.seen(name) > since and health is not None and holds(health):
                found.append(health)
                return True
            return False

        self.wait(seen, timeout, f"status of {name} where {what} (last: {self.node.latest(name)})")
        return found[0]

    def close(self) -> None:
        """npp-deploy deactivated (its safe command), then both processes stopped by SIGTERM."""
        try:
            if "npp-deploy" in self.procs and self.procs["npp-deploy"].poll() is None:
                health = self.node.latest(DEPLOY)
                if health is not None and health.doing.startswith("active"):
                    self.transition("deactivate", 10.0)
        except Exception as exc:  # stopping anyway
            print(f"npp-deploy's deactivate at exit: {exc}", file=sys.stderr)
        finally:
            for name in ("npp-deploy", "npp-robot"):
                if name in self.procs:
                    stop(self.procs[name])
            self.executor.remove_node(self.node)
            self.node.destroy_node()
            self.executor.shutdown()


def counts(health: Health | None, names: tuple[str, ...]) -> dict[str, int]:
    values = {} if health is None else health.values
    return {name: int(str(values[name])) for name in names if name in values}


def difference(after: dict[str, int], before: dict[str, int]) -> dict[str, int]:
    return {name: value - before.get(name, 0) for name, value in after.items()}


def load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


class Judge:
    """A run's task, plant and policy: the robot's joint states assembled as the task stores states, and judged."""

    def __init__(self, run_dir: Path) -> None:
        run = read_run(run_dir)
        self.run, self.task, self.seed = run, run.task, int(run.metadata.seed)
        self.horizon = int(run.metadata.horizon)
        self.plant = self.task.make_plant(self.seed)
        self.policy = run.policy
        self.success = self.task.success
        definition = self.task.definition  # a task file's task (the Panda's reach)
        self.origin = target_origin(self.plant)
        names = list(self.plant.joint_names)
        self.names = names
        self.targets = [names.index(n) for n in definition.target_joints]
        self.arm = [n for n in names if n not in definition.target_joints]
        self.actuated = list(self.plant.actuated_joint_names)
        self.low, self.high = np.asarray(self.plant.action_low), np.asarray(self.plant.action_high)

    def target_point(self, s0: np.ndarray) -> np.ndarray:
        """The world point of s0's target: its joints' positions plus the target's origin."""
        return s0[self.targets] + self.origin

    def stored(self, msg: JointState, s0: np.ndarray) -> np.ndarray:
        """[qpos, qvel] in the task's order: the arm's joints by name from the joint state, the target's from s0,
        the target at rest; then as the task stores it (npp_ros.deployment.joints.stored_state)."""
        n = len(self.names)
        raw = np.zeros(2 * n)
        where = {name: i for i, name in enumerate(msg.name)}
        for i, name in enumerate(self.names):
            if i in self.targets:
                raw[i] = s0[i]
            else:
                raw[i], raw[n + i] = msg.position[where[name]], msg.velocity[where[name]]
        return stored_state(self.plant, raw)

    def effort(self, msg: JointState) -> np.ndarray:
        where = {name: i for i, name in enumerate(msg.name)}
        return np.array([msg.effort[where[name]] for name in self.actuated])

    def answer(self, state: np.ndarray) -> np.ndarray:
        """The policy's command for a state, clamped to the actuators' range as npp-deploy clamps it."""
        return np.clip(np.asarray(self.policy.act(state), dtype=np.float64), self.low, self.high)

    def distances(self, states: np.ndarray) -> np.ndarray:
        assert self.success is not None
        return self.success.holds.bands[0].values(states)

    def speeds(self, states: np.ndarray) -> np.ndarray:
        assert self.success is not None
        return self.success.holds.bands[1].values(states)


def episode(trial: Trial, judge: Judge, k: int, s0: np.ndarray, reference: Any) -> Reach:
    """One reach: the reset, the target, the episode's joint states by stamp, judged."""
    node, args = trial.node, trial.args
    dt_ns = round(judge.plant.dt * 1e9)
    point = judge.target_point(s0)
    words = f"{describe_point(point)} in {TARGET_FRAME}"  # as npp-deploy says a target it took
    started = time.monotonic()
    before_deploy = counts(node.latest(DEPLOY), DEPLOY_COUNTS)
    before_robot = counts(node.latest(ROBOT), ROBOT_COUNTS)
    if args.between == "deactivate":
        trial.transition("deactivate")
        time.sleep(0.05)  # the safe command deactivate sent is applied before the reset, never after it
        reset_stamp = reset(trial, s0)
        aim(trial, point, words)
        trial.transition("activate")
    else:
        aim(trial, point, words)
        reset_stamp = reset(trial, s0)
    steps = judge.horizon - 1  # the stored states are s0 and the states after the first H - 1 steps

    def stepped() -> list[tuple[int, JointState]]:
        return [(ns, msg) for ns, msg in node.states if ns > reset_stamp]

    trial.wait(lambda: (lambda s: bool(s) and s[-1][0] - s[0][0] >= (steps - 1) * dt_ns)(stepped()),
               60.0 + 4 * judge.horizon * judge.plant.dt, f"reach {k}'s {steps} steps")  # fmt: skip
    wall = time.monotonic() - started
    after = stepped()
    first = after[0][0]
    by_step: dict[int, JointState] = {}
    for ns, msg in after:
        index = 1 + round((ns - first) / dt_ns)
        if index <= steps:
            by_step[index] = msg
    missing = [i for i in range(1, steps + 1) if i not in by_step]
    if missing:
        raise RuntimeError(f"reach {k}: no joint state for steps {missing[:5]}... of the robot's clock")
    states = np.array([s0] + [judge.stored(by_step[i], s0) for i in range(1, steps + 1)])
    applied = [judge.effort(by_step[i]) for i in range(1, steps + 1)]
    fresh = [np.array_equal(judge.answer(states[i - 1]), applied[i - 1]) for i in range(1, steps + 1)]
    assert judge.success is not None
    window = judge.success.window(len(states))
    health = trial.status(DEPLOY, lambda h: ANSWER_TIME in h.values, "the answer time is given")
    robot_health = trial.status(ROBOT, lambda h: True, "any")
    node.states = [(ns, msg) for ns, msg in node.states if ns > after[-1][0]]  # what is judged is let go
    return Reach(
        reach=k, start=s0.tolist(), target=point.tolist(), success=bool(judge.success.met(states)),
        final_distance_m=float(judge.distances(states[-1:])[0]),
        max_speed_last_s=float(judge.speeds(states[-window:]).max()),
        in_process_success=bool(judge.success.met(reference.states)),
        in_process_final_distance_m=float(judge.distances(reference.states[-1:])[0]),
        first_command_answers_s0=bool(fresh[0]), fresh_share=float(np.mean(fresh)), steps=steps,
        late_steps=steps - sum(fresh), late_at=[i + 1 for i, f in enumerate(fresh) if not f],
        max_state_gap=float(np.max(np.abs(states - reference.states))),
        answer_time_us=str(health.values[ANSWER_TIME]),
        deploy_counts=difference(counts(health, DEPLOY_COUNTS), before_deploy),
        robot_counts=difference(counts(robot_health, ROBOT_COUNTS), before_robot), wall_s=wall,
    )  # fmt: skip


def reset(trial: Trial, s0: np.ndarray) -> int:
    """npp-robot at s0, held until the next command; the stamp of its measurement (ns)."""
    future = trial.node.reset.call_async(ResetRobot.Request(state=[float(x) for x in s0]))
    trial.wait(future.done, 30.0, "answer to npp-robot's reset")
    answer = future.result()
    if not answer.success:
        raise RuntimeError(f"npp-robot refused the reset: {answer.message}")
    if not np.array_equal(np.asarray(answer.state), s0):
        raise RuntimeError(f"npp-robot reset to {list(answer.state)}, not the start asked for")
    return ns_of(answer.stamp)


def aim(trial: Trial, point: np.ndarray, words: str) -> None:
    """The target on npp-deploy's topic (again every second) until its /diagnostics show it taken."""
    msg = PointStamped(point=Point(x=float(point[0]), y=float(point[1]), z=float(point[2])))
    msg.header.frame_id = TARGET_FRAME
    end = time.monotonic() + STATUS_TIMEOUT_S
    while True:
        msg.header.stamp = trial.node.get_clock().now().to_msg()
        trial.node.target_pub.publish(msg)
        try:
            trial.status(DEPLOY, lambda h: h.values.get("target") == words, f"the target {words} is taken", 1.0)
            return
        except RuntimeError:
            if time.monotonic() > end:
                raise


def wait_for_a_target(trial: Trial, judge: Judge) -> dict[str, Any]:
    """After activation: /diagnostics says npp-deploy waits for a target, its watchdog's safe command (the gravity
    torques) goes out, and the arm, at npp-robot's own start, is watched for WAIT_DRIFT_S robot seconds."""
    health = trial.status(DEPLOY, lambda h: h.doing == WAITING, "it waits for a target")
    health = trial.status(DEPLOY, lambda h: int(str(h.values.get("watchdog expiries", 0))) >= 1, "the safe command")
    node = trial.node
    since = len(node.states)
    trial.wait(lambda: len(node.states) > since and node.states[-1][0] - node.states[since][0] >= WAIT_DRIFT_S * 1e9,
               30.0, "the arm's joint states while npp-deploy waits")  # fmt: skip
    watched = node.states[since:]
    positions = np.array([[m.position[list(m.name).index(n)] for n in judge.arm] for _, m in watched])
    return {"status": health.doing, "level": health.level, "target": health.values.get("target"),
            "watchdog_expiries": int(str(health.values.get("watchdog expiries", 0))),
            "watched_s": (watched[-1][0] - watched[0][0]) * 1e-9,
            "largest_joint_drift_rad": float(np.max(np.abs(positions - positions[0])))}  # fmt: skip


def summary(reaches: list[Reach]) -> dict[str, Any]:
    def spread(values: list[float]) -> dict[str, float]:
        return {"median": statistics.median(values), "min": min(values), "max": max(values)} if values else {}

    answer = [tuple(float(x) for x in r.answer_time_us.split("/")) for r in reaches]
    robot_totals = {name: sum(r.robot_counts.get(name, 0) for r in reaches) for name in ROBOT_COUNTS}
    deploy_totals = {name: sum(r.deploy_counts.get(name, 0) for r in reaches) for name in DEPLOY_COUNTS}
    return {
        "reaches": len(reaches),
        "succeeded": sum(r.success for r in reaches),
        "in_process_succeeded": sum(r.in_process_success for r in reaches),
        "final_distance_mm": spread([r.final_distance_m * 1e3 for r in reaches]),
        "in_process_final_distance_mm": spread([r.in_process_final_distance_m * 1e3 for r in reaches]),
        "max_speed_last_s_mm_s": spread([r.max_speed_last_s * 1e3 for r in reaches]),
        "first_command_answers_s0": sum(r.first_command_answers_s0 for r in reaches),
        "fresh_share": spread([r.fresh_share for r in reaches]),
        "late_steps": sum(r.late_steps for r in reaches),
        "steps_judged": sum(r.steps for r in reaches),
        "reaches_identical_to_in_process": sum(r.max_state_gap == 0.0 for r in reaches),
        "answer_time_p50_us": spread([a[0] for a in answer]),
        "answer_time_p99_us": spread([a[1] for a in answer]),
        "deploy_counts": deploy_totals,
        "robot_counts": robot_totals,
    }


def markdown(out: dict[str, Any]) -> str:
    s, w = out["summary"], out["waiting"]
    lines = [
        f"# The certified Panda policy reaching targets over DDS: {out['run']}",
        "",
        f"Command: `{out['command']}` ({out['date']}; load average {out['load_average_start']} at the start, "
        f"{out['load_average_end']} at the end; {os.cpu_count()} cores shared with other jobs).",
        "",
        f"npp-robot (real time, `start_on_command`, its own description) and npp-deploy (`safe_effort:=gravity`, "
        f"every other parameter its default) as processes over DDS; between reaches: `{out['between']}`. "
        f"Configure (the gate, the run derived again) took {out['configure_s']:.1f} s.",
        "",
        f"Before the first target: /diagnostics said `{w['status']}` (target `{w['target']}`); the watchdog's safe "
        f"command (the gravity torques) held the arm, which moved at most {w['largest_joint_drift_rad']:.2g} rad in "
        f"any joint over {w['watched_s']:.2f} s of the robot's clock.",
        "",
        "| | over DDS, real time | in process (the certificate's rollouts) |",
        "|---|---|---|",
        f"| success | {s['succeeded']} of {s['reaches']} | {s['in_process_succeeded']} of {s['reaches']} |",
        f"| final distance median / max (mm) | {s['final_distance_mm']['median']:.1f} / "
        f"{s['final_distance_mm']['max']:.1f} | {s['in_process_final_distance_mm']['median']:.1f} / "
        f"{s['in_process_final_distance_mm']['max']:.1f} |",
        "",
        f"- Hand's largest speed over the last 0.5 s: median {s['max_speed_last_s_mm_s']['median']:.1f} mm/s, max "
        f"{s['max_speed_last_s_mm_s']['max']:.1f} mm/s.",
        f"- The first command was the policy's answer to (s0, target) in {s['first_command_answers_s0']} of "
        f"{s['reaches']} reaches; the share of steps whose applied command answered the state just before: median "
        f"{s['fresh_share']['median']:.3f} (min {s['fresh_share']['min']:.3f}); late commands (a step that ran on the "
        f"command before): {s['late_steps']} of {s['steps_judged']} steps; reaches whose 150 states equal the "
        f"in-process rollout's exactly: {s['reaches_identical_to_in_process']} of {s['reaches']}.",
        f"- npp-deploy's answer time per reach (its /diagnostics, over each activation): p50 median "
        f"{s['answer_time_p50_us']['median']:.0f} us (max {s['answer_time_p50_us']['max']:.0f}), p99 median "
        f"{s['answer_time_p99_us']['median']:.0f} us (max {s['answer_time_p99_us']['max']:.0f}).",
        "- npp-deploy's counts over the reaches: " + ", ".join(f"{k} {v}" for k, v in s["deploy_counts"].items()) + ".",
        "- npp-robot's counts from the first reset to the last reach's end (its /diagnostics; its steps on a held "
        "command include those between reaches, when the deactivated npp-deploy's safe command holds the arm): "
        + ", ".join(f"{k} {v}" for k, v in s["robot_counts"].items())
        + ".",
        "",
        "| reach | target (m) | success | final distance (mm) | max speed last 0.5 s (mm/s) | in process | "
        "in-process distance (mm) | late steps | answer p50 / p99 (us) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in out["reaches"]:
        target = ", ".join(f"{x:.3f}" for x in r["target"])
        lines.append(
            f"| {r['reach']} | ({target}) | {'yes' if r['success'] else 'no'} | {r['final_distance_m'] * 1e3:.1f} | "
            f"{r['max_speed_last_s'] * 1e3:.1f} | {'yes' if r['in_process_success'] else 'no'} | "
            f"{r['in_process_final_distance_m'] * 1e3:.1f} | {r['late_steps']} | {r['answer_time_us']} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog=__doc__.split("\n\n", 1)[1])  # fmt: skip
    parser.add_argument("--run", type=Path, default=Path("runs/panda/success-s3"), help="the certified run folder")
    parser.add_argument("--reaches", type=int, default=20, help="reaches, each from a held-out s0 of the run")
    parser.add_argument("--between", choices=("deactivate", "active"), default="deactivate",
                        help="between reaches: deactivate npp-deploy for the reset and the target (default), or keep "
                        "it active and give the target before the reset")  # fmt: skip
    parser.add_argument("--logs", type=Path, default=None, help="the nodes' logs (default runs/panda-deploy-trial/"
                        "RUN_NAME-logs)")  # fmt: skip
    parser.add_argument("--out", type=Path, default=Path("results/panda-reach/reach"),
                        help="writes OUT/trial.json and OUT/trial.md")  # fmt: skip
    args = parser.parse_args(argv)
    args.logs = args.logs or Path("runs/panda-deploy-trial") / f"{args.run.name}-logs"
    command = "scripts/panda_deploy_trial.py " + " ".join(sys.argv[1:] if argv is None else argv)
    out: dict[str, Any] = {"command": command, "run": str(args.run), "between": args.between,
                           "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
                           "load_average_start": load()}  # fmt: skip
    judge = Judge(args.run)
    starts = held_out_states(judge.task, judge.seed, args.reaches, LEARN_HELD_OUT_STREAM)
    references = [rollout(judge.plant, judge.policy.controller(), s0, judge.horizon) for s0 in starts]
    assert judge.success is not None
    print(f"in process: {sum(bool(judge.success.met(r.states)) for r in references)} of {len(starts)} reached "
          f"(the certified policy on the model)", flush=True)  # fmt: skip
    reaches: list[Reach] = []
    with reserved_domain() as env:
        interrupt_on_signals()  # the nodes are deactivated before they are stopped
        trial = Trial(args, env)
        try:
            trial.start(args.run.resolve())
            out["configure_s"] = trial.configure_s
            out["waiting"] = wait_for_a_target(trial, judge)
            print(f"npp-deploy configured in {trial.configure_s:.1f} s: {out['waiting']['status']}", flush=True)
            for k, (s0, reference) in enumerate(zip(starts, references, strict=True), start=1):
                r = episode(trial, judge, k, s0, reference)
                reaches.append(r)
                print(f"reach {k}/{len(starts)}: {'success' if r.success else 'FAILED'}, "
                      f"{r.final_distance_m * 1e3:.1f} mm (in process {r.in_process_final_distance_m * 1e3:.1f} mm), "
                      f"fresh {r.fresh_share:.3f}, answer {r.answer_time_us} us", flush=True)  # fmt: skip
        except KeyboardInterrupt:
            print("interrupted: stopping the nodes", file=sys.stderr)
            return 130
        finally:
            trial.close()
    out["load_average_end"] = load()
    out["summary"] = summary(reaches)
    out["reaches"] = [asdict(r) for r in reaches]
    write_report(args.out, "trial", out, markdown(out))
    s = out["summary"]
    print(f"over DDS {s['succeeded']} of {s['reaches']}, in process {s['in_process_succeeded']} of {s['reaches']}; "
          f"wrote {args.out / 'trial.md'}", flush=True)  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
