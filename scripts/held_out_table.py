"""A table of finished npp-learn runs, with the held-out success an oracle run's summary does not give.

For each run folder: whether it certified, its episodes and expert calls, and its held-out check (summary.json,
from npp-learn --evaluate N: the share of N fresh s0 whose gap to the expert is within epsilon); then the policy
the certificate names (all the run's data where none) is rolled out again from the same N held-out s0 (the
stream npp-learn draws them from; --held-out N for a run made with --evaluate 0) and judged by the task's
[success]. The exact model only (no --uncertainty).

    .venv/bin/python scripts/held_out_table.py /work/exp/rotary-seed0 /work/exp/rotary-seed1 --out table.md
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from npp_ros.deployment.gate import Acceptance, load_deployment
from npp_ros.run.held_out import LEARN_HELD_OUT_STREAM, check_success, held_out_states


def row(run_dir: Path, held_out: int) -> dict[str, object]:
    summary = json.loads((run_dir / "summary.json").read_text())
    evaluation = summary.get("evaluation") or {}
    deployment = load_deployment(run_dir, Acceptance(override=True))  # an uncertified run: all its data
    meta = deployment.metadata
    if meta.uncertainty:
        raise SystemExit(f"{run_dir}: a run on a set of robots; this table checks the exact model only")
    count = int(evaluation.get("rollouts", held_out))
    success = None
    if count:
        states = held_out_states(deployment.task, int(meta.seed), count, LEARN_HELD_OUT_STREAM)
        check = check_success(deployment.policy, deployment.task, deployment.plant, states, int(meta.horizon),
                              p=0.9, delta=0.05)  # fmt: skip
        success = check.succeeded
    return {
        "run": str(run_dir), "seed": summary["seed"], "certified": summary["certificate"] is not None,
        "ended": summary.get("ended"), "episodes": summary["episodes"], "expert_calls": summary["oracle_calls"],
        "held_out": count, "succeeded": success,
        "within_epsilon": round(evaluation["fraction_within_epsilon"] * count) if evaluation else None,
        "gap_median": evaluation.get("true_gap_median"), "gap_max": evaluation.get("true_gap_max"),
        "wall_s": summary.get("wall_time_s"),
    }  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="finished npp-learn run folders")
    parser.add_argument("--held-out", type=int, default=1000, help="held-out s0 where a run was not checked on any")
    parser.add_argument("--out", type=Path, default=None, help="also write the table and rows (.json) here")
    args = parser.parse_args()
    rows = [row(run_dir, args.held_out) for run_dir in args.runs]
    lines = [
        "| seed | certified | episodes | expert calls | held-out within epsilon | held-out success | run wall time |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        n = r["held_out"]
        within = "-" if r["within_epsilon"] is None else f"{r['within_epsilon']}/{n}"
        success = "-" if r["succeeded"] is None else f"{r['succeeded']}/{n}"
        wall = "-" if r["wall_s"] is None else f"{float(r['wall_s']) / 60:.1f} min"
        certified = "yes" if r["certified"] else f"no ({r['ended']})"
        lines.append(
            f"| {r['seed']} | {certified} | {r['episodes']} | {r['expert_calls']} | {within} | {success} | {wall} |"
        )
    print("\n".join(lines))
    if args.out is not None:
        args.out.write_text("\n".join(lines) + "\n")
        args.out.with_suffix(".json").write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
