"""npp-bench-deploy: npp-deploy's latency from a joint state to its command, the watchdog's reaction time, and
the state period's jitter as npp-deploy sees it.

For each case (lqr_2_1 with 10^5 points, lqr_6_2 with 10^6) the core loop stores a run of real LQR
expert trajectories (``certify=surrogate`` with a tiny epsilon, so every episode asks the expert and
the run never certifies); npp-deploy, as its own process, deploys it with ``override_gate`` (logged:
the gate is not what is measured here; the coverage check runs with a radius nothing exceeds) and drives
this process, which plays the robot in lockstep:
it publishes a sensor_msgs/JointState on /joint_states, waits for the Float64MultiArray command,
steps the task's MuJoCo plant with it and publishes the next state (a new s0 ~ rho every H steps).

Measured:
- round trip: from publishing a joint state to receiving its command here (both DDS hops, the
  node's assembly, query, clamp and publish), p50 and p99 over ``--states`` states;
- the node's own answer time (its callback's start to its publish), p50 and p99 of its last 1,000
  answers, as npp-deploy reports them on /diagnostics;
- the watchdog: ``--stops`` times, states at the control rate for 0.5 s and then none; the time from
  the last state published to the safe command received, against ``state_timeout``;
- the state period: npp-robot, as its own process, publishes the task's joint states in real time (one
  per control period) and npp-deploy answers ``--periods`` of them; the interval between two joint states
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
from pathlib import Path
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from lifecycle_msgs.srv import ChangeState
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from npp_ros.bench.report import write_report
from npp_ros.deployment.timing import percentiles
from npp_ros.run.request import RunRequest, resolve_run
from npp_ros.run.setup import build_loop, plant_fingerprint
from npp_ros.tasks.registry import get_task
from npp_ros_graph.bench.loop import reserved_domain, spawn, stop, wait_for
from npp_ros_graph.runtime.diagnostics import DIAGNOSTICS, DIAGNOSTICS_QOS, health_of
from npp_ros_graph.transport.convert import float64_array, stamp
from npp_ros_graph.transport.topics import CONTROL_QOS, FORWARD_COMMANDS, JOINT_STATES, SERVICE_QOS

CASES = (("lqr_2_1", 100), ("lqr_6_2", 1000))  # (task, trajectories of H = 1000): 10^5 and 10^6 points
HORIZON = 1000
STATE_TIMEOUT_S = 0.1
STATE_PERIOD = "state period p50 / p99 / max (ms)"  # npp-deploy's /diagnostics values, over its last 1,000
STATE_PERIODS = "state periods measured"


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


class Robot(Node):
    """This process's side: the robot in lockstep, and npp-deploy's lifecycle and /diagnostics."""

    def __init__(self, task: str) -> None:
        super().__init__("npp_bench_robot")
        self.plant = get_task(task).make_plant(0)
        self.state_pub = self.create_publisher(JointState, JOINT_STATES, CONTROL_QOS)
        self.create_subscription(Float64MultiArray, FORWARD_COMMANDS, self.on_command, CONTROL_QOS)
        self.create_subscription(DiagnosticArray, DIAGNOSTICS, self.on_diagnostics, DIAGNOSTICS_QOS)
        self.change = self.create_client(ChangeState, "/npp_deploy/change_state", qos_profile=SERVICE_QOS)
        self.command: tuple[float, list[float]] | None = None
        self.health: Any = None
        self.statuses = 0
        self.sent = 0

    def on_command(self, msg: Float64MultiArray) -> None:
        self.command = (time.perf_counter(), list(msg.data))

    def on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name == "/npp_deploy":
                self.health = health_of(status)
                self.statuses += 1

    def publish(self) -> float:
        """The plant's state as the robot's joint state, with a new stamp; returns when it went out."""
        self.sent += 1
        data = self.plant.physics.data
        msg = JointState(name=list(self.plant.joint_names), position=float64_array(data.qpos),
                         velocity=float64_array(data.qvel))  # fmt: skip
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


def round_trips(executor: SingleThreadedExecutor, robot: Robot, states: int) -> list[float]:
    """Lockstep: each state's time to its command (seconds); the plant steps with every command."""
    task = get_task(robot.plant.task)
    rng = np.random.default_rng(1)
    latencies: list[float] = []
    while len(latencies) < states:
        robot.plant.reset(task.sample_initial_state(rng))
        for _ in range(min(HORIZON, states - len(latencies))):
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
        robot.plant.reset(get_task(robot.plant.task).initial_state(0, len(delays)))
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
    executor: SingleThreadedExecutor, robot: Robot, periods: int, env: dict[str, str], log_path: Path
) -> tuple[list[float], int]:
    """npp-robot in real time against the active npp-deploy: the state period's p50, p99 and max (seconds) over
    the intervals npp-deploy took, as it reports them, and how many intervals those are."""
    transition(executor, robot, "deactivate", 60.0)
    task = robot.plant.task
    proc = spawn(["npp_ros_graph.nodes.robot", "--ros-args", "-p", f"task:={task}"], env, log_path)
    try:
        # The robot publishes from its start; npp-deploy measures from its activation on.
        if not wait_for(executor, lambda: robot.count_publishers(JOINT_STATES) >= 2, 120.0):
            raise RuntimeError(f"npp-robot's joint states did not appear; see {log_path}")
        transition(executor, robot, "activate", 60.0)
        wait_for(executor, lambda: False, periods * robot.plant.dt)
        seen = robot.statuses
        if not wait_for(executor, lambda: robot.statuses > seen and STATE_PERIOD in robot.health.values, 10.0):
            raise RuntimeError("npp-deploy reported no state period")
        health = robot.health
        transition(executor, robot, "deactivate", 60.0)
    finally:
        stop(proc)
    figures = [float(x) * 1e-3 for x in str(health.values[STATE_PERIOD]).split("/")]
    return figures, int(health.values[STATE_PERIODS])


def measure_case(task: str, trajectories: int, args: argparse.Namespace, env: dict[str, str]) -> dict[str, Any]:
    started = time.perf_counter()
    run = make_run(task, trajectories, args.runs / f"{task}-{trajectories}")
    made_s = time.perf_counter() - started
    log(f"{task}: run of {trajectories} trajectories ready in {made_s:.0f} s ({run})")
    params = {"run_dir": str(run), "robot_model_fingerprint": plant_fingerprint(task, 0), "override_gate": "true",
              "state_timeout": repr(STATE_TIMEOUT_S), "coverage_radius": "100.0"}  # fmt: skip
    ros_args = [arg for name, value in params.items() for arg in ("-p", f"{name}:={value}")]
    proc = spawn(["npp_ros_graph.nodes.deploy", "--ros-args", *ros_args], env, args.logs / f"deploy-{task}.log")
    executor = SingleThreadedExecutor()
    robot = Robot(task)
    executor.add_node(robot)
    try:
        started = time.perf_counter()
        transition(executor, robot, "configure", 900.0)
        configure_s = time.perf_counter() - started
        transition(executor, robot, "activate", 60.0)
        wait_for(executor, lambda: robot.state_pub.get_subscription_count() > 0, 60.0)
        round_trips(executor, robot, 50)  # warm-up: the first queries compile and fill caches
        latencies = round_trips(executor, robot, args.states)
        robot.health = None
        wait_for(executor, lambda: robot.health is not None and "answer time p50 / p99 (us)" in robot.health.values,
                 5.0)  # fmt: skip
        answer = robot.health.values.get("answer time p50 / p99 (us)", "-") if robot.health else "-"
        delays = watchdog_delays(executor, robot, args.stops)
        (j50, j99, jmax), intervals = state_periods(executor, robot, args.periods, env, args.logs / f"robot-{task}.log")
    finally:
        stop(proc)
        executor.remove_node(robot)
        robot.destroy_node()
        executor.shutdown()
    p50, p99 = (v * 1e6 for v in percentiles(latencies))
    w50, wmax = percentiles(delays, (50, 100))
    result = {
        "task": task, "points": trajectories * HORIZON, "state_dim": robot.plant.state_dim, "states": len(latencies),
        "round_trip_p50_us": p50, "round_trip_p99_us": p99, "node_answer_p50_p99_us": answer,
        "configure_s": configure_s, "state_timeout_ms": STATE_TIMEOUT_S * 1e3, "stops": len(delays),
        "safe_command_after_last_state_ms": [d * 1e3 for d in delays], "safe_p50_ms": w50 * 1e3,
        "safe_max_ms": wmax * 1e3, "control_period_ms": robot.plant.dt * 1e3,
        "state_periods": intervals,
        "state_period_p50_ms": j50 * 1e3, "state_period_p99_ms": j99 * 1e3, "state_period_max_ms": jmax * 1e3,
    }  # fmt: skip
    log(f"{task} {result['points']:,d} points: round trip p50 {p50:.0f} us, p99 {p99:.0f} us; node {answer} us; "
        f"safe command {w50 * 1e3:.1f} ms (max {wmax * 1e3:.1f}) after the last state, timeout "
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
        "npp-deploy deploys a stored run of real LQR expert trajectories (uncertified, `override_gate`: the gate "
        "is not measured) and answers a robot played by the bench in lockstep over DDS on this machine.",
        "",
        "| case | points | states | round trip p50 / p99 (us) | node answer p50 / p99 (us) | configure (s) |",
        "|---|---|---|---|---|---|",
    ]
    for r in out["cases"]:
        lines.append(
            f"| {r['task']} ({r['state_dim']}-D) | {r['points']:,d} | {r['states']:,d} | "
            f"{r['round_trip_p50_us']:.0f} / {r['round_trip_p99_us']:.0f} | {r['node_answer_p50_p99_us']} | "
            f"{r['configure_s']:.1f} |"
        )
    lines += [
        "",
        "Round trip: from the joint state published to its command received (both DDS hops). Node answer: "
        "npp-deploy's own time from its callback's start to its publish, over its last 1,000 answers.",
        "",
        "| case | state_timeout (ms) | control period (ms) | stops | safe command after the last state, "
        "median / max (ms) |",
        "|---|---|---|---|---|",
    ]
    for r in out["cases"]:
        lines.append(
            f"| {r['task']} | {r['state_timeout_ms']:.0f} | {r['control_period_ms']:.0f} | {r['stops']} | "
            f"{r['safe_p50_ms']:.1f} / {r['safe_max_ms']:.1f} |"
        )
    lines += [
        "",
        "State period: npp-robot publishes joint states in real time, one per control period, and npp-deploy "
        "answers them; the interval between two joint states as npp-deploy takes them, over its last intervals "
        "(up to 1,000), as npp-deploy reports it on /diagnostics.",
        "",
        "| case | control period (ms) | intervals | state period p50 / p99 / max (ms) |",
        "|---|---|---|---|",
    ]
    for r in out["cases"]:
        lines.append(
            f"| {r['task']} | {r['control_period_ms']:.0f} | {r['state_periods']:,d} | "
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
    parser.add_argument("--runs", type=Path, default=Path("runs/bench-deploy"), help="folder for the runs it stores")
    parser.add_argument("--logs", type=Path, default=None, help="folder for npp-deploy's logs")
    parser.add_argument("--out", type=Path, default=None, help="write OUT/bench.json and OUT/bench.md")
    args = parser.parse_args(argv)
    cases = [(task, 2 if args.quick else n) for task, n in CASES]
    if args.quick:
        args.states, args.stops, args.periods = min(args.states, 300), min(args.stops, 3), min(args.periods, 100)
    args.logs = args.logs or args.runs / "logs"
    args.logs.mkdir(parents=True, exist_ok=True)
    out: dict[str, Any] = {
        "command": "npp-bench-deploy " + " ".join(sys.argv[1:] if argv is None else argv),
        "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
        "load_average_start": list(os.getloadavg()),
    }
    with reserved_domain() as env:
        out["cases"] = [measure_case(task, n, args, env) for task, n in cases]
    out["load_average_end"] = list(os.getloadavg())
    if args.out:
        figures, tables = write_report(args.out, "bench", out, markdown(out))
        log(f"wrote {figures} and {tables}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
