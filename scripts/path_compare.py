"""The per-step choice against the path policy on the same data: held-out success, no expert call.

Usage: .venv/bin/python scripts/path_compare.py RUN_DIR [RUN_DIR ...] [--starts 200] [--prefixes 1,3,10]

For each run folder, each prefix of its stored trajectories (the data as it was after that many expert calls; 0
or a prefix past the end: all of them) and each policy (feedback: the greedy choice at every step; path:
npp_ros.policy.path), the policy with the run's L is rolled out from ``--starts`` fresh s0 ~ rho (episodes
10^6 + k of the run's stream, never drawn by a run) and judged on the task's success criterion. Both policies see
the same data and the same s0, so the difference is the choice rule alone. Prints one markdown table.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.run.setup import task_control_space
from npp_ros.run.store import RunStore
from npp_ros.tasks.registry import get_task, task_label
from npp_ros.tasks.rollout import rollout_batch

HELD_OUT = 10**6  # episode indices no run reaches


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run_dirs", type=Path, nargs="+", help="run folders (their run.sqlite)")
    ap.add_argument("--starts", type=int, default=200, help="fresh s0 per policy and prefix")
    ap.add_argument("--prefixes", default="1,3,10,0", help="trajectory counts to compare at (0: all)")
    args = ap.parse_args()
    print("| task | seed | trajectories | feedback: success | path: success | feedback / path return (median) |")
    print("|---|---|---|---|---|---|")
    for run_dir in args.run_dirs:
        with RunStore.open(run_dir / "run.sqlite") as store:
            meta, data = store.metadata, store.load_dataset()
        task = get_task(str(meta.task))
        if task.success is None:
            raise SystemExit(f"{run_dir}: its task states no success criterion")
        plant, space = task.make_plant(int(meta.seed)), task_control_space(str(meta.task), int(meta.seed))
        starts = np.array([task.initial_state(int(meta.seed), HELD_OUT + k) for k in range(args.starts)])
        for prefix in (int(p) for p in args.prefixes.split(",")):
            count = data.num_trajectories if prefix <= 0 or prefix > data.num_trajectories else prefix
            held = data.prefix(count)
            cells = []
            returns = []
            for kind in ("feedback", "path"):
                policy = NonparametricPolicy(held, float(meta.lipschitz), control=space, kind=kind)
                runs = rollout_batch(plant, policy.controller(), starts, int(meta.horizon))
                met = sum(bool(task.success.met(run.states)) for run in runs)
                cells.append(f"{met}/{len(runs)}")
                returns.append(float(np.median([run.total_return for run in runs])))
            label = task_label(str(meta.task))
            median = f"{returns[0]:.0f} / {returns[1]:.0f}"
            print(f"| {label} | {meta.seed} | {count} | {cells[0]} | {cells[1]} | {median} |")


if __name__ == "__main__":
    main()
