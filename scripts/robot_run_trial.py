"""Certifying on the robot itself, measured through real processes: npp-robot as a hidden pendulum robot (its
parameters given to it, not to the run), npp-robot-run certifying on it, each its own process over DDS.

    .venv/bin/python scripts/robot_run_trial.py --out results/robot-run

Six measurements, each with its run folders under runs/robot-run/ (not in git):

- inside: a robot inside the pendulum's set where its set-certified policy is weak (damping x 0.55, a command one
  period late), in lockstep (or real time at --time-scale); the certificate, robot episodes, robot time, expert
  calls, faults and late commands; then an independent check of the certified policy on that robot (its physics in
  process, --held-out starts from a stream no run draws from), with a one-sided Clopper-Pearson bound.
- set: the policy a run on the whole set certified (--set-run, made by npp-learn --task pendulum_swingup --seed 0
  --uncertainty 1 --certify success --rule mixture --evaluate 0 --run-dir runs/per-robot/pendulum-u1-s0), on the same
  starts of the same robot.
- from_set: the inside run again, starting from the set run's certified data (npp-robot-run start_from).
- corner: the set's corner robot (mass x 1.2, gear x 0.8, damping x 1.5, one period late), where the expert itself
  fails, up to --corner-episodes episodes: whether, and when, the run says it can no longer certify.
- disturbed: the inside robot in lockstep (deterministic), undisturbed and with its joint states stopped for 1 s in
  the middle of an episode (the robot process paused) and the robot process restarted mid-run: the rows and the
  claim compared episode by episode.
- pace: a few episodes at each time scale of --scales, real time: the share of commands late by a period or more.

Writes robot-run.json and robot-run.md into --out; progress goes to stderr.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from npp_ros.identification.check import clopper_pearson_lower
from npp_ros.run.read import read_run
from npp_ros.run.store import RUN_FILE, RunStore
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.rollout import rollout
from npp_ros.tasks.uncertainty import Robot

TASK = "pendulum_swingup"
BIN = Path(sys.executable).parent
INSIDE = {"damping_scale": 0.55, "action_delay": 1}
CORNER = {"mass_scale": 1.2, "gear_scale": 0.8, "damping_scale": 1.5, "action_delay": 1}
HELD_OUT_FROM = 1_000_000  # held-out starts: s0 ~ rho of episodes no run reaches
DOMAIN = 100 + os.getpid() % 100  # this invocation's measurements, one after another, on a domain of their own


def say(text: str) -> None:
    print(f"robot_run_trial: {text}", file=sys.stderr, flush=True)


def fresh(run_dir: Path) -> Path:
    """A run folder emptied first: each measurement is a run of its own, never a resumed one."""
    shutil.rmtree(run_dir, ignore_errors=True)
    return run_dir


class Processes:
    """npp-robot and npp-robot-run on a domain of their own, localhost only; every one stopped at the end."""

    def __init__(self, logs: Path) -> None:
        self.logs = logs
        logs.mkdir(parents=True, exist_ok=True)
        self.env = {
            **os.environ,
            "ROS_DOMAIN_ID": str(DOMAIN),
            "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        }
        self.procs: list[subprocess.Popen[bytes]] = []

    def start(self, command: str, params: dict[str, Any], label: str) -> subprocess.Popen[bytes]:
        args = [str(BIN / command), "--ros-args"]
        for name, value in params.items():
            args += ["-p", f"{name}:={str(value).lower() if isinstance(value, bool) else value}"]
        log = open(self.logs / f"{len(self.procs):02d}-{label}.log", "wb")  # kept for the process
        proc = subprocess.Popen(args, stdout=log, stderr=subprocess.STDOUT, env=self.env)
        self.procs.append(proc)
        return proc

    def stop(self, proc: subprocess.Popen[bytes]) -> None:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()

    def close(self) -> None:
        for proc in self.procs:
            self.stop(proc)


def robot_params(extra: dict[str, Any], **how: Any) -> dict[str, Any]:
    return {"task": TASK, "seed": 0, "publish_description": "nominal", **extra, **how}


def run_params(run_dir: Path, **how: Any) -> dict[str, Any]:
    return {"task": TASK, "seed": 0, "certify": "success", "run_dir": str(run_dir), **how}


def episodes_in(path: Path) -> int:
    try:
        with RunStore.open(path) as store:
            return len(store.episodes())
    except Exception:  # being made: none yet
        return 0


def wait(proc: subprocess.Popen[bytes], run_file: Path, label: str, until: int | None = None) -> None:
    """Until the process ends (or the run holds ``until`` episodes), saying how far it is every 30 s."""
    last = 0.0
    while proc.poll() is None:
        done = episodes_in(run_file) if run_file.exists() else 0
        if until is not None and done >= until:
            return
        if time.monotonic() - last > 30:
            say(f"{label}: {done} episodes")
            last = time.monotonic()
        time.sleep(0.5)


def summary(run_dir: Path) -> dict[str, Any]:
    run = read_run(run_dir)
    kept = run.robot_episodes
    cert = run.certificate
    prior = json.loads(run.metadata.prior)["trajectories"] if run.metadata.prior else 0
    return {
        "episodes": len(run.episodes),
        "expert_calls": run.dataset.num_trajectories - prior,  # the run's own: not the trajectories it started with
        "started_with": prior,
        "certified": cert is not None,
        "policy_trajectories": None if cert is None else cert.policy_trajectories,
        "robot_episodes": len(kept),
        "checks": sum(k.role == "check" and k.fault is None for k in kept),
        "answers": sum(k.role == "answer" and k.fault is None for k in kept),
        "faults": [k.fault for k in kept if k.fault is not None],
        "robot_time_s": round(sum(k.robot_time for k in kept), 2),
        "late_commands": sum(k.late_commands for k in kept),
        "steps": sum(k.steps for k in kept),
        "check_successes": sum(bool(k.success) for k in kept if k.role == "check"),
        "expert_successes": sum(bool(row.expert_success) for row in run.episodes),  # its plans, run on the robot
        "statement": None if cert is None else cert.statement,
    }


def held_out(policy_dir: Path, robot: Robot, starts: int) -> dict[str, Any]:
    """The run's certified policy on ``robot`` (the physics npp-robot runs), from ``starts`` fresh s0 ~ rho."""
    run = read_run(policy_dir)
    task = get_task(TASK)
    plant = task.make_plant(0)
    policy = run.policy
    met = 0
    for k in range(starts):
        s0 = task.initial_state(0, HELD_OUT_FROM + k)
        controller = policy.controller()
        met += bool(task.success.met(rollout(plant, controller, s0, run.metadata.horizon, robot).states))  # type: ignore[union-attr]
    return {"starts": starts, "successes": met, "lower_bound_90": round(clopper_pearson_lower(met, starts, 0.1), 4)}


def pace_params(time_scale: float) -> dict[str, Any]:
    """The robot's pace: lockstep (time_scale 0: it steps when a command answers its state, so none is late), else
    real time at time_scale."""
    return {"lockstep": True} if time_scale == 0 else {"time_scale": time_scale}


def inside(out: Path, time_scale: float, starts: int, start_from: Path | None = None) -> dict[str, Any]:
    name = "inside" if start_from is None else "inside-from-set"
    run_dir = fresh(out / name)
    procs = Processes(out / f"{name}-logs")
    more = {} if start_from is None else {"start_from": str(start_from)}
    try:
        procs.start("npp-robot", robot_params(INSIDE, **pace_params(time_scale)), "robot")
        started = time.monotonic()
        runner = procs.start("npp-robot-run", run_params(run_dir, max_episodes=1000, **more), "robot-run")
        wait(runner, run_dir / RUN_FILE, name)
        wall = time.monotonic() - started
    finally:
        procs.close()
    found = summary(run_dir) | {"wall_s": round(wall, 1), "time_scale": time_scale}
    robot = Robot((("damping", "hinge", INSIDE["damping_scale"]),), INSIDE["action_delay"])
    if found["certified"]:
        found["held_out"] = held_out(run_dir, robot, starts)
    return found


def set_policy(set_run: Path, starts: int) -> dict[str, Any]:
    """The policy a run on the whole set certified, on the inside robot from the held-out starts."""
    robot = Robot((("damping", "hinge", INSIDE["damping_scale"]),), INSIDE["action_delay"])
    run = read_run(set_run)
    return held_out(set_run, robot, starts) | {
        "run": set_run.name,
        "certified": run.certificate is not None,
        "statement": None if run.certificate is None else run.certificate.statement,
    }


def corner(out: Path, time_scale: float, episodes: int) -> dict[str, Any]:
    run_dir = fresh(out / "corner")
    procs = Processes(out / "corner-logs")
    try:
        procs.start("npp-robot", robot_params(CORNER, **pace_params(time_scale)), "robot")
        runner = procs.start("npp-robot-run", run_params(run_dir, max_episodes=episodes), "robot-run")
        wait(runner, run_dir / RUN_FILE, "corner")
    finally:
        procs.close()
    log = (out / "corner-logs" / "01-robot-run.log").read_text(errors="replace")
    said = [line.split("npp-robot-run: ", 1)[1] for line in log.splitlines() if "can no longer be reached" in line]
    return summary(run_dir) | {"unreachable": said[0] if said else None}


def disturbed(out: Path, episodes: int) -> dict[str, Any]:
    """The inside robot in lockstep, undisturbed and disturbed: the same episodes must give the same rows."""
    results: dict[str, Any] = {}
    for kind in ("undisturbed", "disturbed"):
        run_dir = fresh(out / f"lockstep-{kind}")
        procs = Processes(out / f"lockstep-{kind}-logs")
        try:
            robot = procs.start("npp-robot", robot_params(INSIDE, lockstep=True), "robot")
            runner = procs.start("npp-robot-run", run_params(run_dir, max_episodes=episodes), "robot-run")
            if kind == "disturbed":
                wait(runner, run_dir / RUN_FILE, kind, until=episodes // 3)
                os.kill(robot.pid, signal.SIGSTOP)  # its joint states stop for a second, mid-episode
                time.sleep(1.0)
                os.kill(robot.pid, signal.SIGCONT)
                wait(runner, run_dir / RUN_FILE, kind, until=2 * episodes // 3)
                procs.stop(robot)  # the robot goes away and comes back
                robot = procs.start("npp-robot", robot_params(INSIDE, lockstep=True), "robot-again")
            wait(runner, run_dir / RUN_FILE, kind)
        finally:
            procs.close()
        results[kind] = summary(run_dir)
    a, b = read_run(out / "lockstep-undisturbed"), read_run(out / "lockstep-disturbed")
    same = [
        all(
            getattr(x, f.name) == getattr(y, f.name)
            for f in dataclasses.fields(x)
            if f.name not in ("wall_time", "checked_gap", "v_lb", "v_ub", "gap", "policy_return", "initial_state")
        )
        and np.allclose(x.initial_state, y.initial_state, atol=1e-12)
        and math.isclose(x.policy_return or 0.0, y.policy_return or 0.0, rel_tol=1e-9, abs_tol=1e-9)
        for x, y in zip(a.episodes, b.episodes, strict=False)
    ]
    results["episodes_compared"] = len(same)
    results["episodes_identical"] = sum(same)
    return results


def pace(out: Path, scales: Sequence[float], episodes: int) -> list[dict[str, Any]]:
    rows = []
    for scale in scales:
        run_dir = fresh(out / f"pace-{scale:g}")
        procs = Processes(out / f"pace-{scale:g}-logs")
        try:
            procs.start("npp-robot", robot_params(INSIDE, time_scale=scale), "robot")
            runner = procs.start("npp-robot-run", run_params(run_dir, max_episodes=episodes), "robot-run")
            wait(runner, run_dir / RUN_FILE, f"pace x{scale:g}")
        finally:
            procs.close()
        found = summary(run_dir)
        steps = max(found["steps"], 1)
        rows.append(
            {
                "time_scale": scale,
                "steps": found["steps"],
                "late_commands": found["late_commands"],
                "late_share": round(found["late_commands"] / steps, 4),
                "faults": len(found["faults"]),
            }
        )
        say(f"pace x{scale:g}: {found['late_commands']} of {steps} commands late")
    return rows


def pace_words(time_scale: float) -> str:
    return "lockstep" if time_scale == 0 else f"x{time_scale:g} real time"


def report(found: dict[str, Any]) -> str:
    inside_run = found["inside"]
    lines = [
        "# Certifying on the robot itself: measured",
        "",
        "Made by `.venv/bin/python scripts/robot_run_trial.py --out results/robot-run` (its arguments in "
        "robot-run.json); numbers from robot-run.json.",
        "",
        "| measurement | result |",
        "|---|---|",
    ]
    lines.append(
        f"| inside (damping x0.55, delay 1, {pace_words(inside_run['time_scale'])}) | certified "
        f"{inside_run['certified']} after {inside_run['episodes']} episodes, {inside_run['expert_calls']} expert "
        f"calls, {inside_run['robot_time_s']} s robot time, {inside_run['wall_s']} s wall, "
        f"{len(inside_run['faults'])} faults, {inside_run['late_commands']} late commands |"
    )
    if "held_out" in inside_run:
        h = inside_run["held_out"]
        lines.append(
            f"| its policy on that robot, {h['starts']} fresh starts | {h['successes']} succeed (lower "
            f"bound {h['lower_bound_90']} at 90%) |"
        )
    if "from_set" in found:
        f = found["from_set"]
        lines.append(
            f"| the same robot, starting from the set run's {f['started_with']} trajectories | certified "
            f"{f['certified']} after {f['episodes']} episodes, {f['expert_calls']} expert calls, "
            f"{f['robot_time_s']} s robot time"
            + (f"; its policy {f['held_out']['successes']} of {f['held_out']['starts']}" if "held_out" in f else "")
            + " |"
        )
    if "set" in found:
        h = found["set"]
        lines.append(
            f"| the set-certified policy ({h['run']}) on that robot, the same starts | {h['successes']} "
            f"succeed (lower bound {h['lower_bound_90']}) |"
        )
    c = found["corner"]
    lines.append(
        f"| corner (mass x1.2, gear x0.8, damping x1.5, delay 1) | certified {c['certified']} in "
        f"{c['episodes']} episodes ({c['expert_calls']} expert calls); said: {c['unreachable']} |"
    )
    d = found["disturbed"]
    lines.append(
        f"| lockstep, states stopped 1 s and the robot restarted | {d['episodes_identical']} of "
        f"{d['episodes_compared']} episodes identical to the undisturbed run's; faults "
        f"{d['disturbed']['faults']}; certified {d['undisturbed']['certified']} / "
        f"{d['disturbed']['certified']} |"
    )
    for row in found["pace"]:
        lines.append(
            f"| x{row['time_scale']:g} real time | {row['late_commands']} of {row['steps']} commands late "
            f"({row['late_share']:.2%}), {row['faults']} faults |"
        )
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("results/robot-run"), help="where the figures go")
    parser.add_argument("--runs", type=Path, default=Path("runs/robot-run"), help="where the run folders go")
    parser.add_argument(
        "--time-scale",
        type=float,
        default=0.0,
        help="the robot's speed against real time in the inside, from_set and corner runs (0: lockstep)",
    )
    parser.add_argument("--held-out", type=int, default=200, help="fresh starts for the held-out checks")
    parser.add_argument(
        "--set-run",
        type=Path,
        default=Path("runs/per-robot/pendulum-u1-s0"),
        help="a run certified on the pendulum's set, whose policy is checked on the same robot",
    )
    parser.add_argument("--corner-episodes", type=int, default=200, help="episodes the corner robot gets")
    parser.add_argument("--disturbed-episodes", type=int, default=30, help="episodes of each lockstep run")
    parser.add_argument("--scales", type=float, nargs="+", default=[1.0, 5.0, 10.0, 20.0, 40.0])
    parser.add_argument("--pace-episodes", type=int, default=4, help="episodes at each time scale")
    parser.add_argument("--only", nargs="+", choices=("inside", "set", "from_set", "corner", "disturbed", "pace"))
    args = parser.parse_args(argv)
    args.runs.mkdir(parents=True, exist_ok=True)
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "robot-run.json"
    found: dict[str, Any] = json.loads(path.read_text()) if path.exists() else {}
    arguments = {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()}
    steps = {
        "inside": lambda: inside(args.runs, args.time_scale, args.held_out),
        "set": lambda: set_policy(args.set_run, args.held_out),
        "from_set": lambda: inside(args.runs, args.time_scale, args.held_out, args.set_run),
        "corner": lambda: corner(args.runs, args.time_scale, args.corner_episodes),
        "disturbed": lambda: disturbed(args.runs, args.disturbed_episodes),
        "pace": lambda: pace(args.runs, args.scales, args.pace_episodes),
    }
    for name in args.only or steps:
        say(f"{name} ...")
        found[name] = steps[name]()
        found.setdefault("arguments", {})[name] = arguments  # what made each measurement
        path.write_text(json.dumps(found, indent=2) + "\n")
    if all(name in found for name in steps):
        (args.out / "robot-run.md").write_text(report(found))
    say(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
