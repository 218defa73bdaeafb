"""Returns against expert calls, one figure per task, for the policies of several npp-experiment results folders.

    .venv/bin/python scripts/policy_figures.py --out results/policies \\
        open-loop=results/cartpole feedback=results/cartpole-feedback ...

Each LABEL=FOLDER is one npp-experiment output. Where the folder still holds its run folders (``runs/``, kept
on the machine that ran it, not committed), every evaluation checkpoint is plotted: the median over seeds of
the policy's median return on the evaluation s0, at the median number of expert calls the run had made by then
(every call counts: in oracle mode one per episode, plus any asked where the policy went). Otherwise only the
folder's final figures (results.json) are plotted, as one point. The expert's median return is the dashed line.
Writes OUT/<task>.png and OUT/policies.json (every plotted number, with its folder).
"""

from __future__ import annotations

import argparse
import csv
import json
from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from npp_ros.run.store import RunStore


def checkpoints(folder: Path) -> dict[str, list[tuple[float, float, float]]]:
    """task -> [(expert calls, policy return, expert return)] per checkpoint, medians over seeds."""
    by_task: dict[str, dict[int, list[tuple[int, float, float]]]] = defaultdict(lambda: defaultdict(list))
    for run in sorted((folder / "runs").glob("*-seed*")):
        evaluations = run / "evaluations.csv"
        if not evaluations.is_file():
            continue
        with RunStore.open(run / "run.sqlite") as store:
            task, rows, explore = store.metadata.task, store.episodes(), float(store.metadata.explore)
        task = f"{task}|explore {explore:g}" if explore else task  # its own series beside the arm without
        per_checkpoint: dict[int, list[tuple[float, float]]] = defaultdict(list)
        with evaluations.open() as fh:
            for row in csv.DictReader(fh):
                per_checkpoint[int(row["checkpoint"])].append(
                    (float(row["policy_return"]), float(row["expert_return"]))
                )
        for checkpoint, returns in per_checkpoint.items():
            calls = rows[min(checkpoint, len(rows)) - 1].oracle_calls
            policy, expert = np.median([r[0] for r in returns]), np.median([r[1] for r in returns])
            by_task[task][checkpoint].append((calls, float(policy), float(expert)))
    out = {}
    for task, points in by_task.items():
        out[task] = [
            (float(np.median([p[0] for p in seeds])), float(np.median([p[1] for p in seeds])),
             float(np.median([p[2] for p in seeds])))
            for _, seeds in sorted(points.items())
        ]  # fmt: skip
    return out


def final_points(folder: Path) -> dict[str, list[tuple[float, float, float]]]:
    """task -> [(median oracle calls, median policy return, median expert return)] from results.json."""
    records = json.loads((folder / "results.json").read_text())
    by_task: dict[str, list[dict]] = defaultdict(list)
    for record in records:
        by_task[record["task"]].append(record)
    return {
        task: [tuple(float(np.median([r[key] for r in rs]))
                     for key in ("oracle_calls", "policy_return_q50", "expert_return_q50"))]
        for task, rs in by_task.items()
    }  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("series", nargs="+", metavar="LABEL=FOLDER", help="a label and an npp-experiment output folder")
    ap.add_argument("--out", type=Path, default=Path("results/policies"))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    plotted: dict[str, dict[str, dict]] = defaultdict(dict)
    for item in args.series:
        label, _, folder = item.partition("=")
        path = Path(folder)
        curves = checkpoints(path) if (path / "runs").is_dir() else {}
        source = "checkpoints"
        if not curves:
            curves, source = final_points(path), "final"
        for key, points in curves.items():
            task, _, arm = key.partition("|")
            plotted[task][f"{label}, {arm}" if arm else label] = {"folder": folder, "from": source, "points": points}
    for task, series in plotted.items():
        fig, ax = plt.subplots(figsize=(6.4, 4.0))
        expert = []
        for label, data in series.items():
            calls, policy, experts = zip(*data["points"], strict=True)
            ax.plot(calls, policy, marker="o", label=f"{label} policy")
            expert += experts
        ax.axhline(float(np.median(expert)), color="k", linestyle="--", linewidth=1, label="expert (median)")
        ax.set_xscale("log")
        ax.set_xlabel("expert calls (median over seeds)")
        ax.set_ylabel("median return on the evaluation s0")
        ax.set_title(task)
        ax.legend(loc="center right", fontsize=8)
        fig.tight_layout()
        fig.savefig(args.out / f"{task}.png", dpi=120)
        plt.close(fig)
        print(f"wrote {args.out / f'{task}.png'}")
    (args.out / "policies.json").write_text(json.dumps(plotted, indent=1) + "\n")


if __name__ == "__main__":
    main()
