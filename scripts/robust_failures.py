"""Why a run's policy fails on robots of its set: each held-out failure, and whether the same draw succeeds without
the robot's delay and on the nominal model.

Rolls the run folder's policy (its certificate's, or its last) out on the held-out (s0, robot) draws npp-learn's
check uses, judges each on the task's success criterion, and prints one line per failure and a count.

    .venv/bin/python scripts/robust_failures.py RUN_FOLDER --draws 300
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from npp_ros import read_run
from npp_ros.run.held_out import LEARN_HELD_OUT_STREAM, held_out_robots, held_out_states
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.rollout import rollout
from npp_ros.tasks.uncertainty import Robot


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run_dir", type=Path, help="a run folder made under model uncertainty (npp-learn --uncertainty)")
    ap.add_argument("--draws", type=int, default=300, help="held-out (s0, robot) draws, as npp-learn --evaluate")
    args = ap.parse_args(argv)
    run = read_run(args.run_dir)
    task, seed = get_task(str(run.metadata.task)), int(run.metadata.seed)
    if task.success is None or not run.metadata.uncertainty:
        ap.error(f"{args.run_dir}: needs a task with a success criterion and a run on a set of robots")
    horizon = int(run.metadata.horizon)
    plant, policy = task.make_plant(seed), run.policy
    states = held_out_states(task, seed, args.draws, LEARN_HELD_OUT_STREAM)
    robots = held_out_robots(str(run.metadata.uncertainty), seed, args.draws)
    assert robots is not None
    counts = {"failed": 0, "succeeds without the delay": 0, "succeeds on the nominal model": 0}
    for k, (s0, robot) in enumerate(zip(states, robots, strict=True)):
        if task.success.met(rollout(plant, policy.controller(), s0, horizon, robot).states):
            continue
        no_delay = task.success.met(rollout(plant, policy.controller(), s0, horizon, Robot(robot.scales)).states)
        nominal = task.success.met(rollout(plant, policy.controller(), s0, horizon).states)
        counts["failed"] += 1
        counts["succeeds without the delay"] += int(no_delay and robot.action_delay > 0)
        counts["succeeds on the nominal model"] += int(nominal)
        print(f"draw {k}: {robot.describe()}; s0 {np.round(s0, 2).tolist()}; without the delay: "
              f"{'met' if no_delay else 'failed'}; nominal model: {'met' if nominal else 'failed'}")  # fmt: skip
    print(f"{args.draws} draws: " + ", ".join(f"{name} {count}" for name, count in counts.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
