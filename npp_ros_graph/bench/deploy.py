"""npp-bench-deploy: npp-deploy's latency from a joint state to its command, the watchdog's reaction time, and
the state period's jitter as npp-deploy sees it.

For each built-in case (lqr_2_1 with 10^5 points, lqr_6_2 with 10^6) the core loop stores a run of real LQR
expert trajectories (``certify=surrogate`` with a tiny epsilon, so every episode asks the expert and
the run never certifies); npp-deploy, as its own process, deploys it with ``override_gate`` (logged:
the gate is not what is measured here; the coverage check runs with a radius nothing exceeds). ``--case-run
RUN_DIR ...`` adds a case per run folder (its task and seed read from the run): a certified run whose plant
fingerprint is its task's own model is deployed through the gate, as a user deploys it (npp-deploy's defaults but
``state_timeout``); any other with ``override_gate``, and the report says which. ``--only-runs`` leaves the
built-in cases out. npp-deploy drives this process, which plays the robot in lockstep:
it publishes a sensor_msgs/JointState on /joint_states (the robot's own joints: a target's are in none),
waits for the Float64MultiArray command, steps the task's MuJoCo plant with it and publishes the next state (a new
s0 ~ rho every H steps, the run's horizon). For a task whose state holds a target (a task file's
``state.target``), each new s0's target part goes, as a world point, to npp-deploy's target topic before the
episode's first state, and the episode starts once npp-deploy's /diagnostics shows it taken.

Measured:
- round trip: from publishing a joint state to receiving its command here (both DDS hops, the
  node's assembly, query, clamp and publish), p50 and p99 over ``--states`` states;
- the node's own answer time (its callback's start to its publish), p50 and p99 of its last 1,000
  answers, as npp-deploy reports them on /diagnostics;
- the watchdog: ``--stops`` times, states at the control rate for 0.5 s and then none; the time from
  the last state published to the safe command received, against ``state_timeout``;
- the state period: npp-robot, as its own process, publishes the task's joint states in real time (one
  per control period; for a target task this process gives npp-deploy the target npp-robot simulates) and
  npp-deploy answers ``--periods`` of them; the interval between two joint states
  as npp-deploy takes them, median, p99 and max, as npp-deploy reports them on /diagnostics (its last
  1,000 intervals). This is the figure ``state_timeout`` must stay above.

Every run gets its own ROS_DOMAIN_ID and localhost-only discovery. ``--out DIR`` writes DIR/bench.json
and DIR/bench.md with the command, the date and the load average.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Point, PointStamped
from lifecycle_msgs.srv import ChangeState
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from npp_ros.bench.report import write_report
from npp_ros.deployment.joints import JointLayout, describe_point
from npp_ros.deployment.timing import percentiles
from npp_ros.run.read import read_run
from npp_ros.run.request import RunRequest, resolve_run
from npp_ros.run.setup import build_loop, plant_fingerprint
from npp_ros.tasks.registry import Task, get_task
from npp_ros_graph.bench.ros_loop import reserved_domain, spawn, stop, wait_for
from npp_ros_graph.runtime.diagnostics import DIAGNOSTICS, DIAGNOSTICS_QOS, health_of
from npp_ros_graph.transport.convert import float64_array, stamp
from npp_ros_graph.transport.topics import CONTROL_QOS, FORWARD_COMMANDS, JOINT_STATES, SERVICE_QOS

CASES = (("lqr_2_1", 100), ("lqr_6_2", 1000))  # (task, trajectories of H = 1000): 10^5 and 10^6 points
HORIZON = 1000
STATE_TIMEOUT_S = 0.1
STATE_PERIOD = "state period p50 / p99 / max (ms)"  # npp-deploy's /diagnostics values, over its last 1,000
STATE_PERIODS = "state periods measured"
ANSWER_TIME = "answer time p50 / p99 (us)"
TARGET_TOPIC, TARGET_FRAME = "/npp_deploy/target", "world"  # npp-deploy's defaults (~/target, world)
TARGET_TIMEOUT_S = 30.0  # for npp-deploy to show a target taken; the target goes out again every second until then
CONFIGURE_TIMEOUT_S = 1800.0  # a certified run is derived again at configure (rederive): minutes on a long run


def log(text: str) -> None:
    sys.stderr.write(f"npp-bench-deploy: {text}\n")
    sys.stderr.flush()


def make_run(task: str, trajectories: int, folder: Path) -> Path:
    """A run of ``trajectories`` expert trajectories, stored by the core loop (uncertified: epsilon is tiny)."""
    if (folder / "run.sqlite").exists():
        return folder  # made by an earlier bench run: the same seed gives the same data
    run = resolve_run(RunRequest(task=task, lipschitz="analytic", epsilon=1e-9, horizon=HORIZON, certify="surrogate"))
    loop = build_loop(run.config, run.expert, store_path=folder / "run.sqlite")
    try:
        loop.run(trajectories)
    finally:
        assert loop.store is not None
        loop.store.close()
    return folder


@dataclass(frozen=True)
class Case:
    """One deployment measured: the run npp-deploy loads, the task and seed the bench's robot plays, and how
    npp-deploy was told to deploy it."""

    label: str  # the report's name for it: the task, or the run folder and its task
    slug: str  # its log files' name
    task: Task
    task_ref: str  # the task as get_task and npp-robot's task parameter take it (a task file's path)
    seed: int
    horizon: int  # the states between two resets: the run's own horizon
    points: int  # the data points of the policy npp-deploy acts with
    params: dict[str, str]  # npp-deploy's parameters
    gate: bool  # deployed through the gate (not override_gate)
    deployed: str  # how, in words
    given: str = ""  # a run folder as given on the command line


def built_in_case(task: str, trajectories: int, runs: Path) -> Case:
    """lqr_2_1 or lqr_6_2 over a run of expert trajectories this bench stores, deployed with override_gate."""
    started = time.perf_counter()
    run = make_run(task, trajectories, runs / f"{task}-{trajectories}")
    log(f"{task}: run of {trajectories} trajectories ready in {time.perf_counter() - started:.0f} s ({run})")
    params = {"run_dir": str(run), "robot_model_fingerprint": plant_fingerprint(task, 0), "override_gate": "true",
              "state_timeout": repr(STATE_TIMEOUT_S), "coverage_radius": "100.0"}  # fmt: skip
    deployed = "override_gate: a stored run of LQR expert trajectories, uncertified (the gate is not measured)"
    return Case(task, task, get_task(task), task, 0, HORIZON, trajectories * HORIZON, params, False, deployed)


def task_label(task: Task) -> str:
    """A task's own name: a task file's ``name``, not its path."""
    definition = getattr(task, "definition", None)
    return str(definition.label) if definition is not None else task.name


def run_case(folder: Path) -> Case:
    """A run folder's case, its task and seed read from the run: through the gate (npp-deploy's defaults but
    state_timeout) when it is certified and its data's plant is its task's own model; with override_gate, the
    reasons said, otherwise. Its points are those of the certified policy (of all the data, uncertified)."""
    run = read_run(folder)
    seed, ref = int(run.metadata.seed), str(run.metadata.task)
    fingerprint = plant_fingerprint(ref, seed)
    certificate = run.certificate
    count = run.dataset.num_trajectories if certificate is None else certificate.policy_trajectories
    points = int(run.dataset.trajectory_offsets[count])
    reasons = [] if certificate is not None else ["the run holds no certificate"]
    recorded = str(run.metadata.plant_fingerprint)
    if recorded != fingerprint:
        reasons.append(f"its data's plant ({recorded[:12]}...) is not its task's model ({fingerprint[:12]}...)")
    params = {"run_dir": str(run.folder.resolve()), "robot_model_fingerprint": fingerprint,
              "state_timeout": repr(STATE_TIMEOUT_S)}  # fmt: skip
    if reasons:
        params |= {"override_gate": "true", "coverage_radius": "100.0"}
        deployed = f"override_gate: {'; '.join(reasons)}"
    else:
        spec = run.spec
        claim = f"{run.metadata.certify}, p {spec.p:g}, delta {spec.delta:g}"
        used = f"{count} of {run.dataset.num_trajectories} trajectories"
        deployed = f"through the gate: certified ({claim}, {used}), its plant its task's own model"
    label = f"{run.folder.name} ({task_label(run.task)})"
    horizon = int(run.metadata.horizon)
    return Case(
        label, run.folder.name, run.task, ref, seed, horizon, points, params, not reasons, deployed, str(folder)
    )


def ros_args(params: dict[str, str]) -> list[str]:
    return ["--ros-args", *(arg for name, value in params.items() for arg in ("-p", f"{name}:={value}"))]


class Robot(Node):
    """This process's side: the robot in lockstep (its own joints only), the target of a task whose state holds
    one, and npp-deploy's lifecycle and /diagnostics."""

    def __init__(self, task: Task, seed: int) -> None:
        super().__init__("npp_bench_robot")
        self.task, self.seed = task, seed
        self.plant = task.make_plant(seed)
        layout = JointLayout.of_plant(self.plant)
        model = self.plant.physics.model
        self.names = list(layout.measured)  # what a robot measures: never a target's joints
        self.qpos = np.array([model.jnt_qposadr[model.joint(n).id] for n in self.names], dtype=np.intp)
        self.qvel = np.array([model.jnt_dofadr[model.joint(n).id] for n in self.names], dtype=np.intp)
        self.box = layout.target
        self.target_entries = [] if self.box is None else [self.plant.joint_names.index(n) for n in self.box.joints]
        self.state_pub = self.create_publisher(JointState, JOINT_STATES, CONTROL_QOS)
        self.target_pub = None if self.box is None else self.create_publisher(PointStamped, TARGET_TOPIC, CONTROL_QOS)
        self.create_subscription(Float64MultiArray, FORWARD_COMMANDS, self.on_command, CONTROL_QOS)
        self.create_subscription(DiagnosticArray, DIAGNOSTICS, self.on_diagnostics, DIAGNOSTICS_QOS)
        self.change = self.create_client(ChangeState, "/npp_deploy/change_state", qos_profile=SERVICE_QOS)
        self.command: tuple[float, list[float]] | None = None
        self.health: Any = None
        self.statuses = 0
        self.sent = 0
        self.target = ""  # the target npp-deploy took last, in its /diagnostics words
        self.targets = 0  # targets given and taken

    def on_command(self, msg: Float64MultiArray) -> None:
        self.command = (time.perf_counter(), list(msg.data))

    def on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name == "/npp_deploy":
                self.health = health_of(status)
                self.statuses += 1

    def start(self, executor: SingleThreadedExecutor, s0: np.ndarray) -> None:
        """The plant reset to ``s0``; for a target task, npp-deploy given s0's target first (:meth:`aim`)."""
        self.plant.reset(s0)
        self.aim(executor, s0)

    def aim(self, executor: SingleThreadedExecutor, s0: np.ndarray) -> None:
        """For a task whose state holds a target: s0's target part, as a world point, on npp-deploy's target
        topic (again every second) until its /diagnostics show it taken; nothing for another task."""
        if self.box is None or self.target_pub is None:
            return
        point = self.box.point(np.asarray(s0, dtype=np.float64)[self.target_entries])
        words = f"{describe_point(self.box.point(self.box.coordinates(point)))} in {TARGET_FRAME}"  # as npp-deploy
        if words == self.target:
            return
        publisher = self.target_pub
        if not wait_for(executor, lambda: publisher.get_subscription_count() > 0, TARGET_TIMEOUT_S):
            raise RuntimeError(f"npp-deploy does not listen on {TARGET_TOPIC}")
        msg = PointStamped(point=Point(x=float(point[0]), y=float(point[1]), z=float(point[2])))
        msg.header.frame_id = TARGET_FRAME
        end = time.monotonic() + TARGET_TIMEOUT_S
        while True:
            msg.header.stamp = self.get_clock().now().to_msg()
            publisher.publish(msg)
            if wait_for(executor, lambda: self.health is not None and self.health.values.get("target") == words, 1.0):
                break
            if time.monotonic() > end:
                error = self.health.error if self.health is not None else "no /diagnostics"
                raise RuntimeError(f"npp-deploy did not take the target {words} within {TARGET_TIMEOUT_S:g} s: {error}")
        self.target = words
        self.targets += 1

    def publish(self) -> float:
        """The plant's state as the robot's joint state, with a new stamp; returns when it went out."""
        self.sent += 1
        data = self.plant.physics.data
        msg = JointState(name=self.names, position=float64_array(data.qpos[self.qpos]),
                         velocity=float64_array(data.qvel[self.qvel]))  # fmt: skip
        msg.header.stamp = stamp(self.sent * 1_000_000)
        self.command = None
        at = time.perf_counter()
        self.state_pub.publish(msg)
        return at


def transition(executor: SingleThreadedExecutor, robot: Robot, label: str, timeout: float) -> None:
    if not wait_for(executor, robot.change.service_is_ready, timeout):
        raise RuntimeError("npp-deploy's lifecycle services did not appear")
    request = ChangeState.Request()
    request.transition.label = label
    future = robot.change.call_async(request)
    if not wait_for(executor, future.done, timeout) or not future.result().success:
        raise RuntimeError(f"npp-deploy refused {label}; see its log")


def round_trips(executor: SingleThreadedExecutor, robot: Robot, states: int, horizon: int) -> list[float]:
    """Lockstep: each state's time to its command (seconds); the plant steps with every command, from a new
    s0 ~ rho every ``horizon`` states."""
    rng = np.random.default_rng(1)
    latencies: list[float] = []
    while len(latencies) < states:
        robot.start(executor, robot.task.sample_initial_state(rng))
        for _ in range(min(horizon, states - len(latencies))):
            sent_at = robot.publish()
            # Its answer, not a safe command the watchdog sent while this answer was late (a busy machine).
            if not wait_for(executor, lambda: robot.command is not None and any(robot.command[1]), 60.0):
                raise RuntimeError(f"no command for state {robot.sent} within 60 s")
            assert robot.command is not None
            received_at, command = robot.command
            latencies.append(received_at - sent_at)
            robot.plant.step(np.asarray(command))
    return latencies


def watchdog_delays(executor: SingleThreadedExecutor, robot: Robot, stops: int) -> list[float]:
    """Times from the last state published to the safe command received (seconds)."""
    delays = []
    period = robot.plant.dt
    zero = [0.0] * robot.plant.action_dim
    for _ in range(stops):
        robot.start(executor, robot.task.initial_state(robot.seed, len(delays)))
        last = 0.0
        end = time.perf_counter() + 0.5
        while time.perf_counter() < end:  # states at the control rate, the commands applied
            last = robot.publish()
            wait_for(executor, lambda: robot.command is not None, 1.0)
            if robot.command is not None:
                robot.plant.step(np.asarray(robot.command[1]))
            pause = period - (time.perf_counter() - last)
            if pause > 0:
                time.sleep(pause)
        robot.command = None
        if not wait_for(executor, lambda: robot.command is not None and robot.command[1] == zero, 10.0):
            raise RuntimeError("no safe command within 10 s of the last state")
        assert robot.command is not None
        delays.append(robot.command[0] - last)
    return delays


def state_periods(
    executor: SingleThreadedExecutor, robot: Robot, case: Case, periods: int, env: dict[str, str], log_path: Path
) -> tuple[list[float], int]:
    """npp-robot in real time against the active npp-deploy: the state period's p50, p99 and max (seconds) over
    the intervals npp-deploy took, as it reports them, and how many intervals those are. npp-robot starts at the
    task's first s0 for the case's seed; for a target task npp-deploy is given that s0's target, the one npp-robot
    simulates, before it activates."""
    transition(executor, robot, "deactivate", 60.0)
    s0 = case.task.initial_state(case.seed, 0)
    robot.aim(executor, s0)
    # npp-deploy takes the model's fingerprint from its parameter here and reads no description; npp-robot publishes
    # the task's own MJCF unchecked (nominal: the model it runs, no robot of a set), since it refuses to start on a
    # task file whose model loads mesh files: the published text does not compile away from its folder.
    params = {"task": case.task_ref, "seed": str(case.seed), "initial_state": ",".join(repr(float(x)) for x in s0),
              "publish_description": "nominal"}  # fmt: skip
    proc = spawn(["npp_ros_graph.nodes.robot", *ros_args(params)], env, log_path)
    try:
        # The robot publishes from its start; npp-deploy measures from its activation on.
        if not wait_for(executor, lambda: proc.poll() is not None or robot.count_publishers(JOINT_STATES) >= 2, 120):
            raise RuntimeError(f"npp-robot's joint states did not appear; see {log_path}")
        transition(executor, robot, "activate", 60.0)
        wait_for(executor, lambda: proc.poll() is not None, periods * robot.plant.dt)
        if proc.poll() is not None:
            tail = log_path.read_text().strip().splitlines()[-1:]
            raise RuntimeError(f"npp-robot stopped (exit {proc.returncode}): {' '.join(tail)}; see {log_path}")
        seen = robot.statuses
        if not wait_for(executor, lambda: robot.statuses > seen and STATE_PERIOD in robot.health.values, 10.0):
            raise RuntimeError("npp-deploy reported no state period")
        health = robot.health
        transition(executor, robot, "deactivate", 60.0)
    finally:
        stop(proc)
    figures = [float(x) * 1e-3 for x in str(health.values[STATE_PERIOD]).split("/")]
    return figures, int(health.values[STATE_PERIODS])


NODE_COUNTERS = ("answered", "refused states", "overtaken states", "clamped entries", "outside coverage",
                 "watchdog expiries")  # fmt: skip


def measure_case(case: Case, args: argparse.Namespace, env: dict[str, str]) -> dict[str, Any]:
    log(f"{case.label}: {case.points:,d} points, deployed {case.deployed}")
    deploy_log = args.logs / f"deploy-{case.slug}.log"
    proc = spawn(["npp_ros_graph.nodes.deploy.node", *ros_args(case.params)], env, deploy_log)
    executor = SingleThreadedExecutor()
    robot = Robot(case.task, case.seed)
    executor.add_node(robot)
    try:
        started = time.perf_counter()
        transition(executor, robot, "configure", CONFIGURE_TIMEOUT_S)
        configure_s = time.perf_counter() - started
        transition(executor, robot, "activate", 60.0)
        wait_for(executor, lambda: robot.state_pub.get_subscription_count() > 0, 60.0)
        round_trips(executor, robot, 50, case.horizon)  # warm-up: the first queries compile and fill caches
        sent, targets = robot.sent, robot.targets
        latencies = round_trips(executor, robot, args.states, case.horizon)
        sent, targets = robot.sent - sent, robot.targets - targets
        robot.health = None
        wait_for(executor, lambda: robot.health is not None and ANSWER_TIME in robot.health.values, 5.0)
        values = robot.health.values if robot.health is not None else {}
        answer = values.get(ANSWER_TIME, "-")
        counters = {name: int(values[name]) for name in NODE_COUNTERS if name in values}
        delays = watchdog_delays(executor, robot, args.stops)
        (j50, j99, jmax), intervals = state_periods(executor, robot, case, args.periods, env,
                                                     args.logs / f"robot-{case.slug}.log")  # fmt: skip
    finally:
        stop(proc)
        executor.remove_node(robot)
        robot.destroy_node()
        executor.shutdown()
    p50, p99, pmax = (v * 1e6 for v in percentiles(latencies, (50, 99, 100)))
    w50, wmax = percentiles(delays, (50, 100))
    result = {
        "case": case.label, "task": task_label(case.task), "run": case.given or None, "seed": case.seed,
        "deployed": case.deployed, "gate": case.gate, "target": robot.box is not None, "horizon": case.horizon,
        "points": case.points, "state_dim": robot.plant.state_dim, "states": len(latencies),
        "states_sent": sent, "commands_received": len(latencies), "targets_given": targets,
        "round_trip_p50_us": p50, "round_trip_p99_us": p99, "round_trip_max_us": pmax,
        "node_answer_p50_p99_us": answer, "node_counters": counters,
        "configure_s": configure_s, "state_timeout_ms": STATE_TIMEOUT_S * 1e3, "stops": len(delays),
        "safe_command_after_last_state_ms": [d * 1e3 for d in delays], "safe_p50_ms": w50 * 1e3,
        "safe_max_ms": wmax * 1e3, "control_period_ms": robot.plant.dt * 1e3,
        "state_periods": intervals,
        "state_period_p50_ms": j50 * 1e3, "state_period_p99_ms": j99 * 1e3, "state_period_max_ms": jmax * 1e3,
    }  # fmt: skip
    log(f"{case.label} {case.points:,d} points: round trip p50 {p50:.0f} us, p99 {p99:.0f} us, max {pmax:.0f} us; "
        f"node {answer} us; safe command {w50 * 1e3:.1f} ms (max {wmax * 1e3:.1f}) after the last state, timeout "
        f"{STATE_TIMEOUT_S * 1e3:.0f} ms; state period {j50 * 1e3:.2f} / {j99 * 1e3:.2f} / {jmax * 1e3:.2f} ms "
        f"(p50 / p99 / max) against {robot.plant.dt * 1e3:g} ms")  # fmt: skip
    return result


def markdown(out: dict[str, Any]) -> str:
    lines = [
        "# npp-deploy: latency, watchdog and state period",
        "",
        f"Command: `{out['command']}` ({out['date']}; load average {out['load_average_start'][0]:.2f} at the start, "
        f"{out['load_average_end'][0]:.2f} at the end; {os.cpu_count()} cores shared with other jobs).",
        "",
        "npp-deploy, as its own process, deploys each case's run and answers a robot played by the bench in lockstep "
        "over DDS on this machine (a new s0 ~ rho every horizon states). How each run was deployed:",
        "",
    ]
    for r in out["cases"]:
        line = f"- {r['case']}: {r['deployed']}."
        if r["target"]:
            line += (f" Its state holds a target: the joint states list the robot's own joints, and before each "
                     f"episode's first state the bench gives npp-deploy s0's target on {TARGET_TOPIC} "
                     f"(geometry_msgs/PointStamped in frame {TARGET_FRAME}) and waits until npp-deploy shows it taken "
                     f"({r['targets_given']} targets over the states timed).")  # fmt: skip
        counters = r.get("node_counters") or {}
        if counters:
            line += (
                " npp-deploy's counts after the warm-up and the states timed: "
                + ", ".join(f"{name} {value:,d}" for name, value in counters.items())
                + "."
            )
        lines.append(line)
    lines += [
        "",
        "| case | points | states | commands | round trip p50 / p99 / max (us) | node answer p50 / p99 (us) | "
        "control period (ms) | configure (s) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in out["cases"]:
        lines.append(
            f"| {r['case']} ({r['state_dim']}-D) | {r['points']:,d} | {r['states']:,d} | "
            f"{r.get('commands_received', r['states']):,d} | {r['round_trip_p50_us']:.0f} / "
            f"{r['round_trip_p99_us']:.0f} / {r['round_trip_max_us']:.0f} | {r['node_answer_p50_p99_us']} | "
            f"{r['control_period_ms']:g} | {r['configure_s']:.1f} |"
        )
    lines += [
        "",
        "Round trip: from the joint state published to its command received (both DDS hops). Node answer: "
        "npp-deploy's own time from its callback's start to its publish, over its last 1,000 answers. Configure: "
        "npp-deploy's configure transition (for a run through the gate, its checks: the run derived again).",
        "",
        "| case | state_timeout (ms) | control period (ms) | stops | safe command after the last state, "
        "median / max (ms) |",
        "|---|---|---|---|---|",
    ]
    for r in out["cases"]:
        lines.append(
            f"| {r['case']} | {r['state_timeout_ms']:.0f} | {r['control_period_ms']:g} | {r['stops']} | "
            f"{r['safe_p50_ms']:.1f} / {r['safe_max_ms']:.1f} |"
        )
    lines += [
        "",
        "State period: npp-robot publishes joint states in real time, one per control period, and npp-deploy "
        "answers them; the interval between two joint states as npp-deploy takes them, over its last intervals "
        "(up to 1,000), as npp-deploy reports it on /diagnostics. For a target task npp-deploy is given the target "
        "npp-robot simulates.",
        "",
        "| case | control period (ms) | intervals | state period p50 / p99 / max (ms) |",
        "|---|---|---|---|",
    ]
    for r in out["cases"]:
        lines.append(
            f"| {r['case']} | {r['control_period_ms']:g} | {r['state_periods']:,d} | "
            f"{r['state_period_p50_ms']:.2f} / {r['state_period_p99_ms']:.2f} / {r['state_period_max_ms']:.2f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="npp-bench-deploy", description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="small runs and few states (a smoke run)")
    parser.add_argument("--states", type=int, default=5000, help="joint states timed per case")
    parser.add_argument("--stops", type=int, default=20, help="times the states stop, per case")
    parser.add_argument("--periods", type=int, default=1000, help="real-time joint states npp-deploy answers for "
                        "the state period, per case (it reports its last 1,000)")  # fmt: skip
    parser.add_argument("--case-run", type=Path, nargs="+", default=[], metavar="RUN_DIR",
                        help="a case per run folder, after the built-in ones: its task and seed read from the run, "
                        "its robot reset every horizon of the run; a certified run whose data's plant is its task's "
                        "own model is deployed through the gate, any other with override_gate (the report says "
                        "which). A task whose state holds a target is given one per s0 on npp-deploy's target "
                        "topic")  # fmt: skip
    parser.add_argument("--only-runs", action="store_true", help="only the --case-run cases: no built-in lqr case")
    parser.add_argument("--runs", type=Path, default=Path("runs/bench-deploy"), help="folder for the runs it stores")
    parser.add_argument("--logs", type=Path, default=None, help="folder for npp-deploy's logs")
    parser.add_argument("--out", type=Path, default=None, help="write OUT/bench.json and OUT/bench.md")
    args = parser.parse_args(argv)
    if args.only_runs and not args.case_run:
        parser.error("--only-runs needs --case-run RUN_DIR")
    built_in = [] if args.only_runs else [(task, 2 if args.quick else n) for task, n in CASES]
    if args.quick:
        args.states, args.stops, args.periods = min(args.states, 300), min(args.stops, 3), min(args.periods, 100)
    args.logs = args.logs or args.runs / "logs"
    args.logs.mkdir(parents=True, exist_ok=True)
    runs = [run_case(folder) for folder in args.case_run]  # before any node starts: a run that does not read stops here
    out: dict[str, Any] = {
        "command": "npp-bench-deploy " + " ".join(sys.argv[1:] if argv is None else argv),
        "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
        "load_average_start": list(os.getloadavg()),
    }
    with reserved_domain() as env:
        cases = [built_in_case(task, n, args.runs) for task, n in built_in] + runs
        out["cases"] = [measure_case(case, args, env) for case in cases]
    out["load_average_end"] = list(os.getloadavg())
    if args.out:
        figures, tables = write_report(args.out, "bench", out, markdown(out))
        log(f"wrote {figures} and {tables}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
