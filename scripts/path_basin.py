"""How far from a stored s0 one expert trajectory still carries the policy, and how far rho's s0 lie from the data.

Usage: .venv/bin/python scripts/path_basin.py RUN_DIR [RUN_DIR ...] [--trajectories 4] [--radii 0.01,0.03,0.1,0.3]

A certificate needs the policy within epsilon of the expert on 90% of rho. Over a stored trajectory alone, the
run's policy (its kind and L, the task's control space) is rolled out from s0' = s_k + delta u, for the first
``--trajectories`` trajectories k, each radius delta and ``--directions`` unit directions u (in the policy's
distance: angles wrapped, invariant entries left out) pointing at fresh s0 ~ rho, so s0' lies where rho puts its
starts. Each rollout is judged against that trajectory's stored H-step value at s_k (the expert's return from
there; the expert's from s0' is not asked for: no expert call is made) and by the task's success criterion. At
delta 0 the policy replays its expert.

Then the data against rho: for ``--starts`` fresh s0, the distance to the nearest stored s0 and to the nearest
stored state (the policy chooses among every stored state), in the same distance. Where fresh s0 lie farther
from the data than the basin reaches, more trajectories are what the policy lacks.

``--tvlqr Q:R`` (Q one weight per state entry, comma separated; R one number) also follows each path with gains
of its own: a time-varying LQR computed along the stored path on the task's plant (finite-difference A_t, B_t,
tracking cost diag(Q), R I, no actuator limits in the Riccati pass; the action is still clamped). Rows say which
gains they used. Where the expert's gains are 0 on clamped actions, these are not: if the path still does not
carry the policy with them, no linear tracking law about that path will.

Fresh s0 come from npp-learn's held-out stream of the run's seed (npp_ros.run.held_out.held_out_states).
Prints markdown; ``--out FILE`` also writes it with the rows as FILE.json. The exact model only.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from npp_ros.policy.dataset import Dataset, Trajectory
from npp_ros.policy.feedback import ControlSpace
from npp_ros.run.held_out import LEARN_HELD_OUT_STREAM, held_out_states
from npp_ros.run.read import read_run
from npp_ros.run.setup import policy_for, task_control_space
from npp_ros.tasks.registry import task_label
from npp_ros.tasks.rollout import rollout_batch


def single(path: Trajectory) -> Dataset:
    """The dataset holding ``path`` alone."""
    out = Dataset(path.states.shape[1], path.actions.shape[1], capacity=max(len(path), 1))
    out.append(path)
    return out


def tvlqr_gains(plant: object, space: ControlSpace, path: Trajectory, q: list[float], r: float) -> np.ndarray:
    """K_t of the LQR tracking ``path`` on ``plant``: A_t, B_t by forward differences of one control step, then the
    backward Riccati pass from P_T = diag(q) with cost diag(q), r I (the same for every step)."""
    states, actions = path.states, path.actions
    steps, n, m = len(states), states.shape[1], actions.shape[1]
    step = 1e-5

    def next_state(state: np.ndarray, action: np.ndarray) -> np.ndarray:
        plant.reset(state)
        plant.step(action)
        return np.asarray(plant.state())

    a_mats, b_mats = np.zeros((steps, n, n)), np.zeros((steps, n, m))
    for t in range(steps):
        base = next_state(states[t], actions[t])
        for i in range(n):
            moved = states[t].copy()
            moved[i] += step
            a_mats[t, :, i] = space.difference(next_state(moved, actions[t])[None], base[None])[0] / step
        for j in range(m):
            pushed = actions[t].copy()
            pushed[j] += step
            b_mats[t, :, j] = space.difference(next_state(states[t], pushed)[None], base[None])[0] / step
    cost_q, cost_r = np.diag(q), r * np.eye(m)
    riccati, gains = cost_q.copy(), np.zeros((steps, m, n))
    for t in range(steps - 1, -1, -1):
        bp = b_mats[t].T @ riccati
        gains[t] = -np.linalg.solve(cost_r + bp @ b_mats[t], bp @ a_mats[t])
        closed = a_mats[t] + b_mats[t] @ gains[t]
        riccati = cost_q + gains[t].T @ cost_r @ gains[t] + closed.T @ riccati @ closed
    return gains


def nearest(probe: np.ndarray, points: np.ndarray, space: ControlSpace) -> np.ndarray:
    """Each probe's distance to the nearest of ``points`` in the policy's distance (angles wrapped, invariant
    entries left out; a plain KD-tree would miss the +-pi seam)."""
    measured = list(space.measured)
    out = np.empty(len(probe))
    for i, state in enumerate(probe):
        diff = space.difference(np.broadcast_to(state, points.shape).copy(), points)
        out[i] = np.min(np.linalg.norm(diff[:, measured], axis=1))
    return out


def basin(
    run_dir: Path,
    trajectories: int,
    radii: list[float],
    directions: int,
    starts: int,
    tvlqr: tuple[list[float], float] | None,
) -> dict[str, object]:
    run = read_run(run_dir)
    if run.robots is not None:
        raise SystemExit(f"{run_dir}: a run on a set of robots; this measures the exact model only")
    task, seed, horizon = run.task, int(run.metadata.seed), int(run.metadata.horizon)
    name = str(run.metadata.task)
    space = task_control_space(name, seed)
    measured = list(space.measured)
    data, epsilon = run.dataset, float(run.spec.epsilon)
    offsets = np.asarray(data.trajectory_offsets)
    s0 = data.states[offsets[:-1]]  # every stored trajectory's first state
    fresh = held_out_states(task, seed, max(directions, starts), LEARN_HELD_OUT_STREAM)
    rows = []
    for k in range(min(trajectories, data.num_trajectories)):
        path = data.trajectory(k)
        paths = {"expert": path}
        if tvlqr is not None:
            paths["tvlqr"] = replace(path, gains=tvlqr_gains(task.make_plant(seed), space, path, *tvlqr))
        toward = space.difference(fresh[:directions].copy(), np.broadcast_to(s0[k], (directions, s0.shape[1])))
        norms = np.linalg.norm(toward[:, measured], axis=1)
        units = toward[norms > 0] / norms[norms > 0, None]
        reference = float(data.values[offsets[k]])
        for gains_of, followed in paths.items():
            print(f"{run_dir.name}: trajectory {k}, {gains_of} gains", file=sys.stderr)
            policy = policy_for(single(followed), run.spec, name, seed)
            for radius in [0.0, *radii]:
                starts_k = s0[k] + radius * units if radius > 0 else s0[k][None, :]
                runs = rollout_batch(task.make_plant(seed), policy.controller(), starts_k, horizon)
                gaps = np.array([reference - run.total_return for run in runs])
                met = [bool(task.success.met(run.states)) for run in runs] if task.success is not None else []
                rows.append(
                    {
                        "trajectory": k,
                        "gains": gains_of,
                        "radius": radius,
                        "rollouts": len(runs),
                        "within_epsilon": int(np.sum(gaps <= epsilon)),
                        "succeeded": int(sum(met)) if met else None,
                        "gap_median": float(np.median(gaps)),
                    }
                )
    low, high = np.asarray(space.action_low), np.asarray(space.action_high)
    limited = np.isfinite(low) & np.isfinite(high)
    span = np.where(limited, high - low, 1.0)
    at_limit = np.any(limited & ((data.actions <= low + 1e-3 * span) | (data.actions >= high - 1e-3 * span)), axis=1)
    gains = data.gains.reshape(len(data), -1) if data.trajectories_with_gains else np.zeros((len(data), 1))
    open_loop = ~np.any(gains != 0.0, axis=1)
    probe = fresh[:starts]
    nearest_s0 = nearest(probe, s0, space)
    nearest_state = nearest(probe, data.states, space)
    return {
        "run": str(run_dir),
        "task": task_label(name),
        "seed": seed,
        "horizon": horizon,
        "epsilon": epsilon,
        "policy": run.spec.policy,
        "stored_trajectories": data.num_trajectories,
        "rows": rows,
        "fresh_s0": len(probe),
        "expert_steps_at_limit": float(np.mean(at_limit)),
        "expert_steps_without_gains": float(np.mean(open_loop)),
        "nearest_stored_s0": {"median": float(np.median(nearest_s0)), "p90": float(np.quantile(nearest_s0, 0.9))},
        "nearest_stored_state": {
            "median": float(np.median(nearest_state)),
            "p90": float(np.quantile(nearest_state, 0.9)),
        },
    }


def basin_rows(rows: list[dict[str, object]]) -> list[str]:
    """The markdown table of ``rows``: per gains and distance, counts summed over trajectories (and runs)."""
    lines = [
        "| gains | distance from the stored s0 | within epsilon of the stored return | success | gap median |",
        "|---|---|---|---|---|",
    ]
    for gains_of in dict.fromkeys(r["gains"] for r in rows):
        for radius in sorted({float(r["radius"]) for r in rows}):
            at = [r for r in rows if r["radius"] == radius and r["gains"] == gains_of]
            n = sum(int(r["rollouts"]) for r in at)
            within = sum(int(r["within_epsilon"]) for r in at)
            succeeded = [r["succeeded"] for r in at]
            success = "-" if None in succeeded else f"{sum(int(x) for x in succeeded)}/{n}"
            gap = float(np.median([float(r["gap_median"]) for r in at]))
            lines.append(f"| {gains_of} | {radius:g} | {within}/{n} | {success} | {gap:.1f} |")
    return lines


def pooled(results: list[dict[str, object]]) -> list[str]:
    """One table over every run given (same task): what a single run's handful of trajectories cannot settle."""
    rows = [row for result in results for row in result["rows"]]
    seeds = ", ".join(str(result["seed"]) for result in results)
    return [f"### {results[0]['task']}, seeds {seeds} pooled", "", *basin_rows(rows), ""]


def table(result: dict[str, object]) -> list[str]:
    rows = result["rows"]
    assert isinstance(rows, list)
    head = (
        f"### {result['task']}, seed {result['seed']}: the {result['policy']} policy over one stored trajectory "
        f"(epsilon {result['epsilon']:g}, H {result['horizon']})"
    )
    lines = [head, "", *basin_rows(rows)]
    s0, state = result["nearest_stored_s0"], result["nearest_stored_state"]
    assert isinstance(s0, dict) and isinstance(state, dict)
    lines += [
        "",
        f"{result['fresh_s0']} fresh s0 against the run's {result['stored_trajectories']} stored trajectories: "
        f"nearest stored s0 median {s0['median']:.3f} (90% within {s0['p90']:.3f}); nearest stored state median "
        f"{state['median']:.3f} (90% within {state['p90']:.3f}). The expert's stored actions are at the actuator's "
        f"limit (within 0.1% of its range) on {100 * float(result['expert_steps_at_limit']):.0f}% of stored steps; "
        f"its feedback gains are 0 "
        f"(the path is replayed open loop there) on {100 * float(result['expert_steps_without_gains']):.0f}%.",
        "",
    ]
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run_dirs", type=Path, nargs="+", help="finished run folders (their run.sqlite)")
    ap.add_argument("--trajectories", type=int, default=4, help="stored trajectories to start near (the first ones)")
    ap.add_argument("--radii", default="0.01,0.03,0.1,0.3", help="distances from the stored s0, comma separated")
    ap.add_argument("--directions", type=int, default=10, help="directions per trajectory and distance")
    ap.add_argument("--starts", type=int, default=1000, help="fresh s0 for the distance to the data")
    ap.add_argument(
        "--tvlqr", default="", help="also follow each path with TVLQR gains of cost Q:R (e.g. 1,1,0.1,0.1:0.01)"
    )
    ap.add_argument("--out", type=Path, default=None, help="also write the tables here, and the rows as .json")
    args = ap.parse_args()
    radii = [float(r) for r in args.radii.split(",")]
    tvlqr = None
    if args.tvlqr:
        weights, _, control = args.tvlqr.partition(":")
        if not control:
            raise SystemExit(
                f"--tvlqr takes Q:R (state weights, comma separated: one control weight), got {args.tvlqr!r}"
            )
        tvlqr = ([float(w) for w in weights.split(",")], float(control))
    results = [
        basin(run_dir, args.trajectories, radii, args.directions, args.starts, tvlqr) for run_dir in args.run_dirs
    ]
    lines = [line for result in results for line in table(result)]
    if len(results) > 1 and len({result["task"] for result in results}) == 1:
        lines += pooled(results)
    text = "\n".join(lines)
    print(text)
    if args.out is not None:
        args.out.write_text(text + "\n")
        args.out.with_suffix(".json").write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
