"""What decides a policy's coverage: success on held-out starts against the expert trajectories it holds, per
policy kind, per distance and per L the policy acts by.

For a run folder, the policy is rebuilt on the run's first k trajectories (k on a doubling schedule up to all of
them), for each policy kind, each distance (the task's own weights; ``plain``: every entry 1; ``spread``: each
entry by the inverse of its spread in the data the policy holds, ControlSpace.weighted_by_spread) and each L of a
grid (multiples of the run's own L, and 1e10, where V_lb's choice is the nearest point), and rolled out from N
held-out starts of the run's seed (npp-learn's held-out stream: starts no run drew); the figure is the share that
met the task's success criterion. No expert is asked anything. The success claim rests on no L, so the L a policy
acts by is free to choose by what it does.

    .venv/bin/python scripts/policy_coverage.py RUN_DIR [RUN_DIR ...] --starts 200 --out results/panda-reach/coverage
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import time
from pathlib import Path

from npp_ros.run.held_out import LEARN_HELD_OUT_STREAM, check_success, held_out_states
from npp_ros.run.loop import make_policy
from npp_ros.run.read import read_run
from npp_ros.run.setup import task_control_space

KINDS = ("feedback", "path", "open-loop")
L_FACTORS = (1.0, 10.0, 100.0)
NEAREST_L = 1e10


def schedule(count: int) -> list[int]:
    sizes = [k for k in (2, 4, 8, 16, 32, 64, 128, 256) if k < count]
    return [*sizes, count]


DISTANCES = ("task", "plain", "spread")


def measure(
    folder: Path, starts: int, kinds: tuple[str, ...], distances: tuple[str, ...], factors: tuple[float, ...]
) -> dict[str, object]:
    run = read_run(folder)
    task = run.task
    seed = int(run.metadata.seed)
    horizon = int(run.metadata.horizon)
    plant = task.make_plant(seed)
    states = held_out_states(task, seed, starts, LEARN_HELD_OUT_STREAM)
    own = float(run.spec.lipschitz.value)
    grid = [own * f if f < NEAREST_L else NEAREST_L for f in factors]
    control = task_control_space(str(run.metadata.task), seed)
    rows = []
    for k in schedule(run.dataset.num_trajectories):
        data = run.dataset.prefix(k)
        spread = control.weighted_by_spread(data.states)  # read off the data the policy holds, no other
        spaces = {"task": control, "plain": dataclasses.replace(control, weights=()), "spread": spread}
        for kind, distance, lipschitz in itertools.product(kinds, distances, grid):
            spec = dataclasses.replace(
                run.spec, policy=kind, lipschitz=dataclasses.replace(run.spec.lipschitz, value=lipschitz)
            )
            policy = make_policy(data, spec, spaces[distance])
            started = time.perf_counter()
            check = check_success(policy, task, plant, states, horizon, p=run.spec.p, delta=run.spec.delta)
            rows.append({"trajectories": k, "policy": kind, "distance": distance, "lipschitz": lipschitz,
                         "succeeded": check.succeeded, "starts": check.states,
                         "seconds": round(time.perf_counter() - started, 1)})  # fmt: skip
            print(folder.name, rows[-1], flush=True)
    certified = None if run.certificate is None else run.certificate.policy_trajectories
    return {"run": folder.name, "seed": seed, "own_lipschitz": own, "certified_trajectories": certified, "rows": rows}


def figure(results: list[dict[str, object]], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kinds = sorted({r["policy"] for res in results for r in res["rows"]})  # type: ignore[attr-defined]
    fig, axes = plt.subplots(1, len(kinds), figsize=(5 * len(kinds), 4), sharey=True, squeeze=False)
    for ax, kind in zip(axes[0], kinds, strict=True):
        for res in results:
            rows = [r for r in res["rows"] if r["policy"] == kind]  # type: ignore[attr-defined]
            for distance, lipschitz in sorted({(r["distance"], r["lipschitz"]) for r in rows}):
                line = [r for r in rows if (r["distance"], r["lipschitz"]) == (distance, lipschitz)]
                label = "L 1e10 (nearest)" if lipschitz >= NEAREST_L else f"L {lipschitz:.3g}"
                ax.plot([r["trajectories"] for r in line], [r["succeeded"] / r["starts"] for r in line], marker="o",
                        linestyle="-" if distance == "task" else "--",
                        label=f"{res['run']}, {distance} distance, {label}")  # fmt: skip
        ax.set_xscale("log", base=2)
        ax.set_xlabel("expert trajectories in the policy")
        ax.set_title(f"{kind} policy")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("success on held-out starts")
    axes[0][-1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "coverage.png", dpi=120)


def report(results: list[dict[str, object]], starts: int, command: str) -> str:
    lines = ["# Coverage: success on held-out starts against expert trajectories, per policy and L", "",
             f"`{command}`", ""]  # fmt: skip
    for res in results:
        lines += [f"## {res['run']} (seed {res['seed']}, the run's own L {res['own_lipschitz']:.4g}, certified "
                  f"with {res['certified_trajectories']} trajectories)", "",
                  "| trajectories | policy | distance | L | success |", "|---|---|---|---|---|"]  # fmt: skip
        for r in res["rows"]:  # type: ignore[attr-defined]
            lines.append(f"| {r['trajectories']} | {r['policy']} | {r['distance']} | {r['lipschitz']:.4g} | "
                         f"{r['succeeded']} of {r['starts']} |")  # fmt: skip
        lines.append("")
    lines += ["![coverage](coverage.png)", ""]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="run folders (npp-learn's --run-dir)")
    parser.add_argument("--starts", type=int, default=200, help="held-out starts per evaluation")
    parser.add_argument("--policies", nargs="+", default=list(KINDS), choices=KINDS, help="policy kinds")
    parser.add_argument("--distances", nargs="+", default=list(DISTANCES), choices=DISTANCES,
                        help="the task's distance weights, plain (every entry 1), and/or spread (each entry "
                        "weighed by the inverse of its spread in the policy's data)")  # fmt: skip
    parser.add_argument("--lipschitz-factors", nargs="+", type=float, default=[*L_FACTORS, NEAREST_L],
                        help="the policy's L as multiples of the run's own (1e10 or more: L = 1e10)")  # fmt: skip
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    args = parser.parse_args()
    results = [
        measure(folder, args.starts, tuple(args.policies), tuple(args.distances), tuple(args.lipschitz_factors))
        for folder in args.runs
    ]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "coverage.json").write_text(json.dumps(results, indent=1) + "\n")
    figure(results, args.out)
    names = " ".join(f"runs/.../{folder.name}" for folder in args.runs)
    factors = " ".join(f"{f:g}" for f in args.lipschitz_factors)
    command = (f".venv/bin/python scripts/policy_coverage.py {names} --starts {args.starts} "
               f"--policies {' '.join(args.policies)} --distances {' '.join(args.distances)} "
               f"--lipschitz-factors {factors}")  # fmt: skip
    (args.out / "coverage.md").write_text(report(results, args.starts, command))
    print(f"wrote {args.out / 'coverage.md'}")


if __name__ == "__main__":
    main()
