"""Certify the Panda's reach (or any ``--task``) on several seeds, then check each certificate on fresh draws.

Per seed: ``npp-learn --task examples/panda_reach/task.toml --seed S --certify CLAIM --rule RULE --evaluate 0
--run-dir RUNS/CLAIM-sS`` (its output in RUNS/CLAIM-sS.log; ``--prefix`` names the folders otherwise),
unless that folder already holds the run; then the same command again with ``--evaluate N``, which resumes the
stored run (no new episode, no expert call) and rolls its certified policy out from N held-out starts. The
table: expert calls, episodes, trajectories in the certified policy, the run's wall time (its own closing line),
and the held-out success.

    .venv/bin/python scripts/panda_reach_trial.py --seeds 0 1 2 3 --certify success --rule mixture \\
        --evaluate 1000 --runs runs/panda --out results/panda-reach/success
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
import subprocess
import sys
from pathlib import Path

TASK = "examples/panda_reach/task.toml"
WALL = re.compile(r"run folder\s+.*\(([\d.]+) s\)")


def learn(args: argparse.Namespace, seed: int, evaluate: int, log: Path) -> None:
    run_dir = args.runs / f"{args.prefix or args.certify}-s{seed}"
    command = [sys.executable, "-m", "npp_ros.cli.learn", "--task", args.task, "--seed", str(seed), "--certify",
               args.certify, "--rule", args.rule, "--evaluate", str(evaluate), "--run-dir", str(run_dir)]  # fmt: skip
    if args.uncertainty is not None:
        command += ["--uncertainty", str(args.uncertainty)]
    if args.policy_lipschitz is not None:
        command += ["--policy-lipschitz", args.policy_lipschitz]
    if args.policy is not None:
        command += ["--policy", args.policy]
    if args.max_episodes is not None:
        command += ["--max-episodes", str(args.max_episodes)]
    with log.open("a") as out:
        subprocess.run(command, stdout=out, stderr=subprocess.STDOUT, check=False)


def seed_row(args: argparse.Namespace, seed: int) -> dict[str, object]:
    name = f"{args.prefix or args.certify}-s{seed}"
    run_dir, log = args.runs / name, args.runs / f"{name}.log"
    if not (run_dir / "summary.json").is_file():
        learn(args, seed, 0, log)
    first = WALL.search(log.read_text()) if log.is_file() else None
    learn(args, seed, args.evaluate, args.runs / f"{name}-evaluate.log")
    summary = json.loads((run_dir / "summary.json").read_text())
    certificate = summary.get("certificate") or {}
    evaluation = summary.get("evaluation") or {}
    return {
        "seed": seed,
        "ended": summary.get("ended"),
        "oracle_calls": summary.get("oracle_calls"),
        "episodes": summary.get("episodes"),
        "policy_trajectories": certificate.get("policy_trajectories"),
        "wall_time_s": float(first.group(1)) if first else None,
        "held_out": evaluation,
    }


def held_out_words(evaluation: dict[str, object]) -> str:
    if "succeeded" in evaluation and "rollouts" in evaluation:
        return f"{evaluation['succeeded']} of {evaluation['rollouts']}"
    if "fraction_within_epsilon" in evaluation and "rollouts" in evaluation:
        return f"{float(evaluation['fraction_within_epsilon']):.1%} of {evaluation['rollouts']} within epsilon"  # type: ignore[arg-type]
    return json.dumps(evaluation)


def report(args: argparse.Namespace, rows: list[dict[str, object]]) -> str:
    command = " ".join("RUNS" if arg == str(args.runs) else arg for arg in sys.argv[1:])  # the runs' folder, named
    robots = "" if args.uncertainty is None else f" on its set of robots (--uncertainty {args.uncertainty:g})"
    name = "The Panda's reach" if args.task == TASK else args.task
    lines = [f"# {name}: the {args.certify} claim{robots}, {len(rows)} seeds", "",
             f"`.venv/bin/python scripts/panda_reach_trial.py {command}`", "",
             "| seed | ended | expert calls | episodes | trajectories in the policy | wall time | held-out success |",
             "|---|---|---|---|---|---|---|"]  # fmt: skip
    for r in rows:
        wall = "" if r["wall_time_s"] is None else f"{float(r['wall_time_s']) / 60:.1f} min"  # type: ignore[arg-type]
        lines.append(f"| {r['seed']} | {r['ended']} | {r['oracle_calls']} | {r['episodes']} | "
                     f"{r['policy_trajectories']} | {wall} | {held_out_words(r['held_out'])} |")  # type: ignore[arg-type]  # fmt: skip
    calls = [int(r["oracle_calls"]) for r in rows if r["ended"] == "certified"]  # type: ignore[call-overload]
    if calls:
        lines += ["", f"Certified {len(calls)} of {len(rows)}; median expert calls {statistics.median(calls):g}."]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default=TASK, help="the task (default: the Panda's reach); any task npp-learn takes")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3])
    parser.add_argument("--certify", default="success", choices=("success", "oracle"))
    parser.add_argument("--rule", default="mixture", choices=("sequential", "mixture"))
    parser.add_argument("--uncertainty", type=float, default=None, help="the set of robots' factor (default: none)")
    parser.add_argument("--evaluate", type=int, default=1000, help="held-out (start, target) draws per certificate")
    parser.add_argument("--runs", type=Path, default=Path("runs/panda"), help="where the run folders go")
    parser.add_argument("--policy", default=None, help="how the policy acts (default: the task's)")
    parser.add_argument(
        "--policy-lipschitz", default=None, choices=("claim", "select"), help="the policy's L (default: npp-learn's)"
    )
    parser.add_argument("--max-episodes", type=int, default=None, help="stop uncertified after this many episodes")
    parser.add_argument("--prefix", default="", help="the run folders' names: PREFIX-sSEED (default: the claim)")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    args = parser.parse_args()
    args.runs.mkdir(parents=True, exist_ok=True)
    rows = [seed_row(args, seed) for seed in args.seeds]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "trial.json").write_text(json.dumps(rows, indent=1) + "\n")
    (args.out / "trial.md").write_text(report(args, rows))
    print((args.out / "trial.md").read_text())


if __name__ == "__main__":
    main()
