"""Measure the Panda reaching expert under the settings its task file chose, and under each one changed back.

The file examples/panda_reach/task.toml sets four things of its iLQR expert: ``warm_start = "gravity"``, the
offset's Gauss-Newton Hessian on its distance term, ``control_weight = 1e-6`` and ``velocity_weight = 3e-2``.
For each variant (the file as shipped; each of those keys set back) this answers the same requests, from s0 of
rho drawn with seeds 1..N, and records per request the iterations and how they ended, the wall time, and over
the last 0.5 s the hand's largest distance from the target and its largest speed, and whether [success] held.

    .venv/bin/python scripts/panda_expert_settings.py --requests 5 --out results/panda-reach/expert
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
from pathlib import Path

import numpy as np

from npp_ros.tasks.registry import get_task

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "panda_reach"
VARIANTS = {
    "as shipped": [],
    'hessian = "distance"': [('hessian = "offset"', 'hessian = "distance"')],
    "control_weight = 1e-5": [("control_weight = 1e-6", "control_weight = 1e-5")],
    "velocity_weight = 1e-4 (the default)": [("velocity_weight = 3e-2", "velocity_weight = 1e-4")],
    'warm_start = "zero"': [('warm_start = "gravity"', 'warm_start = "zero"')],
}


def variant_file(folder: Path, edits: list[tuple[str, str]]) -> Path:
    text = (EXAMPLE / "task.toml").read_text().replace('model = "scene.xml"', f'model = "{EXAMPLE / "scene.xml"}"')
    for old, new in edits:
        assert old in text, old
        text = text.replace(old, new, 1)
    path = folder / "task.toml"
    path.write_text(text)
    return path


def measure(path: Path, requests: int) -> list[dict[str, object]]:
    task = get_task(str(path))
    assert task.success is not None
    distance, speed = task.success.holds.bands  # type: ignore[attr-defined]
    window = task.success.steps
    expert = task.make_expert(0, task.default_horizon)
    rows = []
    for seed in range(1, requests + 1):
        s0 = task.sample_initial_state(np.random.default_rng(seed))
        solution = expert.solve(s0)
        states = solution.trajectory.states
        rows.append({
            "seed": seed,
            "iterations": solution.optimization.iterations,
            "stop": solution.optimization.stop_reason,
            "seconds": round(solution.optimization.wall_time, 2),
            "start_distance_m": round(float(distance.values(states[:1])[0]), 4),
            "last_distance_max_m": round(float(distance.values(states[-window:]).max()), 4),
            "last_speed_max_m_s": round(float(speed.values(states[-window:]).max()), 4),
            "success": task.success.met(states),
        })  # fmt: skip
        print(path.parent.name, rows[-1], flush=True)
    return rows


def iterations(row: dict[str, object]) -> str:
    """A request's iterations, with how iLQR stopped when it did not converge."""
    return f"{row['iterations']}" if row["stop"] == "converged" else f"{row['iterations']} ({row['stop']})"


def report(results: dict[str, list[dict[str, object]]], requests: int) -> str:
    lines = [
        "# The Panda reaching expert: its settings, each set back",
        "",
        f"`.venv/bin/python scripts/panda_expert_settings.py --requests {requests}`: the same {requests} requests "
        "(s0 of rho, seeds 1..N) per variant, one process, one core; seconds are wall time on a shared machine.",
        "",
        "| variant | success | iterations | seconds, median | hand distance, last 0.5 s (max) | "
        "hand speed, last 0.5 s (max) |",
        "|---|---|---|---|---|---|",
    ]
    for name, rows in results.items():
        its = ", ".join(iterations(r) for r in rows)
        lines.append(
            f"| {name} | {sum(bool(r['success']) for r in rows)} of {len(rows)} | {its} | "
            f"{statistics.median(float(r['seconds']) for r in rows):.1f} | "  # type: ignore[arg-type]
            f"{max(float(r['last_distance_max_m']) for r in rows) * 1000:.1f} mm | "  # type: ignore[arg-type]
            f"{max(float(r['last_speed_max_m_s']) for r in rows):.3f} m/s |"  # type: ignore[arg-type]
        )
    lines += ["", "An iteration count without a note converged; the others say how iLQR stopped instead.", ""]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--requests", type=int, default=5, help="requests per variant")
    parser.add_argument("--out", type=Path, default=Path("results/panda-reach/expert"), help="output folder")
    parser.add_argument("--render", action="store_true", help="only write the table again from OUT's json")
    args = parser.parse_args()
    if args.render:
        results = json.loads((args.out / "expert-settings.json").read_text())
        (args.out / "expert-settings.md").write_text(report(results, len(next(iter(results.values())))))
        return
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for k, (name, edits) in enumerate(VARIANTS.items()):
            folder = Path(tmp) / f"variant-{k}"
            folder.mkdir()
            results[name] = measure(variant_file(folder, edits), args.requests)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "expert-settings.json").write_text(json.dumps(results, indent=1) + "\n")
    (args.out / "expert-settings.md").write_text(report(results, args.requests))
    print(f"wrote {args.out / 'expert-settings.md'}")


if __name__ == "__main__":
    main()
