"""Whether a robot outside the certified set is found under the certified policy's own commands: the transition
monitor npp-deploy runs (npp_ros.deployment.model_monitor) against identification on a sliding window of the same motion
(npp_ros.identification.fit), robot by robot, in process.

    .venv/bin/python scripts/monitor_windows.py --run RUN_DIR --out results/monitor-windows [--seconds 30]

Each robot drives SECONDS of motion under the run's certified policy alone (no excitation), from s0 ~ rho of its
own stream, with noise on every state read (--noise, at least the set's); both monitors see the recorded states and
commands only. The window identification flags a window when no robot of the set lies within its intervals (verdict
"outside"), and the robot when two windows in a row are flagged. Writes monitor-windows.json and monitor-windows.md
into --out.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from npp_ros.deployment.model_monitor import ModelMonitor
from npp_ros.identification.fit import identify
from npp_ros.identification.recording import record_motion
from npp_ros.run.read import read_run
from npp_ros.tasks.uncertainty import Robot

OUTSIDE = {
    "gear x0.6": Robot((("gear", "torque", 0.6),)),
    "mass x1.5": Robot((("mass", "pole", 1.5),)),
    "delay 2": Robot((), 2),
    "delay 3": Robot((), 3),
    "damping x2.5": Robot((("damping", "hinge", 2.5),)),
}


def first_flag(flags: list[bool], times: list[float], in_a_row: int) -> float | None:
    run = 0
    for flag, at in zip(flags, times, strict=True):
        run = run + 1 if flag else 0
        if run >= in_a_row:
            return at
    return None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, required=True, help="a certified run on a set of robots")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--seconds", type=float, default=30.0, help="motion per robot")
    ap.add_argument("--window", type=float, default=3.0, help="seconds of motion per identification")
    ap.add_argument("--every", type=float, default=1.0, help="seconds between identifications")
    ap.add_argument("--inside", type=int, default=4, help="robots drawn from the set (false alarms)")
    ap.add_argument("--noise", type=float, default=1e-3, help="standard deviation of the noise on each state read")
    args = ap.parse_args(argv)
    run = read_run(args.run)
    assert run.robots is not None, "a run on a set of robots"
    plant = run.task.make_plant(int(run.metadata.seed))
    steps = round(args.seconds / plant.dt)
    robots = dict(OUTSIDE)
    for k in range(args.inside):
        robots[f"drawn {k}"] = run.robots.draw(int(run.metadata.seed), 10_000 + k)
    rows = []
    for index, (name, robot) in enumerate(robots.items()):
        robot = Robot(robot.scales, robot.action_delay, max(args.noise, run.robots.state_noise), index)
        s0 = run.task.initial_state(int(run.metadata.seed), 50_000 + index)
        motion = record_motion(plant, robot, run.policy.controller(), s0, steps)
        monitor = ModelMonitor.of_plant(plant, run.robots)
        hull_at = None
        for t in range(len(motion)):
            monitor.observe(motion.states[t], motion.commands[t])
            if hull_at is None and monitor.outside:
                hull_at = float(motion.times[t])
        flags, ends, spent = [], [], []
        start = 0.0
        while start + args.window <= motion.seconds + 1e-9:
            started = time.perf_counter()
            try:
                found = identify(run.task, motion.window(start, args.window), run.robots, seed=int(run.metadata.seed))
                outside = found.verdict == "outside"
            except ValueError as exc:  # a window identification refuses (too few transitions): no finding
                print(f"monitor_windows: {name}: window at {start:g} s: {exc}", file=sys.stderr)
                outside = False
            spent.append(time.perf_counter() - started)
            flags.append(outside)
            ends.append(start + args.window)
            start += args.every
        window_at = first_flag(flags, ends, 2)
        row = {
            "robot": name, "record": robot.record(), "hull_monitor_found_at_s": hull_at,
            "windows": len(flags), "windows_outside": int(sum(flags)), "window_found_at_s": window_at,
            "identify_s_median": float(np.median(spent)),
        }  # fmt: skip
        rows.append(row)
        print(f"monitor_windows: {name}: hull {hull_at}, windows {sum(flags)}/{len(flags)}, at {window_at}",
              file=sys.stderr)  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "monitor-windows.json").write_text(json.dumps(rows, indent=2) + "\n")
    lines = [
        "# A robot outside the set under the certified policy's own commands: the transition monitor and a sliding "
        "window of identification",
        "",
        f"`.venv/bin/python scripts/monitor_windows.py --run RUN_DIR --out {args.out} --seconds {args.seconds:g} "
        f"--window {args.window:g} --every {args.every:g} --inside {args.inside} --noise {args.noise:g}`, on "
        f"{run.task.name}'s set ({run.robots.describe()}); {args.seconds:g} s of motion per robot under the certified "
        "policy alone, noise on every state read. Times are of the motion; on a robot a finding comes after the fits' "
        "own time too.",
        "",
        "| robot | transition monitor found it at | windows outside | two windows in a row at | identify, median s |",
        "|---|---|---|---|---|",
    ]
    for row in rows:
        hull = "-" if row["hull_monitor_found_at_s"] is None else f"{row['hull_monitor_found_at_s']:.2f} s"
        window = "-" if row["window_found_at_s"] is None else f"{row['window_found_at_s']:.1f} s"
        lines.append(f"| {row['robot']} | {hull} | {row['windows_outside']} of {row['windows']} | {window} | "
                     f"{row['identify_s_median']:.2f} |")  # fmt: skip
    (args.out / "monitor-windows.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
