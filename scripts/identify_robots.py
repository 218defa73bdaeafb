"""Robots identified from their own motion, and the certified policy checked at each before it moves, measured.

For each hidden robot (5 inside the pendulum's set of robots, its corners among them, and 3 outside it, plus one
that lies outside in its mass alone), ``--seconds`` of motion are made in process: the certified run's policy drives
the plant made into that robot from rest (hanging down), its delay and ``--noise`` on the states read applied by
RobotEffects, with the multisine excitation of npp_ros.identification.excitation added to its commands.
npp_ros.identification.fit then identifies the set's parameters from the recording alone; the table compares the
identifiable combinations with the hidden robot's, and the delay. For the robots named in ``--check``, the certified
policy is then simulated at the identified region (npp_ros.identification.check) and the verdict against ``--p``
recorded.

    .venv/bin/python scripts/identify_robots.py --run RUN --out results/identification

RUN is a certified pendulum_swingup run made with ``--uncertainty 1`` (see results/identification/README.md).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

import npp_ros
from npp_ros.identification.check import check_before_move
from npp_ros.identification.excitation import multisine
from npp_ros.identification.fit import identify
from npp_ros.identification.recording import record_motion
from npp_ros.tasks.uncertainty import Robot


def pendulum(mass: float, gear: float, damping: float, delay: int, noise: float, seed: int) -> Robot:
    return Robot((("mass", "pole", mass), ("gear", "torque", gear), ("damping", "hinge", damping)), delay, noise, seed)


# name -> (mass, gear, damping, delay, where it lies)
ROBOTS: dict[str, tuple[float, float, float, int, str]] = {
    "nominal": (1.0, 1.0, 1.0, 0, "inside"),
    "central": (0.95, 1.05, 1.1, 1, "inside"),
    "corner-heavy-weak-damped": (1.2, 0.8, 1.5, 1, "inside (corner)"),
    "corner-light-strong-free": (0.8, 1.2, 0.5, 0, "inside (corner)"),
    "corner-heavy-strong-free": (1.2, 1.2, 0.5, 1, "inside (corner)"),
    "weak-motor": (1.0, 0.6, 1.0, 0, "outside: gear x0.6"),
    "stiff-joint": (1.0, 1.0, 2.5, 0, "outside: damping x2.5"),
    "late": (1.0, 1.0, 1.0, 2, "outside: delay 2"),
    "heavy": (1.5, 1.0, 1.0, 0, "outside: mass x1.5 (its motion is an inside robot's)"),
}


def truth(robot: Robot, labels: list[str]) -> list[float]:
    """The hidden robot's value of each combination, from the exponents' labels' parameters."""
    factors = {f"{p}[{n}]": f for p, n, f in robot.scales}
    values = []
    for label in labels:
        top, _, bottom = label.partition(" / ")
        value = math.prod(factors[name] for name in top.split(" * "))
        value /= math.prod(factors[name] for name in bottom.split(" * ")) if bottom else 1.0
        values.append(value)
    return values


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", type=Path, required=True, help="a certified pendulum_swingup run folder (uncertainty 1)")
    ap.add_argument("--out", type=Path, required=True, help="where results.json and results.md go")
    ap.add_argument("--seconds", type=float, default=10.0, help="seconds of motion per robot (default 10)")
    ap.add_argument("--noise", type=float, default=1e-3, help="noise on the states read (default 1e-3)")
    ap.add_argument(
        "--check",
        nargs="*",
        default=["nominal", "central", "corner-heavy-weak-damped"],
        help="robots to run the check before moving on (default: nominal, central, the corner)",
    )
    ap.add_argument("--check-n", type=int, default=200, help="s0 per point of the check (default 200)")
    ap.add_argument("--p", type=float, default=None, help="the check's threshold (default: the run's p)")
    ap.add_argument("--delta-g", type=float, default=0.05, help="the check's level (default 0.05)")
    args = ap.parse_args(argv)
    run = npp_ros.read_run(args.run)
    task = run.task
    robots = run.robots
    if robots is None:
        print(f"{args.run} was certified on the exact model; identification needs a set of robots", file=sys.stderr)
        return 2
    plant = task.make_plant(int(run.metadata.seed))
    policy = run.policy
    excitation = multisine(plant, args.seconds)
    steps = round(args.seconds / plant.dt)
    rows = []
    for index, (name, (mass, gear, damping, delay, where)) in enumerate(ROBOTS.items()):
        hidden = pendulum(mass, gear, damping, delay, args.noise, 100 + index)
        s0 = np.array([math.pi, 0.0])  # at rest, hanging: the swing-up moves it through every speed it will see
        recording = record_motion(plant, hidden, policy.controller(), s0, steps, excitation.apply)
        print(f"{name}: {hidden.describe()}, {steps} steps recorded; identifying", file=sys.stderr, flush=True)
        started = time.perf_counter()
        found = identify(task, recording, robots, seed=int(run.metadata.seed))
        wall = time.perf_counter() - started
        labels = [c.label for c in found.combinations]
        true = truth(hidden, labels)
        errors = [c.value / t - 1 for c, t in zip(found.combinations, true, strict=True)]
        covered = [c.low <= t <= c.high for c, t in zip(found.combinations, true, strict=True)]
        row = {
            "robot": name, "hidden": hidden.describe(), "where": where, "verdict": found.verdict,
            "delay": found.delay, "true_delay": delay, "labels": labels, "true": true,
            "estimate": [c.value for c in found.combinations], "low": [c.low for c in found.combinations],
            "high": [c.high for c in found.combinations], "relative_error": errors, "covered": covered,
            "delay_scores": [d.score for d in found.delays], "reasons": list(found.reasons),
            "unidentifiable": list(found.unidentifiable), "identify_seconds": wall, "transitions": found.transitions,
        }  # fmt: skip
        print(found.summary(), file=sys.stderr, flush=True)
        if name in args.check:
            check = check_before_move(run, found, n=args.check_n, p=args.p, delta_g=args.delta_g,
                                      progress=lambda k, total: print(f"  check: point {k}/{total}", file=sys.stderr,
                                                                      flush=True))  # fmt: skip
            print(check.summary(), file=sys.stderr, flush=True)
            row["check"] = check.record()
        rows.append(row)
    args.out.mkdir(parents=True, exist_ok=True)
    result = {"run": {"task": task.name, "seed": int(run.metadata.seed), "set": robots.describe(),
                      "certificate_p": float(run.spec.p)},
              "seconds": args.seconds, "noise": args.noise, "excitation": "multisine, peak 0.2 of the half range",
              "rows": rows}  # fmt: skip
    (args.out / "results.json").write_text(json.dumps(result, indent=1) + "\n")
    (args.out / "results.md").write_text(table(result))
    print(table(result))
    return 0


def table(result: dict) -> str:
    lines = [
        f"Identification of {result['run']['task']}'s robots from {result['seconds']:g} s of motion each (the "
        f"certified policy plus the excitation, noise {result['noise']:g} on the states read). Set: "
        f"{result['run']['set']}.",
        "",
        "| robot | hidden | where | identified: combination = estimate [95% interval] (true; error) | delay "
        "(true) | verdict | time |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in result["rows"]:
        combos = "<br>".join(
            f"{label} = {est:.4f} [{lo:.4f}, {hi:.4f}] ({true:.4f}; {100 * err:+.2f}%)"
            for label, est, lo, hi, true, err in zip(row["labels"], row["estimate"], row["low"], row["high"],
                                                     row["true"], row["relative_error"], strict=True)
        )  # fmt: skip
        lines.append(f"| {row['robot']} | {row['hidden']} | {row['where']} | {combos} | {row['delay']} "
                     f"({row['true_delay']}) | {row['verdict']} | {row['identify_seconds']:.1f} s |")  # fmt: skip
    checks = [row for row in result["rows"] if "check" in row]
    if checks:
        lines += ["", "The check before it moves (each point of the identified region from the same s0 ~ rho; "
                  "Clopper-Pearson lower bounds, each at delta_g / points):", "",
                  "| robot | verdict | worst point | successes | lower bound | threshold p | delta_g | time |",
                  "|---|---|---|---|---|---|---|---|"]  # fmt: skip
        for row in checks:
            check = row["check"]
            worst = check["worst"]
            verdict = "accepted" if check["accepted"] else "refused"
            lines.append(f"| {row['robot']} | {verdict} | {worst['robot']} | {worst['successes']}/{worst['trials']} "
                         f"| {worst['lower']:.3f} | {check['p']:g} | {check['delta_g']:g} | "
                         f"{check['wall_time']:.0f} s |")  # fmt: skip
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
