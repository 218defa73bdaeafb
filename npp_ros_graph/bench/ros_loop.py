"""Closed-loop steps per second through ROS: the policy node against a bare rclpy ping-pong.

This process plays the sim: it publishes a JointState on /npp/state, waits for the JointState
answer on /npp/action, steps the plant's exact linear model x' = A x + B u with it, and repeats,
in lockstep. Against it, in separate processes, runs either

* the real policy node (``npp_ros_graph.nodes.policy``, as npp-run starts it: on rclpy's
  EventsExecutor), which catches the dataset up through this process's /npp/dataset/get service
  and answers with the greedy NPP action; the driver seals each state and checks each answer's
  seal as the sim does, and the policy checks and seals in turn, or
* a bare echo node (``--echo``), a plain rclpy node as a user would write it: rclpy's default
  SingleThreadedExecutor, same message types and QoS, no seals, answers at once.

Both are measured in the same run with the same driver, so their ratio is the cost of the
policy (its query, its seals and its node code) relative to the ROS round trip itself. Every run
gets its own ROS_DOMAIN_ID and localhost-only discovery.

Usage: npp-bench-ros [--quick] [--out DIR] [--json FILE|-] [--steps N]. With --out it puts its
result into DIR/bench.json and bench.md (results/bench: the ROS section and its target rows,
the index figures kept); `npp-bench --ros` calls measure() within its own run instead.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
from domain_coordinator import domain_id
from npp_interfaces.msg import PlantDescription
from npp_interfaces.srv import GetTrajectories
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import UInt32

from npp_ros.policy.dataset import Dataset
from npp_ros.policy.spec import PolicySpec
from npp_ros.run.store import new_run_id
from npp_ros.tasks.builtin.lqr import LQRExpert, sample_initial_state
from npp_ros.tasks.registry import control_space
from npp_ros_graph.runtime.node import run_node
from npp_ros_graph.transport.convert import (
    action_to_joint_state,
    plant_description,
    policy_spec_to_msg,
    stamp,
    stamp_ns,
    state_to_joint_state,
    trajectory_to_msg,
)
from npp_ros_graph.transport.message_seal import RunSeal
from npp_ros_graph.transport.topics import (
    ACTION,
    CONTROL_QOS,
    DATASET_SERVICE,
    LATCHED_QOS,
    LATCHED_READER_QOS,
    PLANT,
    POLICY_STATUS,
    SERVICE_QOS,
    STATE,
)

CASES = (("lqr_2_1", 100), ("lqr_6_2", 1000))  # (task, trajectories): 10^5 points in 4-D, 10^6 in 12-D
TARGETS = {"lqr_2_1": 0.8, "lqr_6_2": 0.5}


class EchoNode(Node):
    """The bare ping-pong partner: answers every state with a zero action at once (run_node's default
    executor, the SingleThreadedExecutor that rclpy.spin uses)."""

    def __init__(self) -> None:
        super().__init__("npp_bench_echo")
        self.pub = self.create_publisher(JointState, ACTION, CONTROL_QOS)
        self.create_subscription(JointState, STATE, self.on_state, CONTROL_QOS)
        self.action_dim = int(os.environ.get("NPP_BENCH_ACTION_DIM", "1"))
        self.names = [f"actuator{i}" for i in range(self.action_dim)]
        self.zero = np.zeros(self.action_dim)

    def on_state(self, msg: JointState) -> None:
        self.pub.publish(action_to_joint_state(self.zero, self.names, msg.header.stamp))


class Driver(Node):
    """Plays the sim (states out, actions in) and the supervisor's dataset service. ``sealed``: seals its
    states and checks the answers' seals, as the sim does, so that the graph's loop is measured with the
    checks every control step of a run makes; the bare ping-pong exchanges plain messages."""

    def __init__(self, expert: LQRExpert, data: Dataset, task: str, seed: int, namespace: str, sealed: bool) -> None:
        super().__init__("npp_bench_driver", namespace=namespace)
        self.expert, self.data, self.task, self.sealed = expert, data, task, sealed
        plant = expert.plant
        self.joint_names = list(plant.joint_names)
        self.state_pub = self.create_publisher(JointState, STATE, CONTROL_QOS)
        self.plant_pub = self.create_publisher(PlantDescription, PLANT, LATCHED_QOS)
        self.create_subscription(JointState, ACTION, self.on_action, CONTROL_QOS)
        self.create_subscription(UInt32, POLICY_STATUS, self.on_status, LATCHED_READER_QOS)
        self.create_service(GetTrajectories, DATASET_SERVICE, self.on_dataset, qos_profile=SERVICE_QOS)
        run_seal = RunSeal.from_environment()
        self.run = new_run_id()  # the bench plays one run's supervisor and sim
        self.seal = run_seal.for_plant(plant.model_sha256()).for_run(self.run)
        self.plant_pub.publish(run_seal.seal(plant_description(plant, seed, expert.horizon)))
        self.held = 0
        self.answer: JointState | None = None
        self.sent_ns = 0

    def on_status(self, msg: UInt32) -> None:
        self.held = int(msg.data)

    def on_dataset(self, request: GetTrajectories.Request, response: GetTrajectories.Response):
        total = self.data.num_trajectories
        response.success, response.total, response.run = True, total, self.run
        # the default policy, with the LQR expert's gains (the costlier answer), as a run's supervisor sends it
        spec = PolicySpec("feedback", self.expert.analytic_lipschitz(), control_space(self.expert.plant))
        response.policy = policy_spec_to_msg(spec)
        stop = min(total, request.start + (request.max_count or 50))
        for k in range(request.start, stop):
            response.trajectories.append(self.seal.seal(trajectory_to_msg(k, self.data.trajectory(k), self.run)))
        return self.seal.seal(response, answering=request)

    def on_action(self, msg: JointState) -> None:
        if stamp_ns(msg.header.stamp) == self.sent_ns:
            if self.sealed:
                self.seal.check_header(msg, "the action")
            self.answer = msg

    def send(self, state: np.ndarray, step_ns: int) -> None:
        msg = state_to_joint_state(state, self.joint_names, stamp(step_ns))
        if self.sealed:
            self.seal.seal_header(msg, "0")
        self.sent_ns = step_ns
        self.answer = None
        self.state_pub.publish(msg)


def wait_for(executor: SingleThreadedExecutor, done, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while not done():
        if time.monotonic() > end:
            return False
        executor.spin_once(timeout_sec=0.05)
    return True


def lockstep(executor: SingleThreadedExecutor, driver: Driver, steps: int, s0: np.ndarray, counter: list[int]) -> float:
    """Steps per second of the closed loop x' = A x + B u(x) through the partner node."""
    A, B = driver.expert.A, driver.expert.B
    x = s0.copy()
    t = time.perf_counter()
    for _ in range(steps):
        counter[0] += 1
        driver.send(x, counter[0])
        tries = 0
        while not wait_for(executor, lambda: driver.answer is not None, 2.0):
            tries += 1  # lost before the partner matched (warm-up), or a slow first answer: ask again
            if tries > 30:
                raise RuntimeError(f"no answer to state {counter[0]} within 60 s")
            driver.send(x, counter[0])
        u = np.asarray(driver.answer.effort, dtype=np.float64)
        x = A @ x + B @ u if u.shape[0] == B.shape[1] else x
    return steps / (time.perf_counter() - t)


def interrupt_on_signals() -> None:
    """Ctrl-C and SIGTERM raise KeyboardInterrupt here, in place of rclpy's handler, which would shut the ROS context
    down first: a script that drives nodes can then still deactivate them (their safe command) before it stops them."""

    def interrupted(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGINT, interrupted)
    signal.signal(signal.SIGTERM, interrupted)


def spawn(module_args: list[str], env: dict[str, str], log: Path) -> subprocess.Popen:
    handle = log.open("w")
    return subprocess.Popen([sys.executable, "-m", *module_args], env=env, stdout=handle, stderr=subprocess.STDOUT)


def stop(proc: subprocess.Popen, grace: float = 10.0) -> None:
    """SIGTERM (a node's clean shutdown), then SIGKILL after ``grace`` seconds."""
    proc.terminate()
    try:
        proc.wait(timeout=grace)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def measure_case(task: str, trajectories: int, args: argparse.Namespace, env: dict[str, str], logs: Path) -> dict:
    t = time.perf_counter()
    expert = LQRExpert(task, 0)
    rng = np.random.default_rng(args.seed)
    data = Dataset(expert.plant.state_dim, expert.plant.actuators, capacity=trajectories * expert.horizon)
    for _ in range(trajectories):
        data.append(expert.trajectory(sample_initial_state(task, rng)))
    starts = [sample_initial_state(task, rng) for _ in range(args.repeats)]
    log(f"{task}: {len(data):,d} points generated ({time.perf_counter() - t:.1f}s)")
    executor = SingleThreadedExecutor()
    partners = ("pingpong", "graph")
    drivers = {name: Driver(expert, data, task, 0, f"/bench_{name}", sealed=name == "graph") for name in partners}
    for driver in drivers.values():
        executor.add_node(driver)
    counter = [0]
    result: dict[str, Any] = {"task": task, "points": len(data), "state_dim": data.state_dim, "steps": args.steps}
    procs = []
    try:
        for name in partners:
            cmd = ["npp_ros_graph.bench.ros_loop", "--echo"] if name == "pingpong" else ["npp_ros_graph.nodes.policy"]
            child_env = {**env, "NPP_BENCH_ACTION_DIM": str(data.action_dim)}
            procs.append(
                spawn([*cmd, "--ros-args", "-r", f"__ns:=/bench_{name}"], child_env, logs / f"{task}-{name}.log")
            )
        for name, driver in drivers.items():
            t = time.perf_counter()
            ready = wait_for(
                executor,
                lambda d=driver, n=name: (
                    d.state_pub.get_subscription_count() > 0
                    and d.count_publishers(ACTION) > 0
                    and (n == "pingpong" or d.held >= data.num_trajectories)
                ),
                900.0,
            )
            if not ready:
                raise RuntimeError(f"the {name} partner is not ready (holds {driver.held} trajectories); see {logs}")
            result[f"{name}_ready_s"] = time.perf_counter() - t
            t = time.perf_counter()  # warm-up: the index build on the first query, caches
            lockstep(executor, driver, 20, starts[0], counter)
            result[f"{name}_first_answers_s"] = time.perf_counter() - t
        rates: dict[str, list[float]] = {name: [] for name in partners}
        for s0 in starts:  # interleaved, so load changes on the machine hit both alike
            for name in partners:
                rates[name].append(lockstep(executor, drivers[name], args.steps, s0, counter))
        for name in partners:
            result[f"{name}_steps_per_s"] = rates[name]
            result[f"{name}_median"] = float(np.median(rates[name]))
            log(f"{task} {name}: median {result[f'{name}_median']:.0f} steps/s over {len(rates[name])} runs")
    finally:
        for proc in procs:
            proc.terminate()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        for driver in drivers.values():
            executor.remove_node(driver)
            driver.destroy_node()
        executor.shutdown()
    result["ratio"] = result["graph_median"] / result["pingpong_median"]
    result["target"] = TARGETS[task]
    result["met"] = result["ratio"] >= TARGETS[task]
    return result


def log(text: str) -> None:
    sys.stderr.write(f"npp-bench-ros: {text}\n")
    sys.stderr.flush()


def isolated_env(domain: int) -> dict[str, str]:
    """The reserved ROS_DOMAIN_ID and localhost-only discovery, for this process and its partners."""
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["ROS_DOMAIN_ID"] = str(domain)
    env.pop("ROS_STATIC_PEERS", None)
    return env


@contextmanager
def reserved_domain() -> Iterator[dict[str, str]]:
    """A ROS domain no other session (tests, runs) is using, with localhost-only discovery, for this process
    (rclpy initialised on it until the block ends) and, through the environment it yields, its partners."""
    keys = ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_DOMAIN_ID", "ROS_STATIC_PEERS")
    saved = {key: os.environ.get(key) for key in keys}
    with domain_id() as domain:
        env = isolated_env(int(domain))
        os.environ.update({k: env[k] for k in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_DOMAIN_ID")})
        os.environ.pop("ROS_STATIC_PEERS", None)
        rclpy.init()
        try:
            yield env
        finally:
            rclpy.try_shutdown()
            for key, value in saved.items():  # the caller's domain again: it may go on using ROS
                if value is None:
                    os.environ.pop(key, None)
                else:
                    os.environ[key] = value


def measure(
    quick: bool = False, steps: int = 2000, repeats: int = 3, seed: int = 0, logs: Path | None = None
) -> dict[str, Any]:
    """Both cases, each partner in its own process, on a ROS domain reserved for this run."""
    args = argparse.Namespace(steps=200 if quick else steps, repeats=2 if quick else repeats, seed=seed)
    cases = [(task, 2 if quick else n) for task, n in CASES]
    logs = logs or Path(os.environ.get("TMPDIR", "/tmp")) / f"npp-bench-loop-{os.getpid()}"
    logs.mkdir(parents=True, exist_ok=True)
    with reserved_domain() as env:
        results = [measure_case(task, n, args, env, logs) for task, n in cases]
    return {"domain_id": env["ROS_DOMAIN_ID"], "logs": str(logs), "cases": results}


def write_into(folder: Path, ros: dict[str, Any]) -> None:
    """The ROS section of folder/bench.json and bench.md, replaced; the rest as npp-bench wrote it."""
    from npp_ros.bench.report import markdown, with_ros, write_report  # the report alone: no index measurement loads

    result = json.loads((folder / "bench.json").read_text())
    with_ros(result, ros)
    figures, tables = write_report(folder, "bench", result, markdown(result))
    log(f"wrote the ROS loop into {figures} and {tables}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="npp-bench-ros", description=__doc__.split("\n\n")[0])
    parser.add_argument("--echo", action="store_true", help="run the bare ping-pong partner node")
    parser.add_argument("--quick", action="store_true", help="small datasets and few steps (smoke run)")
    parser.add_argument("--steps", type=int, default=2000, help="lockstep steps per timed run")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per partner")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None, help="put the result into OUT/bench.json and bench.md")
    parser.add_argument("--json", default=None, help="write the result as JSON to this file ('-' = stdout)")
    parser.add_argument("--logs", type=Path, default=None, help="folder for the partner nodes' logs")
    args, _ = parser.parse_known_args(argv)
    if args.echo:
        return run_node(
            EchoNode, [sys.argv[0], *(sys.argv[sys.argv.index("--ros-args") :] if "--ros-args" in sys.argv else [])]
        )
    if args.out and not (args.out / "bench.json").exists():
        parser.error(f"{args.out / 'bench.json'} does not exist; `npp-bench --out {args.out}` writes it")
    started = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
    load_start = list(os.getloadavg())
    out = measure(args.quick, args.steps, args.repeats, args.seed, args.logs)
    results = out["cases"]
    if args.out:
        out |= {"command": "npp-bench-ros " + " ".join(sys.argv[1:] if argv is None else argv), "date": started,
                "load_average_start": load_start, "load_average_end": list(os.getloadavg())}  # fmt: skip
        write_into(args.out, out)
    text = json.dumps(out, indent=2)
    if args.json == "-":
        sys.stdout.write(text + "\n")
    elif args.json:
        Path(args.json).write_text(text + "\n")
    for r in results:
        log(f"{r['task']} {r['points']:,d} points: graph {r['graph_median']:.0f} steps/s, ping-pong "
            f"{r['pingpong_median']:.0f} steps/s, ratio {r['ratio']:.2f} (target >= {r['target']:.2f})")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
