"""Certificates under model uncertainty, measured: npp-learn over tasks, claims, uncertainty factors and seeds.

Each arm is one npp-learn command per seed, run one after another (its run folder under OUT/runs, resumed if
there); the table OUT/results.csv and OUT/README.md say, per run, whether it certified, after how many episodes and
expert calls, and what its held-out check on fresh draws found (of (s0, robot) where the run drew robots).

    .venv/bin/python scripts/robust_certificates.py --out results/robust-certificates --seeds 0 1 2 3
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
NPP_LEARN = REPO / ".venv" / "bin" / "npp-learn"


@dataclass(frozen=True)
class Arm:
    task: str
    certify: str  # success or oracle
    uncertainty: float
    policy: str = "feedback"
    explore: float = 0.0
    rule: str = "sequential"
    expert_model: str = "robot"  # what the expert plans on: each episode's robot, or the nominal model
    options: tuple[str, ...] = ()  # more npp-learn options (a task without the paper's epsilon and L needs them)

    @property
    def name(self) -> str:
        task = Path(self.task).parent.name if self.task.endswith(".toml") else self.task
        extra = f"-explore{self.explore:g}" if self.explore else ""
        extra += "" if self.rule == "sequential" else f"-{self.rule}"
        extra += "" if self.expert_model == "robot" else f"-{self.expert_model}-expert"
        return f"{task}-{self.certify}-u{self.uncertainty:g}-{self.policy}{extra}"

    def command(self, seed: int, run_dir: Path, max_episodes: int, evaluate: int) -> list[str]:
        return [
            str(NPP_LEARN), "--task", self.task, "--seed", str(seed), "--certify", self.certify,
            "--uncertainty", f"{self.uncertainty:g}", "--policy", self.policy, "--explore", f"{self.explore:g}",
            "--rule", self.rule, "--expert-model", self.expert_model,
            "--max-episodes", str(max_episodes), "--evaluate", str(evaluate), "--run-dir", str(run_dir),
            *self.options,
        ]  # fmt: skip


CARTPOLE = ("--epsilon", "130", "--lipschitz", "4300")  # as the cartpole's certified runs (README, Results)
ARMS = {
    "pendulum-success": Arm("pendulum_swingup", "success", 1.0),
    "pendulum-success-exact": Arm("pendulum_swingup", "success", 0.0),
    "pendulum-success-explore": Arm("pendulum_swingup", "success", 1.0, explore=0.15),
    "pendulum-success-half": Arm("pendulum_swingup", "success", 0.5),
    "pendulum-success-mixture": Arm("pendulum_swingup", "success", 1.0, rule="mixture"),
    "pendulum-success-explore-mixture": Arm("pendulum_swingup", "success", 1.0, explore=0.15, rule="mixture"),
    "pendulum-success-mixture-nominal": Arm("pendulum_swingup", "success", 1.0, rule="mixture", expert_model="nominal"),
    "pendulum-success-path-mixture": Arm("pendulum_swingup", "success", 1.0, policy="path", rule="mixture"),
    "acrobot-success-mixture": Arm(
        "acrobot_swingup", "success", 1.0, rule="mixture", options=("--lipschitz", "4300", "--stop-when-unreachable")
    ),
    "cartpole-success-mixture": Arm("cartpole_swingup", "success", 1.0, rule="mixture", options=CARTPOLE),
    "pendulum-oracle": Arm("pendulum_swingup", "oracle", 1.0),
    "cartpole-success": Arm("cartpole_swingup", "success", 1.0, options=CARTPOLE),
    "cartpole-oracle": Arm("cartpole_swingup", "oracle", 1.0, options=CARTPOLE),
    "rotary-oracle-path": Arm(
        "examples/rotary_pendulum/task.toml", "oracle", 0.0, policy="path", options=("--stop-when-unreachable",)
    ),
}


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="results folder (runs/, results.csv, README.md)")
    ap.add_argument("--arms", nargs="+", choices=sorted(ARMS), default=sorted(ARMS), help="which arms to run")
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3])
    ap.add_argument("--max-episodes", type=int, default=1000, help="npp-learn's --max-episodes")
    ap.add_argument("--evaluate", type=int, default=1000, help="held-out draws after each run (npp-learn --evaluate)")
    ap.add_argument(
        "--collect",
        nargs="+",
        type=Path,
        default=None,
        metavar="DIR",
        help="run nothing: gather the rows of earlier --out folders (their results.csv) into OUT, arm by arm",
    )
    return ap


def row_of(arm: Arm, seed: int, summary: dict, command: list[str], wall: float) -> dict[str, object]:
    evaluation = summary.get("evaluation") or {}
    held = evaluation.get("fraction_succeeded", evaluation.get("fraction_within_epsilon"))
    success = summary.get("success") or {}
    return {
        "arm": arm.name, "seed": seed, "certified": summary["certificate"] is not None,
        "episodes": summary["episodes"], "expert_calls": summary["oracle_calls"], "ended": summary.get("ended"),
        "policy_success": f"{success.get('policy_successes')}/{success.get('policy_checked')}",
        "expert_success": f"{success.get('expert_successes')}/{success.get('expert_answers')}",
        "held_out": evaluation.get("rollouts", 0), "held_out_fraction": held,
        "held_out_measure": "success" if "fraction_succeeded" in evaluation else "within epsilon",
        "wall_s": round(wall, 1), "command": " ".join(command).replace(str(REPO) + "/", ""),
    }  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    if args.collect:
        gathered = [row for folder in args.collect for row in csv.DictReader((folder / "results.csv").open())]
        order = {arm.name: k for k, arm in enumerate(ARMS.values())}
        gathered.sort(key=lambda r: (order.get(str(r["arm"]), len(order)), int(r["seed"])))
        for row in gathered:  # as read back: the table's types
            row["certified"] = row["certified"] == "True"
            row["held_out"] = int(row["held_out"])
            row["held_out_fraction"] = float(row["held_out_fraction"]) if row["held_out_fraction"] else 0.0
        write(args.out, gathered)
        return 0
    rows = []
    for key in args.arms:
        arm = ARMS[key]
        for seed in args.seeds:
            run_dir = args.out / "runs" / f"{arm.name}-seed{seed}"
            command = arm.command(seed, run_dir, args.max_episodes, args.evaluate)
            print(f"robust: {arm.name} seed {seed}", file=sys.stderr, flush=True)
            started = time.perf_counter()
            subprocess.run(command, cwd=REPO, stdout=subprocess.DEVNULL, check=False)
            summary_path = run_dir / "summary.json"
            if not summary_path.exists():
                print(f"robust: {arm.name} seed {seed} wrote no summary", file=sys.stderr)
                continue
            rows.append(row_of(arm, seed, json.loads(summary_path.read_text()), command, time.perf_counter() - started))
            write(args.out, rows)
    return 0


def write(out: Path, rows: list[dict[str, object]]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    with (out / "results.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    lines = [
        "# Certificates under model uncertainty",
        "",
        "Written by `scripts/robust_certificates.py`; each row's command reruns it.",
        "",
        "| arm | seed | certified | episodes | expert calls | policy success in checks | expert success | held-out |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        held = "-" if not r["held_out"] else f"{r['held_out_fraction']:.1%} {r['held_out_measure']} of {r['held_out']}"
        lines.append(
            f"| {r['arm']} | {r['seed']} | {'yes' if r['certified'] else 'no (' + str(r['ended']) + ')'} | "
            f"{r['episodes']} | {r['expert_calls']} | {r['policy_success']} | {r['expert_success']} | {held} |"
        )
    (out / "README.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    raise SystemExit(main())
