"""The policies on the same data and the same fresh s0: held-out success and return, and gap to the expert if asked.

Usage: .venv/bin/python scripts/path_compare.py RUN_DIR [RUN_DIR ...] [--starts 200] [--prefixes 1,3,10]
       [--kinds feedback,path] [--lipschitz 4300,1000] [--expert N]

For each run folder, each prefix of its stored trajectories (the data as it was after that many expert calls; 0
or a prefix past the end: all of them) and each policy kind (open-loop: the stored action at the greedy choice;
feedback: the greedy choice at every step, with its expert's gains; path: npp_ros.policy.path), the policy with
the run's L (or each L of ``--lipschitz``: the L the policy chooses by, which an oracle claim does
not rest on) is rolled out from ``--starts`` fresh s0 ~ rho (episodes 10^6 + k of the run's stream, never drawn by
a run) and judged on the task's success criterion and its return. Every kind sees the same data and the same s0,
so a difference is the way the policy acts alone. With ``--expert N`` the task's expert (its default options) is
asked from the first N of those s0 too, and each policy's share within the run's epsilon of the expert's H-step
return is given: the oracle claim's quantity, on held-out s0 (the JSON rows list the s0 outside it, with their
gaps). Prints one markdown table; ``--out FILE`` also
writes it, with the rows as FILE.json.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from npp_ros.policy.feedback import check_policy_kind
from npp_ros.run.progress import Counter
from npp_ros.run.read import read_run
from npp_ros.run.setup import policy_for
from npp_ros.tasks.registry import task_label
from npp_ros.tasks.rollout import rollout_batch

HELD_OUT = 10**6  # episode indices no run reaches


def compare(
    run_dir: Path, starts: int, prefixes: list[int], kinds: list[str], lipschitz: list[float], asked: int
) -> list[dict[str, object]]:
    run = read_run(run_dir)
    if run.robots is not None:
        raise SystemExit(f"{run_dir}: a run on a set of robots; this compares on the exact model only")
    task, seed, horizon, name = run.task, int(run.metadata.seed), int(run.metadata.horizon), str(run.metadata.task)
    plant = task.make_plant(seed)
    states = np.array([task.initial_state(seed, HELD_OUT + k) for k in range(starts)])
    reference = None
    if asked:
        expert = task.make_expert(seed, horizon)
        asking = Counter(f"{run_dir.name}: the expert's returns")
        reference = np.asarray(task.expert_returns(expert, plant, states[:asked], horizon, asking, None))
    rows: list[dict[str, object]] = []
    for prefix in prefixes:
        count = run.dataset.num_trajectories if prefix <= 0 or prefix > run.dataset.num_trajectories else prefix
        data = run.dataset.prefix(count)
        for kind, value in ((k, v) for k in kinds for v in lipschitz or [run.spec.lipschitz.value]):
            spec = replace(run.spec, policy=kind, lipschitz=replace(run.spec.lipschitz, value=value))
            print(f"{run_dir.name}: {kind} policy, L {value:g}, {count} trajectories, {starts} s0", file=sys.stderr)
            runs = rollout_batch(plant, policy_for(data, spec, name, seed).controller(), states, horizon)
            returns = np.array([r.total_return for r in runs])
            met = None if task.success is None else sum(bool(task.success.met(r.states)) for r in runs)
            within, outside = None, []
            if reference is not None:
                gaps = reference - returns[:asked]
                within = int(np.sum(gaps <= float(run.spec.epsilon)))
                outside = [
                    [*states[k].tolist(), float(gaps[k])] for k in np.flatnonzero(gaps > float(run.spec.epsilon))
                ]
            rows.append({
                "task": task_label(name), "seed": seed, "trajectories": count, "policy": kind, "lipschitz": value,
                "starts": starts,
                "succeeded": met, "return_median": float(np.median(returns)), "asked": asked, "within_epsilon": within,
                "epsilon": float(run.spec.epsilon),
                "expert_return_median": None if reference is None else float(np.median(reference)),
                "outside_epsilon": outside,  # [s0..., gap] of each asked s0 the policy missed by more than epsilon
            })  # fmt: skip
    return rows


def table(rows: list[dict[str, object]]) -> str:
    lines = [
        "| task | seed | trajectories | policy | L | success | return (median) | within epsilon of the expert |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        success = "-" if r["succeeded"] is None else f"{r['succeeded']}/{r['starts']}"
        within = "-"
        if r["within_epsilon"] is not None:
            within = f"{r['within_epsilon']}/{r['asked']} (expert's median {r['expert_return_median']:.0f})"
        lines.append(
            f"| {r['task']} | {r['seed']} | {r['trajectories']} | {r['policy']} | {r['lipschitz']:g} | {success} | "
            f"{r['return_median']:.0f} | {within} |"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run_dirs", type=Path, nargs="+", help="run folders (their run.sqlite)")
    ap.add_argument("--starts", type=int, default=200, help="fresh s0 per policy and prefix")
    ap.add_argument("--prefixes", default="1,3,10,0", help="trajectory counts to compare at (0: all)")
    ap.add_argument("--kinds", default="feedback,path", help="policy kinds: open-loop, feedback, path")
    ap.add_argument("--lipschitz", default="", help="L values to choose by, comma separated (default: the run's)")
    ap.add_argument("--expert", type=int, default=0, help="ask the expert from the first N s0 (gap within epsilon)")
    ap.add_argument("--out", type=Path, default=None, help="also write the table here, and the rows as .json")
    args = ap.parse_args()
    kinds = [check_policy_kind(k) for k in args.kinds.split(",")]
    prefixes = [int(p) for p in args.prefixes.split(",")]
    lipschitz = [float(v) for v in args.lipschitz.split(",") if v]
    asked = min(args.expert, args.starts)
    rows = [
        row for run_dir in args.run_dirs for row in compare(run_dir, args.starts, prefixes, kinds, lipschitz, asked)
    ]
    text = table(rows)
    print(text)
    if args.out is not None:
        args.out.write_text(text + "\n")
        args.out.with_suffix(".json").write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
