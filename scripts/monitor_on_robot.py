"""Whether npp-deploy finds a robot that is not what was certified while the certified policy drives it, over DDS.

The offline comparison (scripts/monitor_windows.py) runs both monitors on recorded motion. This one runs them where
they run: ``npp-robot`` (real time, its own MuJoCo physics, a hidden robot record: scales and a delay its description
does not show, ``publish_description:=nominal``) and ``npp-deploy`` (the run, ``monitor_window`` as given,
``on_model_mismatch:=warn`` so that one activation shows when each robot is found), on a ROS_DOMAIN_ID of their own
with localhost discovery. npp-deploy is configured once (the gate, its re-derivation included); per robot a fresh
npp-robot starts at a held-out s0 of the run, held until the first command, npp-deploy is activated, and its
/diagnostics are watched for SECONDS of wall time for the model monitor's finding (latched: the first one found is the
one it keeps). Then npp-deploy is deactivated, the finding cleared (clear_model_mismatch), and npp-robot stopped.

The robots: those of scripts/monitor_windows.py outside the set, and ``--inside`` robots drawn from the set (any
finding there is a false alarm). ``--load N`` runs N busy processes beside the nodes for the whole trial, so the
control loop's timing breaks as it does on a busy machine (the monitors take no transition whose timing broke).

    .venv/bin/python scripts/monitor_on_robot.py --run runs/pendulum-u1 --out results/monitor-on-robot/load-2 \\
        --window 3 --seconds 30 --inside 10 --load 2

Writes OUT/monitor-on-robot.json and .md; the nodes' logs go to --logs.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from lifecycle_msgs.srv import ChangeState
from npp_interfaces.srv import ResetRobot
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from std_srvs.srv import Trigger

from npp_ros.bench.report import write_report
from npp_ros.run.held_out import LEARN_HELD_OUT_STREAM, held_out_states
from npp_ros.run.read import read_run
from npp_ros.tasks.uncertainty import Robot
from npp_ros_graph.bench.ros_loop import interrupt_on_signals, reserved_domain, spawn, stop, wait_for
from npp_ros_graph.graph.description import parameter_args
from npp_ros_graph.runtime.diagnostics import DIAGNOSTICS, DIAGNOSTICS_QOS, Health, health_of
from npp_ros_graph.transport.topics import SERVICE_QOS

sys.path.insert(0, str(Path(__file__).resolve().parent))
from monitor_windows import OUTSIDE  # the same robots outside the set as the offline comparison

DEPLOY, ROBOT = "/npp_deploy", "/npp_robot"
START_TIMEOUT_S = 180.0  # processes importing rclpy and MuJoCo on a busy 2-core machine
CONFIGURE_TIMEOUT_S = 900.0  # the gate derives the run again at configure
WINDOW_FOUND = "the robot identified from"  # the window identification's finding starts so; the transitions' not
TIMING_COUNTS = ("answered", "overtaken states", "repeated stamps", "watchdog expiries")


@dataclass
class Watched:
    """One robot driven by the certified policy over DDS for one activation."""

    robot: str
    record: str
    outside: bool  # not a robot of the set
    found_after_s: float | None  # wall seconds from the activation's answer to the finding on /diagnostics
    found_by: str  # "windows", "transitions" or ""
    finding: str
    last_window: str  # the window identification's last words, from /diagnostics
    transitions: str  # the transition monitor's summary, from /diagnostics
    counts: dict[str, int]  # npp-deploy's counters over the activation (timing: overtaken states, stamps, watchdog)
    watched_s: float


class MonitorNode(Node):
    """This process's side: npp-deploy's lifecycle and clear service, npp-robot's reset, both nodes' /diagnostics."""

    def __init__(self) -> None:
        super().__init__("npp_monitor_on_robot")
        self.change = self.create_client(ChangeState, f"{DEPLOY}/change_state", qos_profile=SERVICE_QOS)
        self.clear = self.create_client(Trigger, f"{DEPLOY}/clear_model_mismatch", qos_profile=SERVICE_QOS)
        self.reset = self.create_client(ResetRobot, f"{ROBOT}/reset", qos_profile=SERVICE_QOS)
        self.latest: dict[str, Health] = {}
        self.seen: dict[str, int] = {}
        self.create_subscription(DiagnosticArray, DIAGNOSTICS, self.on_diagnostics, DIAGNOSTICS_QOS)

    def on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name in (DEPLOY, ROBOT):
                self.latest[status.name] = health_of(status)
                self.seen[status.name] = self.seen.get(status.name, 0) + 1


def busy() -> None:  # a load process: one core's worth of work until killed
    while True:
        pass


class Bench:
    """npp-deploy for the whole trial, one npp-robot per robot, this process's node."""

    def __init__(self, args: argparse.Namespace, env: dict[str, str]) -> None:
        self.args, self.env = args, env
        self.executor = SingleThreadedExecutor()
        self.node = MonitorNode()
        self.executor.add_node(self.node)
        self.deploy: Any = None
        self.robot: Any = None

    def wait(self, done: Any, timeout: float, what: str) -> None:
        procs = [p for p in (self.deploy, self.robot) if p is not None]
        if not wait_for(self.executor, lambda: done() or any(p.poll() is not None for p in procs), timeout):
            raise RuntimeError(f"no {what} within {timeout:.0f} s; see {self.args.logs}")
        for name, proc in (("npp-deploy", self.deploy), ("npp-robot", self.robot)):
            if proc is not None and proc.poll() is not None:
                raise RuntimeError(f"{name} stopped (exit {proc.returncode}); see {self.args.logs / (name + '.log')}")

    def call(self, client: Any, request: Any, what: str, timeout: float = 60.0) -> Any:
        future = client.call_async(request)
        self.wait(future.done, timeout, f"answer to {what}")
        return future.result()

    def transition(self, label: str, timeout: float = 60.0) -> None:
        request = ChangeState.Request()
        request.transition.label = label
        if not self.call(self.node.change, request, f"npp-deploy's {label}", timeout).success:
            health = self.node.latest.get(DEPLOY)
            raise RuntimeError(f"npp-deploy refused {label}: {health.doing if health else '?'}")

    def start_robot(self, name: str, robot: Robot, s0: Any) -> None:
        """A fresh npp-robot that is ``robot``, at ``s0``, held until the first command."""
        values = {
            "task": self.task, "seed": self.seed, "robot": robot.record(), "publish_description": "nominal",
            "start_on_command": True, "initial_state": ",".join(repr(float(x)) for x in s0),
        }  # fmt: skip
        log = self.args.logs / f"npp-robot-{name.replace(' ', '-')}.log"
        self.robot = spawn(["npp_ros_graph.nodes.robot", "--ros-args", *parameter_args(values)], self.env, log)
        self.wait(lambda: self.node.reset.service_is_ready(), START_TIMEOUT_S, "npp-robot's reset service")

    def stop_robot(self) -> None:
        if self.robot is not None:
            stop(self.robot)
            self.robot = None
            # its reset service gone before the next robot's appears: the next wait is for the new process
            self.wait(lambda: not self.node.reset.service_is_ready(), 30.0, "npp-robot's reset service to go")

    def start_deploy(self, run_dir: Path) -> float:
        """npp-deploy configured against the first robot's description; the seconds configure took."""
        values = {"run_dir": str(run_dir), "monitor_window": float(self.args.window), "on_model_mismatch": "warn"}
        self.deploy = spawn(["npp_ros_graph.nodes.deploy.node", "--ros-args", *parameter_args(values)], self.env,
                            self.args.logs / "npp-deploy.log")  # fmt: skip
        self.wait(lambda: self.node.change.service_is_ready(), START_TIMEOUT_S, "npp-deploy's lifecycle services")
        started = time.monotonic()
        self.transition("configure", CONFIGURE_TIMEOUT_S)
        return time.monotonic() - started

    def watch(self, name: str, robot: Robot, outside: bool) -> Watched:
        before = counts(self.node.latest.get(DEPLOY))
        self.transition("activate")
        activated = time.monotonic()
        found: list[tuple[float, Health]] = []

        def finding() -> bool:
            health = self.node.latest.get(DEPLOY)
            if health is not None and "certified set of robots" in health.error and not found:
                found.append((time.monotonic() - activated, health))
            return time.monotonic() - activated >= self.args.seconds

        self.wait(finding, self.args.seconds + 30.0, f"{self.args.seconds:g} s of {name}")
        health = self.node.latest.get(DEPLOY)
        watched = time.monotonic() - activated
        self.transition("deactivate")
        cleared = self.call(self.node.clear, Trigger.Request(), "npp-deploy's clear_model_mismatch")
        assert bool(found) == cleared.message.startswith("cleared"), cleared.message
        after_s, at = found[0] if found else (None, None)
        error = at.error if at is not None else ""
        values = health.values if health is not None else {}
        return Watched(
            robot=name, record=robot.record(), outside=outside, found_after_s=after_s,
            found_by=("windows" if error.startswith(WINDOW_FOUND) else "transitions") if error else "",
            finding=error, last_window=str(values.get("window identification", "")),
            transitions=str(values.get("model monitor", "")),
            counts={k: v - before.get(k, 0) for k, v in counts(health).items()}, watched_s=watched,
        )  # fmt: skip

    def close(self) -> None:
        try:
            health = self.node.latest.get(DEPLOY)
            if self.deploy is not None and self.deploy.poll() is None and health and health.doing.startswith("active"):
                self.transition("deactivate", 10.0)
        except Exception as exc:  # stopping anyway
            print(f"npp-deploy's deactivate at exit: {exc}", file=sys.stderr)
        finally:
            for proc in (self.deploy, self.robot):
                if proc is not None:
                    stop(proc)
            self.executor.remove_node(self.node)
            self.node.destroy_node()
            self.executor.shutdown()


def counts(health: Health | None) -> dict[str, int]:
    values = {} if health is None else health.values
    return {name: int(str(values[name])) for name in TIMING_COUNTS if name in values}


def markdown(out: dict[str, Any]) -> str:
    rows: list[dict[str, Any]] = out["robots"]
    outside = [r for r in rows if r["outside"]]
    inside = [r for r in rows if not r["outside"]]
    lines = [
        f"# The model monitor over DDS under the certified policy's own commands: {out['task']}",
        "",
        f"`.venv/bin/python {out['command']}` on {out['date']}; the set: {out['set']}. npp-deploy configured "
        f"in {out['configure_s']:.1f} s, then one activation of {out['seconds']:g} s per robot, `monitor_window:="
        f"{out['window']:g}`, {out['load']} busy processes beside the nodes (1-minute load "
        f"{out['load_average_start'][0]} at the start, {out['load_average_end'][0]} at the end). Times are wall "
        "seconds from the activation's answer to the finding on /diagnostics (the robot runs in real time: its "
        "seconds of motion, within the transport's delay).",
        "",
        f"- Outside the set: {sum(r['found_after_s'] is not None for r in outside)} of {len(outside)} found; "
        f"inside: {sum(r['found_after_s'] is not None for r in inside)} false alarms of {len(inside)} robots.",
        "",
        "| robot | found after | by | overtaken states | repeated stamps | watchdog expiries | last window |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        at = "-" if r["found_after_s"] is None else f"{r['found_after_s']:.2f} s"
        c = r["counts"]
        lines.append(f"| {r['robot']} | {at} | {r['found_by'] or '-'} | {c.get('overtaken states', '?')} | "
                     f"{c.get('repeated stamps', '?')} | {c.get('watchdog expiries', '?')} | "
                     f"{r['last_window'][:160]} |")  # fmt: skip
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog=__doc__.split("\n\n", 1)[1])  # fmt: skip
    parser.add_argument("--run", type=Path, required=True, help="a certified run on a set of robots")
    parser.add_argument("--out", type=Path, required=True, help="writes OUT/monitor-on-robot.json and .md")
    parser.add_argument("--seconds", type=float, default=30.0, help="wall seconds per robot")
    parser.add_argument(
        "--window", type=float, default=-1.0, help="npp-deploy's monitor_window (0: transitions only; -1: its default)"
    )
    parser.add_argument("--inside", type=int, default=10, help="robots drawn from the set (false alarms)")
    parser.add_argument("--load", type=int, default=0, help="busy processes beside the nodes")
    parser.add_argument("--only", nargs="*", default=None, help="only these robots (names as in the table)")
    parser.add_argument("--logs", type=Path, default=None, help="the nodes' logs (default OUT's name under runs/)")
    args = parser.parse_args(argv)
    args.logs = args.logs or Path("runs/monitor-on-robot") / f"{args.out.name}-logs"
    args.logs.mkdir(parents=True, exist_ok=True)
    run = read_run(args.run)
    if run.robots is None or run.robots.empty:
        parser.error(f"{args.run} was not certified on a set of robots: there is nothing to monitor against")
    seed = int(run.metadata.seed)
    robots: list[tuple[str, Robot, bool]] = [(name, robot, True) for name, robot in OUTSIDE.items()]
    robots += [(f"drawn {k}", run.robots.draw(seed, 10_000 + k), False) for k in range(args.inside)]
    robots = [r for r in robots if args.only is None or r[0] in args.only]
    starts = held_out_states(run.task, seed, len(robots), LEARN_HELD_OUT_STREAM)
    command = "scripts/monitor_on_robot.py " + " ".join(sys.argv[1:] if argv is None else argv)
    out: dict[str, Any] = {"command": command, "task": run.task.name, "set": run.robots.describe(),
                           "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "seconds": args.seconds,
                           "window": args.window, "load": args.load,
                           "load_average_start": [round(x, 2) for x in os.getloadavg()]}  # fmt: skip
    load = [multiprocessing.get_context("spawn").Process(target=busy, daemon=True) for _ in range(args.load)]
    for proc in load:
        proc.start()
    watched: list[Watched] = []
    with reserved_domain() as env:
        interrupt_on_signals()  # the nodes are deactivated before they are stopped
        bench = Bench(args, env)
        bench.task, bench.seed = str(run.metadata.task), seed
        try:
            for k, ((name, robot, outside), s0) in enumerate(zip(robots, starts, strict=True)):
                bench.start_robot(name, robot, s0)
                if k == 0:
                    out["configure_s"] = bench.start_deploy(args.run.resolve())
                    print(f"npp-deploy configured in {out['configure_s']:.1f} s", flush=True)
                w = bench.watch(name, robot, outside)
                watched.append(w)
                at = "not found" if w.found_after_s is None else f"found after {w.found_after_s:.2f} s by {w.found_by}"
                print(f"{name}: {at}; {w.counts}", flush=True)
                bench.stop_robot()
        except KeyboardInterrupt:
            print("interrupted: stopping the nodes", file=sys.stderr)
            return 130
        finally:
            bench.close()
            for proc in load:
                proc.kill()
    out["load_average_end"] = [round(x, 2) for x in os.getloadavg()]
    out["robots"] = [asdict(w) for w in watched]
    write_report(args.out, "monitor-on-robot", out, markdown(out))
    print(f"wrote {args.out / 'monitor-on-robot.md'}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
