"""npp-learn on lqr_2_1 under each stopping rule and mode: episodes, expert calls, wall time.

Usage: .venv/bin/python scripts/compare_rules_lqr.py [--seeds 0 1 2 3] [--certify rollout oracle]
       [--rules sequential mixture] [--runs runs/rules] [--out results/rules]

Each (mode, rule, seed) is one `npp-learn --task lqr_2_1 --seed S --certify MODE --rule RULE
--run-dir RUNS/MODE-RULE-seedS` process with the main job's other settings (epsilon 50, the
analytic L, p = 0.9, delta = 0.1, H = 1000, 100 held-out s0). A run folder that already holds a
summary is read, not run again (its wall time is the one measured when it ran). Writes
OUT/lqr_2_1.md and OUT/lqr_2_1.json.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path
from typing import Any


def run(mode: str, rule: str, seed: int, runs: Path) -> dict[str, Any]:
    """The run's summary.json, running npp-learn first if the folder has none."""
    folder = runs / f"{mode}-{rule}-seed{seed}"
    summary = folder / "summary.json"
    if not summary.is_file():
        command = [sys.executable, "-m", "npp_ros.cli.learn", "--task", "lqr_2_1", "--seed", str(seed),
                   "--certify", mode, "--rule", rule, "--run-dir", str(folder)]  # fmt: skip
        print(" ".join(command[2:]), file=sys.stderr, flush=True)
        subprocess.run(command, check=False, stdout=subprocess.DEVNULL)
    return json.loads(summary.read_text())


def span(values: list[float], digits: int = 0) -> str:
    middle = statistics.median(values)
    return f"{middle:.{digits}f} ({min(values):.{digits}f}-{max(values):.{digits}f})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    ap.add_argument("--certify", nargs="+", default=["rollout", "oracle"], help="checked quantities")
    ap.add_argument("--rules", nargs="+", default=["sequential", "mixture"], help="stopping rules")
    ap.add_argument("--runs", type=Path, default=Path("runs/rules"), help="run folders (resumed if present)")
    ap.add_argument("--out", type=Path, default=Path("results/rules"), help="where the table goes")
    args = ap.parse_args()
    rows: list[dict[str, Any]] = []
    lines = [
        "| certify | rule | certified | episodes (median, range) | expert calls | policy trajectories "
        "| learning wall s | held-out within 50 (worst seed) | per seed: episodes / expert calls |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for mode in args.certify:
        for rule in args.rules:
            summaries = [run(mode, rule, seed, args.runs) for seed in args.seeds]
            certs = [s["certificate"] for s in summaries if s["certificate"]]
            held = [s["evaluation"]["fraction_within_epsilon"] for s in summaries if s.get("evaluation")]
            per_seed = ", ".join(f"{s['episodes']} / {s['oracle_calls']}" for s in summaries)
            lines.append(
                f"| {mode} | {rule} | {len(certs)}/{len(summaries)} | {span([s['episodes'] for s in summaries])} "
                f"| {span([s['oracle_calls'] for s in summaries])} "
                f"| {span([c['policy_trajectories'] for c in certs]) if certs else '-'} "
                f"| {span([s['wall_time_s'] for s in summaries])} "
                f"| {f'{min(held):.0%}' if held else '-'} | {per_seed} |"
            )
            rows += [{"certify": mode, "rule": rule, **s} for s in summaries]
    args.out.mkdir(parents=True, exist_ok=True)
    command = "scripts/compare_rules_lqr.py " + " ".join(sys.argv[1:])
    text = f"lqr_2_1, npp-learn per seed (`{command.strip()}`):\n\n" + "\n".join(lines) + "\n"
    (args.out / "lqr_2_1.md").write_text(text)
    (args.out / "lqr_2_1.json").write_text(json.dumps(rows, indent=1) + "\n")
    print(text)


if __name__ == "__main__":
    main()
