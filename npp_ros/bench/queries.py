"""The policy's query cost at a robot arm's scale: V_lb / V_ub over 10^4 .. 10^6 points of a task's own state.

The LQR cases of npp-bench are 4-D and 12-D; a 7-joint arm's state (the Panda reaching task's: joint angles,
target, their velocities) is 20 entries. This part of npp-bench (``--only queries``) stores up to 10^6 of them,
the states a run meets: a run folder's expert data first (``--query-run``, read with ``read_run``), then states
of rollouts on the task's plant from s0 ~ rho under the torques that hold the arm where it is plus small noise
(:class:`~npp_ros.tasks.task_file.loader.GravityHold`), each point valued by its rollout's own return-to-go, so that
V_lb's max over Q_i - L|s - s_i| is decided by values and distances both, not by distance alone.

At each size it times, on queries near fresh rollouts (states no point of the index holds): the index build,
a batch of queries, and each query alone (p50 / p90 / p99 / max of one call, what a control loop at the task's
period waits for), for V_lb, V_ub and both, at the run's L and at L = 1e10 (where V_lb is close to 1-NN), beside
pykdtree and cKDTree 1-NN on the same points and queries; and checks the index against brute force.
"""

from __future__ import annotations

import argparse
import gc
import os
import time
from collections.abc import Callable
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before pykdtree loads its OpenMP runtime

import numpy as np
from scipy.spatial import cKDTree

from npp_ros.bench.measure import Progress, PyKDTree, exactness, per_query_us, prefix, summary
from npp_ros.certificate.choices import DATA_ANSWERS, DATA_FACTOR
from npp_ros.policy.compression import index_report
from npp_ros.policy.dataset import Dataset, FloatArray
from npp_ros.policy.kdtree import BoundIndex
from npp_ros.run.read import Run
from npp_ros.run.setup import data_slope
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.sources import short_name
from npp_ros.tasks.task import Task
from npp_ros.tasks.task_file.loader import GravityHold

DEFAULT_QUERY_TASK = "examples/panda_reach/task.toml"
DEFAULT_QUERY_SIZES = (10_000, 100_000, 1_000_000)
QUICK_QUERY_POINTS = 4_000  # --quick: no size above this (above the index's 2,048-point tail: one tree)
ROLLOUT_NOISE = 0.02  # torque noise per step, this share of each actuator's half range: 1.6 Nm of the Panda's 80
LARGE_LIPSCHITZ = 1e10  # distance outweighs any value difference: V_lb (nearly) the nearest point's value
QUERY_STRIDE = 10  # every 10th state of a fresh rollout is a query ...
QUERY_JITTER = 1e-2  # ... moved by this share of the data's spread, entry by entry (zero where the data never moves)
BOUNDS = ("lower", "upper", "both")
BOUND_LABELS = {"lower": "V_lb", "upper": "V_ub", "both": "both"}
TREES = ("pykdtree", "ckdtree")


# ----------------------------------------------------------------------------- points
class HoldingController:
    """The torques that hold the arm still where it is, plus Gaussian noise: cheap, and it stays near rho.

    A plant without a MuJoCo model (none to ask for gravity) gets zero torque plus the noise.
    """

    def __init__(self, plant: Any, noise: float, rng: np.random.Generator) -> None:
        low, high = np.asarray(plant.action_low, float), np.asarray(plant.action_high, float)
        finite = np.isfinite(low) & np.isfinite(high)
        self.low, self.high = low, high
        self.scale = noise * np.where(finite, (high - low) / 2, 1.0)
        physics = getattr(plant, "physics", None)
        self.hold: Callable[[FloatArray], FloatArray] = (
            GravityHold(physics.model.ptr, low, high) if physics is not None else (lambda _x: np.zeros(len(low)))
        )
        self.rng = rng

    def __call__(self, raw: FloatArray) -> FloatArray:
        u = self.hold(raw) + self.scale * self.rng.standard_normal(len(self.scale))
        return np.clip(u, self.low, self.high)


def rollout(
    task: Task, plant: Any, control: HoldingController, horizon: int, rng: np.random.Generator
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """One rollout from a fresh s0 ~ rho: its stored states, actions and return-to-go (undiscounted)."""
    states = np.empty((horizon, task.state_dim))
    actions = np.empty((horizon, task.action_dim))
    rewards = np.empty(horizon)
    states[0] = plant.reset(task.sample_initial_state(rng))
    for t in range(horizon):
        if t:
            states[t] = plant.state()
        actions[t] = control(plant.raw_state())
        rewards[t] = plant.step(actions[t])
    return states, actions, np.cumsum(rewards[::-1])[::-1]


def arm_points(
    task: Task, size: int, horizon: int, seed: int, run: Run | None, progress: Progress
) -> tuple[Dataset, dict[str, Any]]:
    """``size`` points: the run's stored data first (states, actions, values; no gains), then rollouts' states."""
    data = Dataset(task.state_dim, task.action_dim, capacity=size + horizon)
    from_run = 0
    if run is not None:
        stored = run.dataset
        offsets = stored.trajectory_offsets
        for k in range(stored.num_trajectories):
            if len(data) >= size:
                break
            lo, hi = offsets[k], offsets[k + 1]
            data.append_arrays(stored.states[lo:hi], stored.actions[lo:hi], stored.values[lo:hi])
        from_run = len(data)
    plant = task.make_plant(seed)
    rng = np.random.default_rng(seed)
    control = HoldingController(plant, ROLLOUT_NOISE, rng)
    first_rollout = data.num_trajectories
    count, tick, cpu = 0, time.perf_counter(), time.process_time()
    while len(data) < size:
        data.append_arrays(*rollout(task, plant, control, horizon, rng))
        count += 1
        if count % 1000 == 0:
            progress.note(f"{count:,d} rollouts, {len(data):,d} points ({time.perf_counter() - tick:.0f}s)")
    seconds, cpu_seconds = time.perf_counter() - tick, time.process_time() - cpu
    made = len(data) - from_run
    source = {
        "run_points": from_run, "run_trajectories": first_rollout, "rollouts": count, "horizon": horizon,
        "rollout_points": made, "seconds": seconds, "cpu_seconds": cpu_seconds,
        "steps_per_s": made / seconds if seconds > 0 else float("nan"),
        "controller": f"gravity-holding torques (GravityHold) + N(0, ({ROLLOUT_NOISE:g} x half range)^2) per step",
        "values": "each rollout's own return-to-go (undiscounted sum of the task's rewards from the step on)",
    }  # fmt: skip
    progress.step(f"{short_name(task.name)}: {len(data):,d} points ({from_run:,d} from the run, {count:,d} rollouts "
                  f"of {horizon} steps in {seconds:.0f}s, {source['steps_per_s']:.0f} steps/s)")  # fmt: skip
    return data, source


def fresh_queries(task: Task, horizon: int, count: int, seed: int, spread: FloatArray) -> FloatArray:
    """Every QUERY_STRIDE-th state of rollouts from another stream, jittered: near the data, never in it."""
    plant = task.make_plant(seed + 10_000)
    rng = np.random.default_rng(seed + 10_000)
    control = HoldingController(plant, ROLLOUT_NOISE, rng)
    chunks: list[FloatArray] = []
    while sum(len(c) for c in chunks) < count:
        chunks.append(rollout(task, plant, control, horizon, rng)[0][::QUERY_STRIDE])
    out = np.concatenate(chunks)[:count]
    return out + QUERY_JITTER * spread[None, :] * rng.standard_normal(out.shape)


def query_lipschitz(data: Dataset, first_rollout: int, given: float | None, run: Run | None) -> dict[str, Any]:
    """The L the policy would use: given, else the run's, else the 'data' rule over the first rollouts."""
    if given is not None:
        return {"value": float(given), "source": "user", "detail": "--query-lipschitz"}
    if run is not None:
        meta = run.metadata
        return {"value": float(meta.lipschitz), "source": str(meta.lipschitz_source),  # type: ignore[arg-type]
                "detail": f"the run's ({run.folder.name})"}  # fmt: skip
    offsets = data.trajectory_offsets
    first = Dataset(data.state_dim, data.action_dim)
    for k in range(first_rollout, min(first_rollout + DATA_ANSWERS, data.num_trajectories)):
        first.append_arrays(*(a[offsets[k] : offsets[k + 1]] for a in (data.states, data.actions, data.values)))
    pair = data_slope(first, continued=False)
    if pair is None or not pair.slope > 0:
        raise ValueError("the rollouts' values show no slope: give --query-lipschitz")
    return {"value": DATA_FACTOR * pair.slope, "source": "data",
            "detail": f"{DATA_FACTOR:g} x the steepest slope of the first {first.num_trajectories} rollouts' "
                      f"return-to-go, as L = 'data' does with expert answers ({pair.describe()})"}  # fmt: skip


# ----------------------------------------------------------------------------- timing
def latencies(fn: Callable[[FloatArray], object], rows: list[FloatArray]) -> tuple[list[float], list[float]]:
    """Wall and this thread's CPU microseconds of each call alone (the CPU clock outside the wall one)."""
    wall, cpu = [], []
    for row in rows:
        c0 = time.thread_time_ns()
        w0 = time.perf_counter_ns()
        fn(row)
        w1 = time.perf_counter_ns()
        c1 = time.thread_time_ns()
        wall.append((w1 - w0) / 1e3)
        cpu.append((c1 - c0) / 1e3)
    return wall, cpu


def latency_summary(wall: list[float], cpu: list[float]) -> dict[str, Any]:
    """Percentiles of one-call latency: wall time (what the loop waits) and CPU time (without preemption)."""
    w, c = np.asarray(wall), np.asarray(cpu)
    p50, p90, p99 = (float(x) for x in np.percentile(w, [50, 90, 99]))
    return {"calls": len(w), "p50_us": p50, "p90_us": p90, "p99_us": p99, "max_us": float(w.max()),
            "mean_us": float(w.mean()), "cpu_p50_us": float(np.percentile(c, 50)),
            "cpu_p99_us": float(np.percentile(c, 99))}  # fmt: skip


def bound_calls(index: BoundIndex) -> dict[str, Callable[[FloatArray], object]]:
    """V_lb, V_ub and both (the gap's two searches, one after the other) as one call each."""
    return {"lower": lambda q: index.search(q, True), "upper": lambda q: index.search(q, False),
            "both": lambda q: (index.search(q, True), index.search(q, False))}  # fmt: skip


def tree_calls(trees: dict[str, Any]) -> dict[str, Callable[[FloatArray], object]]:
    calls: dict[str, Callable[[FloatArray], object]] = {}
    for label, tree in trees.items():
        if label == "pykdtree":
            calls[label] = lambda q, tree=tree: tree.query(q, k=1)
        else:
            calls[label] = lambda q, tree=tree: tree.query(q, k=1, workers=1)
    return calls


def time_calls(
    calls: dict[str, Callable[[FloatArray], object]], single: FloatArray, batch: FloatArray, repeats: int
) -> tuple[dict[str, dict[str, Any]], dict[str, dict[str, Any]]]:
    """One-call latency percentiles over ``single`` x ``repeats`` calls and batched per-query medians.

    The methods take turns within each repeat, so a change of the machine's load hits every one alike.
    """
    rows = [q[None, :].copy() for q in single]
    for fn in calls.values():  # warm-up: caches, page faults, lazy loads
        latencies(fn, rows[:20])
        fn(batch)
    wall: dict[str, list[float]] = {key: [] for key in calls}
    cpu: dict[str, list[float]] = {key: [] for key in calls}
    batched: dict[str, list[float]] = {key: [] for key in calls}
    for _ in range(repeats):
        for key, fn in calls.items():
            gc.collect()
            w, c = latencies(fn, rows)
            wall[key] += w
            cpu[key] += c
            batched[key].append(per_query_us(lambda fn=fn: fn(batch), len(batch)))
    return ({key: latency_summary(wall[key], cpu[key]) for key in calls},
            {key: summary(batched[key]) for key in calls})  # fmt: skip


def nearest_agreement(index: BoundIndex, tree: Any, queries: FloatArray) -> int:
    """How many queries V_lb answers with the point pykdtree (or cKDTree) calls nearest."""
    _, picked = index.search(queries, True)
    _, nearest = tree.query(queries, k=1)
    return int(np.sum(picked == np.asarray(nearest, dtype=np.int64)))


# ----------------------------------------------------------------------------- one size
def query_size(
    data: Dataset, size: int, lipschitz: list[tuple[str, float]], queries: FloatArray, args: argparse.Namespace,
    progress: Progress,
) -> dict[str, Any]:  # fmt: skip
    """Build times, latencies, batched costs and exactness at ``size`` points, for each L and both trees.

    Every index and tree is built first and then timed in one round, so that they take turns and a change of
    the machine's load hits them alike.
    """
    sub = data if size == len(data) else prefix(data, size)
    points = np.ascontiguousarray(sub.states)
    single, batch, check = queries[: args.single], queries[: args.queries], queries[: args.check]
    row: dict[str, Any] = {"points": size, "trees": {}, "lipschitz": []}
    trees: dict[str, Any] = {}
    for label, build in (("pykdtree", PyKDTree), ("ckdtree", cKDTree)):
        if build is None:
            continue
        tick = time.perf_counter()
        trees[label] = build(points, leafsize=16)
        row["trees"][label] = {"build_s": time.perf_counter() - tick}
    indices: dict[str, BoundIndex] = {}
    calls = tree_calls(trees)
    for label, L in lipschitz:
        tick = time.perf_counter()
        indices[label] = BoundIndex(sub, L)  # the policy's own: compression on
        indices[label].sync()
        kept = index_report(indices[label])
        row["lipschitz"].append({"label": label, "value": L, "build_s": time.perf_counter() - tick,
                                 "kept_lower": kept.kept_lower, "kept_upper": kept.kept_upper})  # fmt: skip
        calls.update({f"{label}/{bound}": fn for bound, fn in bound_calls(indices[label]).items()})
    built = ", ".join(f"L {e['label']} {e['build_s']:.2f}s" for e in row["lipschitz"])
    progress.step(f"{size:>9,d} points: indices built ({built}), pykdtree "
                  f"{row['trees'].get('pykdtree', {}).get('build_s', float('nan')):.2f}s")  # fmt: skip
    latency, batched = time_calls(calls, single, batch, args.repeats)
    for label in trees:
        row["trees"][label].update(single=latency[label], batch=batched[label])
    base = row["trees"]["pykdtree" if "pykdtree" in trees else "ckdtree"]
    for entry in row["lipschitz"]:
        label = entry["label"]
        entry["single"] = {bound: latency[f"{label}/{bound}"] for bound in BOUNDS}
        entry["batch"] = {bound: batched[f"{label}/{bound}"] for bound in BOUNDS}
        entry["ratios"] = {bound: {
            "batch": entry["batch"][bound]["median_us"] / base["batch"]["median_us"],
            "single_p50": entry["single"][bound]["p50_us"] / base["single"]["p50_us"],
            "single_p99": entry["single"][bound]["p99_us"] / base["single"]["p99_us"],
        } for bound in BOUNDS}  # fmt: skip
    lb = row["lipschitz"][0]["single"]["lower"]
    progress.step(f"{size:>9,d} points timed: V_lb (L {row['lipschitz'][0]['label']}) p50 {lb['p50_us']:.1f}us, "
                  f"p99 {lb['p99_us']:.1f}us; pykdtree p50 {base['single']['p50_us']:.1f}us, "
                  f"p99 {base['single']['p99_us']:.1f}us")  # fmt: skip
    nearest = trees["pykdtree" if "pykdtree" in trees else "ckdtree"]
    for entry in row["lipschitz"]:
        index = indices[entry["label"]]
        entry["exact"] = exactness(index, sub, entry["value"], check)
        entry["same_point_as_1nn"] = nearest_agreement(index, nearest, check)
    exact = all(e["exact"]["exact"] for e in row["lipschitz"])
    progress.step(f"{size:>9,d} points: exact on {len(check)} queries at every L: {exact}")
    return row


def query_steps(args: argparse.Namespace) -> int:
    """Progress steps of the queries part: the points, then per size the trees and each L."""
    return 1 + 3 * len(args.query_sizes)


def query_section(args: argparse.Namespace, run: Run | None, progress: Progress, command: str) -> dict[str, Any]:
    """The whole measurement at every ``--query-sizes`` on ``--query-task``'s state (the run's data first)."""
    started = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
    load_start = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    task = get_task(args.query_task)
    horizon = int(run.metadata.horizon) if run is not None else task.default_horizon  # type: ignore[arg-type]
    sizes = sorted(set(args.query_sizes))
    data, source = arm_points(task, max(sizes), horizon, args.seed, run, progress)
    spread = data.states.std(axis=0)
    count = max(args.queries, args.single, args.check)
    queries = fresh_queries(task, horizon, count, args.seed, spread)
    lip = query_lipschitz(data, source["run_trajectories"], args.query_lipschitz, run)
    plant = task.make_plant(args.seed)
    # warm-up of the compiled kernels (numba's cache load), kept out of the first build's time
    small = prefix(data, min(len(data), 600))
    BoundIndex(small, lip["value"], tail_limit=100).search(queries[:1], True)
    rows = [query_size(data, size, [("policy", lip["value"]), ("large", LARGE_LIPSCHITZ)], queries, args, progress)
            for size in sizes]  # fmt: skip
    moving = int(np.sum(spread > 0))
    return {
        "command": command, "date": started, "load_average_start": load_start,
        "load_average_end": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "task": short_name(task.name), "state_dim": task.state_dim, "moving_entries": moving,
        "control_period_s": float(plant.dt), "run": None if run is None else run.folder.name,
        "points": source, "lipschitz": lip, "large_lipschitz": LARGE_LIPSCHITZ,
        "queries": {"batch": min(count, args.queries), "single": min(count, args.single), "repeats": args.repeats,
                    "checked": min(count, args.check), "stride": QUERY_STRIDE, "jitter": QUERY_JITTER},
        "sizes": rows,
        "exact": all(entry["exact"]["exact"] for row in rows for entry in row["lipschitz"]),
    }  # fmt: skip
