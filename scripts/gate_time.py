"""What the deployment gate costs on a run folder: load_deployment with and without deriving the run again from its
seed, side by side, several times each (median, min, max), and the re-derivation's verdict.

    .venv/bin/python scripts/gate_time.py RUN_DIR [RUN_DIR ...] --repeats 3 --out results/gate-time

Writes gate-time.json and gate-time.md into --out (the run folders named by their last component only).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

from npp_ros.deployment.gate import Acceptance, load_deployment
from npp_ros.run.read import read_run


def timed(run_dir: Path, acceptance: Acceptance, repeats: int, *, remembered: bool = False) -> list[float]:
    """Seconds of each gate; each in an empty cache folder of its own (the re-derivation made anew) unless
    ``remembered``, when one first gate fills a cache folder the timed ones then find."""
    seconds = []
    with tempfile.TemporaryDirectory() as shared:
        if remembered:
            os.environ["NPP_ROS_CACHE"] = shared
            load_deployment(run_dir, acceptance)
        for _ in range(repeats):
            with tempfile.TemporaryDirectory() as fresh:
                os.environ["NPP_ROS_CACHE"] = shared if remembered else fresh
                started = time.perf_counter()
                load_deployment(run_dir, acceptance)
                seconds.append(time.perf_counter() - started)
    return seconds


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", type=Path, nargs="+", help="run folders (each holds run.sqlite)")
    ap.add_argument("--repeats", type=int, default=3, help="timings of each arm per run")
    ap.add_argument("--out", type=Path, required=True, help="folder for gate-time.json and gate-time.md")
    args = ap.parse_args(argv)
    rows = []
    for run_dir in args.runs:
        run = read_run(run_dir)
        base = Acceptance(model_fingerprint=str(run.metadata.plant_fingerprint))
        print(f"gate_time: {run_dir.name}: {len(run.episodes)} episodes, {len(run.dataset)} points", file=sys.stderr)
        plain = timed(run_dir, dataclasses.replace(base, rederive=False), args.repeats)
        derived = timed(run_dir, base, args.repeats)
        remembered = timed(run_dir, base, args.repeats, remembered=True)
        verdict = load_deployment(run_dir, base).derived
        rows.append({
            "run": run_dir.name, "task": str(run.metadata.task), "episodes": len(run.episodes),
            "points": len(run.dataset), "trajectories": run.dataset.num_trajectories,
            "without_rederive_s": plain, "with_rederive_s": derived, "remembered_s": remembered, "verdict": verdict,
        })  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "gate-time.json").write_text(json.dumps(rows, indent=2) + "\n")
    lines = [
        "# The gate's time with and without deriving the run again",
        "",
        f"`.venv/bin/python scripts/gate_time.py RUN_DIR ... --repeats {args.repeats} --out {args.out}`; "
        "seconds of load_deployment, median (min-max) of the repeats; the last column is a gate of the same "
        "unchanged file once this machine has derived it again (its agreement remembered in the user's cache).",
        "",
        "| run | task | episodes | points | gate without | gate with re-derivation | added | again, remembered |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        without, with_ = statistics.median(row["without_rederive_s"]), statistics.median(row["with_rederive_s"])
        span = f"({min(row['with_rederive_s']):.2f}-{max(row['with_rederive_s']):.2f})"
        lines.append(
            f"| {row['run']} | {row['task']} | {row['episodes']} | {row['points']} | {without:.2f} | "
            f"{with_:.2f} {span} | {with_ - without:.2f} | {statistics.median(row['remembered_s']):.2f} |"
        )
    (args.out / "gate-time.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
