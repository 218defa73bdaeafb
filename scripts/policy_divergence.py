"""Where a run's greedy policy leaves its expert's path: rollouts of both from the same fresh s0.

Usage: .venv/bin/python scripts/policy_divergence.py RUN_DIR [--starts 2] [--tolerance 0.05]

For each of ``--starts`` s0 ~ rho (episodes 10^6 + k of the run's stream, never drawn by a run),
the greedy policy over every trajectory the run stored (with the run's L) and the run's task expert
(default options) are rolled out for H steps on the task's plant. It prints both returns, the first
step at which the stored states differ by more than ``--tolerance`` in any entry, and both states
there: what the policy had to do that its data did not show it. It also prints how far the
policy's states are from the nearest stored state (Euclidean, in the stored state): at s0, where
it leaves the expert's path, and the median over its rollout. Far from every stored state, the
policy replays an action made for another state.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.run.store import RunStore
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.rollout import rollout


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run_dir", type=Path, help="a run folder (its run.sqlite)")
    ap.add_argument("--starts", type=int, default=2, help="fresh s0 to roll out from")
    ap.add_argument("--tolerance", type=float, default=0.05, help="largest state difference still on the path")
    args = ap.parse_args()
    with RunStore.open(args.run_dir / "run.sqlite") as store:
        meta, data = store.metadata, store.load_dataset()
    task = get_task(meta.task)
    plant, expert = task.make_plant(meta.seed), task.make_expert(meta.seed, meta.horizon)
    policy = NonparametricPolicy(data, meta.lipschitz)
    stored = cKDTree(data.states)
    print(f"{meta.task} seed {meta.seed}, H {meta.horizon}: greedy policy over {data.num_trajectories} trajectories, "
          f"L {meta.lipschitz:g}")  # fmt: skip
    for k in range(args.starts):
        s0 = task.initial_state(meta.seed, 10**6 + k)
        reference = expert.trajectory(s0)
        ours = rollout(plant, policy.controller(), s0, meta.horizon)
        gap = np.abs(ours.states - reference.states[: meta.horizon]).max(axis=1)
        off = np.flatnonzero(gap > args.tolerance)
        where = int(off[0]) if off.size else meta.horizon
        print(f"s0 {k}: return policy {ours.total_return:.1f}, expert {reference.expert_return:.1f}; "
              f"on the expert's path for {where} steps")  # fmt: skip
        if off.size:
            there = f"expert {np.round(reference.states[where], 3)}, policy {np.round(ours.states[where], 3)}"
            print(f"  step {where}: {there}")
        nearest, _ = stored.query(ours.states)
        left = f"{nearest[where]:.3f}" if off.size else "-"
        print(f"  nearest stored state: at s0 {nearest[0]:.3f}, where the policy leaves the path {left}, "
              f"median over its rollout {np.median(nearest):.3f}")  # fmt: skip


if __name__ == "__main__":
    main()
