"""What npp-bench measures: the exact index against 1-NN trees and brute force, any task's expert.

Each function returns plain dicts that :mod:`npp_ros.bench.report` turns into bench.md; npp-bench
(:mod:`npp_ros.cli.bench`) decides what runs.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before pykdtree loads its OpenMP runtime

import numpy as np
from scipy.spatial import cKDTree

from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.compression import compression_report, index_report
from npp_ros.policy.dataset import Dataset, FloatArray
from npp_ros.policy.kdtree import BoundIndex
from npp_ros.tasks.builtin.lqr import LQRExpert, sample_initial_state
from npp_ros.tasks.registry import ExpertOptions, get_task
from npp_ros.tasks.sources import short_name
from npp_ros.trajopt.batch_steps import default_threads
from npp_ros.trajopt.expert import OptimizingExpert
from npp_ros.trajopt.receding import PlanningExpert

try:  # the registry's fastest plain 1-NN tree; the benchmark still runs without it
    from pykdtree.kdtree import KDTree as PyKDTree
except ImportError:  # pragma: no cover - pykdtree is pinned in the dev set
    PyKDTree = None

TARGETS = {"policy": 2.0, "both": 3.0, "4d": 3.0, "brute": 20.0, "pendulum_expert_s": 5.0}
DEFAULT_OUT = Path("results/bench")
EXPERT_TASKS = ("pendulum_swingup", "cartpole_swingup")  # timed by default
TIMEABLE_EXPERT_TASKS = (*EXPERT_TASKS, "acrobot_swingup")  # the acrobot's minutes only when asked for
POLE_ANGLE = {"pendulum_swingup": 0, "cartpole_swingup": 1, "acrobot_swingup": 0}  # upright angle's entry (stored)
EXPERT_TARGET_KEY = {"pendulum_swingup": "pendulum_expert_s"}
EXPERT_PATHS = ("batch", "reference")  # the iLQR expert's code paths (MujocoDynamics.reference)
UPRIGHT_DEGREES = 8.0  # dm_control's pendulum rewards 1 within 8 degrees of upright (its success criterion's band)


# ----------------------------------------------------------------------------- progress and stats
class Progress:
    """One line per step on stderr, with the elapsed time, so a long run shows where it is."""

    def __init__(self, total: int, stream=sys.stderr) -> None:
        self.total, self.done, self.t0, self.stream = total, 0, time.perf_counter(), stream

    def step(self, text: str) -> None:
        self.done += 1
        elapsed = time.perf_counter() - self.t0
        self.stream.write(f"[{self.done:2d}/{self.total}] {elapsed:7.1f}s  {text}\n")
        self.stream.flush()

    def note(self, text: str) -> None:
        self.stream.write(f"          {text}\n")
        self.stream.flush()


def summary(samples: list[float]) -> dict[str, Any]:
    """Median and spread (min, max, relative half-range) of per-query microseconds."""
    arr = np.asarray(samples, dtype=float)
    med = float(np.median(arr))
    return {
        "median_us": med,
        "min_us": float(arr.min()),
        "max_us": float(arr.max()),
        "spread": float((arr.max() - arr.min()) / (2 * med)) if med > 0 else 0.0,
        "samples_us": [float(x) for x in arr],
    }


def per_query_us(fn: Callable[[], object], count: int) -> float:
    t = time.perf_counter()
    fn()
    return (time.perf_counter() - t) / count * 1e6


def single_loop(fn: Callable[[FloatArray], object], queries: FloatArray) -> Callable[[], None]:
    rows = [q[None, :].copy() for q in queries]

    def run() -> None:
        for row in rows:
            fn(row)

    return run


# ----------------------------------------------------------------------------- data
def expert_data(task: str, trajectories: int, seed: int) -> tuple[Dataset, LQRExpert]:
    """Real LQR expert trajectories from s0 ~ rho, H = 1000 points each."""
    expert = LQRExpert(task, 0)
    rng = np.random.default_rng(seed)
    data = Dataset(expert.plant.state_dim, expert.plant.actuators, capacity=trajectories * expert.horizon)
    for _ in range(trajectories):
        data.append(expert.trajectory(sample_initial_state(task, rng)))
    return data, expert


def near_trajectory_queries(expert: LQRExpert, task: str, count: int, seed: int) -> FloatArray:
    """States of fresh expert trajectories (every 50th step), slightly perturbed: what the policy meets."""
    rng = np.random.default_rng(seed + 10_000)
    per = max(1, expert.horizon // 50)
    states = []
    while sum(len(s) for s in states) < count:
        states.append(expert.trajectory(sample_initial_state(task, rng)).states[::50])
    out = np.concatenate(states)[:count]
    scale = 1e-2 * np.abs(out).mean(axis=0, keepdims=True)
    del per
    return out + scale * rng.standard_normal(out.shape)


def prefix(data: Dataset, size: int) -> Dataset:
    out = Dataset(data.state_dim, data.action_dim, capacity=size)
    out.append_arrays(data.states[:size], data.actions[:size], data.values[:size])
    return out


# ----------------------------------------------------------------------------- checks
def exactness(index: BoundIndex, data: Dataset, lipschitz: float, queries: FloatArray) -> dict[str, Any]:
    """Index vs numpy brute force on ``queries``: same values (bit for bit) and same indices."""
    brute = NonparametricPolicy(data, lipschitz, index=False)
    out: dict[str, Any] = {"queries": len(queries)}
    ok = True
    for name, lower in (("lower", True), ("upper", False)):
        value, idx = index.search(queries, lower)
        ref = brute.lower(queries) if lower else brute.upper(queries)
        same_idx = int(np.sum(idx == ref.index))
        same_val = int(np.sum(value == ref.value))
        out[f"{name}_same_index"] = same_idx
        out[f"{name}_same_value"] = same_val
        ok = ok and same_idx == len(queries) and same_val == len(queries)
    out["exact"] = ok
    return out


def tie_case(seed: int, size: int, count: int) -> dict[str, Any]:
    """Integer grid data with L = 1: exact ties everywhere; the index must pick the smallest index."""
    rng = np.random.default_rng(seed)
    data = Dataset(3, 1)
    data.append_arrays(
        rng.integers(-4, 5, size=(size, 3)).astype(float), np.zeros((size, 1)), rng.integers(0, 6, size).astype(float)
    )
    queries = rng.integers(-5, 6, size=(count, 3)).astype(float)
    index = BoundIndex(data, 1.0, tail_limit=max(1, size // 8), leaf_size=4)
    result = exactness(index, data, 1.0, queries)
    scores = data.values[None, :] - np.sqrt(((queries[:, None, :] - data.states[None, :, :]) ** 2).sum(axis=2))
    result["tied_queries_lower"] = int(np.sum((scores == scores.max(axis=1, keepdims=True)).sum(axis=1) > 1))
    return result


def compile_cost() -> dict[str, float]:
    """First build + search in a fresh process with an empty numba cache, then again with it warm."""
    code = (
        "import time; t = time.perf_counter()\n"
        "import numpy as np\n"
        "from npp_ros.policy.dataset import Dataset\n"
        "from npp_ros.policy.kdtree import BoundIndex\n"
        "t_import = time.perf_counter() - t\n"
        "d = Dataset(3, 1); r = np.random.default_rng(0)\n"
        "d.append_arrays(r.normal(size=(600, 3)), np.zeros((600, 1)), r.normal(size=600))\n"
        "t = time.perf_counter(); i = BoundIndex(d, 1.0, tail_limit=100); i.search(np.zeros((1, 3)), True)\n"
        "i.search(np.zeros((1, 3)), False); print(t_import, time.perf_counter() - t)\n"
    )
    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="npp-numba-cache-") as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache}
        for label in ("cold", "warm"):
            res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
            t_import, t_first = (float(x) for x in res.stdout.split())
            out[f"{label}_import_s"] = t_import
            out[f"{label}_first_query_s"] = t_first
    return out


# ----------------------------------------------------------------------------- cases
@dataclass
class Case:
    name: str
    task: str
    dim: int
    points: int
    lipschitz: float
    lipschitz_source: str
    build_s: dict[str, float] = field(default_factory=dict)
    timings: dict[str, dict[str, Any]] = field(default_factory=dict)
    ratios: dict[str, float] = field(default_factory=dict)
    exact: dict[str, Any] = field(default_factory=dict)
    compression: dict[str, Any] = field(default_factory=dict)


def run_case(
    name: str, task: str, data: Dataset, L: float, source: str, queries: FloatArray, args: argparse.Namespace,
    progress: Progress,
) -> Case:  # fmt: skip
    case = Case(name, task, data.state_dim, len(data), L, source)
    points = np.ascontiguousarray(data.states)
    t = time.perf_counter()
    index = BoundIndex(data, L)  # the policy's default: compression on
    index.sync()
    case.build_s["index"] = time.perf_counter() - t
    report = index_report(index)
    case.compression = report.as_dict()
    t = time.perf_counter()
    trees: dict[str, Any] = {"ckdtree": cKDTree(points, leafsize=16)}
    case.build_s["ckdtree"] = time.perf_counter() - t
    if PyKDTree is not None:
        t = time.perf_counter()
        trees["pykdtree"] = PyKDTree(points, leafsize=16)
        case.build_s["pykdtree"] = time.perf_counter() - t
    progress.step(f"{name}: built (index {case.build_s['index']:.2f}s, kept {report.kept_either}/{report.points})")

    single = queries[: args.single]
    nq, ns = len(queries), len(single)
    fns: dict[str, tuple[Callable[[], object], int]] = {
        "index_lower_batch": (lambda: index.search(queries, True), nq),
        "index_upper_batch": (lambda: index.search(queries, False), nq),
        "index_lower_single": (single_loop(lambda q: index.search(q, True), single), ns),
        "index_upper_single": (single_loop(lambda q: index.search(q, False), single), ns),
    }
    for label, tree in trees.items():
        if label == "pykdtree":
            fns[f"{label}_batch"] = (lambda tree=tree: tree.query(queries, k=1), nq)
            fns[f"{label}_single"] = (single_loop(lambda q, tree=tree: tree.query(q, k=1), single), ns)
        else:
            fns[f"{label}_batch"] = (lambda tree=tree: tree.query(queries, k=1, workers=1), nq)
            fns[f"{label}_single"] = (single_loop(lambda q, tree=tree: tree.query(q, k=1, workers=1), single), ns)
    for fn, _ in fns.values():  # warm-up: caches, page faults, lazy loads
        fn()
    samples: dict[str, list[float]] = {key: [] for key in fns}
    for _ in range(args.repeats):
        for key, (fn, count) in fns.items():  # interleaved, so load changes hit every method alike
            samples[key].append(per_query_us(fn, count))
    case.timings = {key: summary(vals) for key, vals in samples.items()}
    for mode in ("batch", "single"):
        base = min(case.timings[f"{t}_{mode}"]["median_us"] for t in trees)
        lo = case.timings[f"index_lower_{mode}"]["median_us"]
        hi = case.timings[f"index_upper_{mode}"]["median_us"]
        case.ratios[f"lower_vs_1nn_{mode}"] = lo / base
        case.ratios[f"both_vs_1nn_{mode}"] = (lo + hi) / base
        case.ratios[f"baseline_{mode}_us"] = base
    progress.step(
        f"{name}: V_lb {case.ratios['lower_vs_1nn_batch']:.2f}x, both {case.ratios['both_vs_1nn_batch']:.2f}x "
        f"the fastest 1-NN (batch)"
    )
    check = queries[: args.check]
    case.exact = exactness(index, data, L, check)
    progress.step(f"{name}: exact on {len(check)} queries: {case.exact['exact']}")
    return case


def run_scaling(
    name: str, data: Dataset, L: float, queries: FloatArray, sizes: list[int], args: argparse.Namespace,
    progress: Progress,
) -> list[dict[str, Any]]:  # fmt: skip
    rows = []
    for size in sizes:
        sub = prefix(data, size)
        index = BoundIndex(sub, L)
        index.sync()
        brute = NonparametricPolicy(sub, L, index=False)
        nb = max(2, min(len(queries), int(args.brute_budget / size)))
        bq = queries[:nb]
        index.search(bq, True)
        brute_s, index_s = [], []
        for _ in range(max(1, args.repeats // 2)):
            brute_s.append(per_query_us(lambda brute=brute, bq=bq: brute.lower(bq), nb))
            index_s.append(per_query_us(lambda index=index: index.search(queries, True), len(queries)))
        exact = exactness(index, sub, L, bq)
        b, i = summary(brute_s), summary(index_s)
        rows.append({
            "case": name, "points": size, "brute_queries": nb, "brute": b, "index": i,
            "speedup": b["median_us"] / i["median_us"], "exact": exact,
        })  # fmt: skip
        progress.step(f"{name} {size:>9,d} points: brute {b['median_us']:.0f}us, index {i['median_us']:.1f}us "
                      f"({rows[-1]['speedup']:.0f}x), exact {exact['exact']}")  # fmt: skip
    return rows


def machine_info() -> dict[str, Any]:
    cpu = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass

    def version(pkg: str) -> str:
        try:
            return metadata.version(pkg)
        except metadata.PackageNotFoundError:
            return "absent"

    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "usable_cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "machine": platform.machine(),
        "system": f"{platform.system()} {platform.release()}",
        "python": platform.python_version(),
        "numpy": np.__version__,
        "numba": version("numba"),
        "scipy": version("scipy"),
        "pykdtree": version("pykdtree"),
        "load_average_start": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "threads": "single-threaded: OMP_NUM_THREADS=" + os.environ.get("OMP_NUM_THREADS", "?") + ", cKDTree workers=1",
    }


def targets(cases: list[Case], scaling: list[dict[str, Any]]) -> list[dict[str, Any]]:
    rows = []
    for case in cases:
        for mode in ("batch", "single"):
            if case.dim >= 12:
                checks = [
                    ("V_lb (policy) vs 1-NN", "lower", TARGETS["policy"]),
                    ("both bounds vs 1-NN", "both", TARGETS["both"]),
                ]
            else:
                checks = [
                    ("V_lb (policy) vs 1-NN", "lower", TARGETS["4d"]),
                    ("both bounds vs 1-NN", "both", TARGETS["4d"]),
                ]
            for label, key, target in checks:
                value = case.ratios[f"{key}_vs_1nn_{mode}"]
                rows.append({"case": f"{case.name}, {mode}", "metric": label, "value": value,
                             "target": f"<= {target:g}x", "met": value <= target})  # fmt: skip
    for row in scaling:
        if row["points"] >= 100_000:
            rows.append({"case": f"{row['case']}, {row['points']:,d} points", "metric": "speed-up vs brute force",
                         "value": row["speedup"], "target": f">= {TARGETS['brute']:g}x",
                         "met": row["speedup"] >= TARGETS["brute"]})  # fmt: skip
    return rows


def compression_of_runs(run_dirs: list[Path], progress: Progress) -> list[dict[str, Any]]:
    from npp_ros.run.store import RUN_FILE, RunStore

    rows = []
    for run in run_dirs:
        store = RunStore.open(run / RUN_FILE if run.is_dir() else run)
        data = store.load_dataset()
        meta = store.metadata
        t = time.perf_counter()
        full = compression_report(data, meta.lipschitz)
        elapsed = time.perf_counter() - t
        rows.append({"run": str(run), "task": meta.task, "seed": meta.seed, "lipschitz": meta.lipschitz,
                     "lipschitz_source": meta.lipschitz_source, "seconds": elapsed, **full.as_dict()})  # fmt: skip
        progress.step(f"compression of {run}: kept V_lb {full.kept_lower}/{full.points}, "
                      f"V_ub {full.kept_upper}/{full.points} ({elapsed:.1f}s)")  # fmt: skip
    return rows


# ----------------------------------------------------------------------------- iLQR experts
def seconds_summary(samples: list[float]) -> dict[str, Any]:
    """Median, quartiles and range of per-request seconds."""
    arr = np.asarray(samples, dtype=float)
    q25, q50, q75 = (float(x) for x in np.percentile(arr, [25, 50, 75]))
    return {"median_s": q50, "q25_s": q25, "q75_s": q75, "min_s": float(arr.min()), "max_s": float(arr.max()),
            "samples_s": [float(x) for x in arr]}  # fmt: skip


def held_part(task: str) -> str:
    """What must stay upright for a request to count as a swing-up: the pole, or both of the acrobot's links."""
    return "both links" if task == "acrobot_swingup" else "pole"


def worst_angle_degrees(states: FloatArray, angle: int, steps: int, lower_link: bool = False) -> float:
    """Largest |pole angle| (degrees from upright) over the last ``steps`` stored states (wrapped angles).

    ``lower_link``: the next entry is a second link's angle relative to the first (the acrobot's elbow),
    and the second link's own angle from upright, wrap(q1 + q2), counts too.
    """
    tail = np.abs(states[-steps:, angle])
    if lower_link:
        both = states[-steps:, angle] + states[-steps:, angle + 1]
        tail = np.maximum(tail, np.abs(np.pi - np.mod(np.pi - both, 2 * np.pi)))
    return float(np.degrees(np.max(tail)))


def time_expert(
    name: str,
    starts: list[FloatArray],
    horizon: int,
    seed: int,
    progress: Progress,
    paths: tuple[str, ...] = ("batch",),
) -> list[dict[str, Any]]:
    """Seconds per request of the task's default expert (options and budget), one request at a time, and how many
    answers met the task's success criterion (npp_ros.tasks.success): any task, a task file's too.

    A request is the whole answer the expert node gives: for an iLQR expert the warm-start rollout, iLQR, and the
    replays on the plant for the true rewards (the optimizer's own phase timings say where its part went; the rest
    of a request is the warm start and the replays); for a closed-form expert its trajectory. An answer succeeded
    when its stored states meet the task's criterion (the last second of a swing-up held upright; an episode
    shorter than the criterion's window is judged on all its states); a task that states none is timed, not
    scored. With several iLQR code paths (EXPERT_PATHS), each s0 is asked of one path after the other, so that the
    paths meet the same load; one result per path (a closed-form expert has one).
    """
    task = get_task(name)
    label = short_name(task.name)
    criterion = task.success
    experts: dict[str, Any] = {}
    for path in paths:
        expert = task.make_expert(seed, horizon, ExpertOptions(threads=default_threads()))  # alone: every core
        if not isinstance(expert, OptimizingExpert):
            experts = {"closed form": expert}
            break
        experts[path] = expert
        expert.optimizer.dynamics.reference = path == "reference"
        expert.solve(starts[0], min(horizon, 50))  # warm-up: lazy loads and first-call costs stay out
    window = criterion.window(horizon) if criterion is not None else max(1, horizon // 2)
    angle = POLE_ANGLE.get(task.name)
    phases = {path: {"derivatives": 0.0, "backward": 0.0, "line_search": 0.0, "rollout": 0.0, "optimizer_other": 0.0,
                     "warm_start_and_replays": 0.0} for path in experts}  # fmt: skip
    rows: dict[str, list[dict[str, Any]]] = {path: [] for path in experts}
    wall: dict[str, list[float]] = {path: [] for path in experts}
    cpu: dict[str, list[float]] = {path: [] for path in experts}
    for k, s0 in enumerate(starts):
        for path, expert in experts.items():
            tick, cpu_tick = time.perf_counter(), time.process_time()
            if isinstance(expert, OptimizingExpert):
                solution = expert.solve(s0)
                trajectory, answer = solution.trajectory, solution.expert_return
            else:
                trajectory = expert.trajectory(s0, horizon)
                answer = trajectory.expert_return
            wall[path].append(time.perf_counter() - tick)
            cpu[path].append(time.process_time() - cpu_tick)
            met = None if criterion is None else criterion.met(trajectory.states)
            row: dict[str, Any] = {"s0": [float(x) for x in s0], "seconds": wall[path][-1],
                                   "cpu_seconds": cpu[path][-1], "expert_return": answer, "success": met}  # fmt: skip
            if isinstance(expert, OptimizingExpert):
                opt = solution.optimization
                for key in ("derivatives", "backward", "line_search", "rollout"):
                    phases[path][key] += opt.timings[key]
                phases[path]["optimizer_other"] += opt.wall_time - sum(opt.timings.values())
                phases[path]["warm_start_and_replays"] += wall[path][-1] - opt.wall_time
                row.update(iterations=opt.iterations, stop_reason=opt.stop_reason,
                           kept_warm_start=solution.kept_warm_start)  # fmt: skip
            else:
                row.update(iterations=0, stop_reason="closed form", kept_warm_start=False)
            if angle is not None:  # how far from upright the pole came, over the states the criterion judges
                row["worst_angle_deg"] = worst_angle_degrees(
                    trajectory.states, angle, window, name == "acrobot_swingup"
                )
            rows[path].append(row)
            said = {None: "not scored", True: "yes", False: "no"}[row["success"]]
            progress.step(f"{label} ({path}) request {k + 1}/{len(starts)}: {wall[path][-1]:.2f}s, "
                          f"{row['stop_reason']} after {row['iterations']} iterations, return {answer:.0f}, "
                          f"succeeded: {said}")  # fmt: skip
    target = TARGETS.get(EXPERT_TARGET_KEY.get(name, ""))
    results = []
    for path, expert in experts.items():
        total = float(sum(wall[path]))
        timing = seconds_summary(wall[path])
        succeeded = None if criterion is None else sum(r["success"] for r in rows[path])
        optimizer = isinstance(expert, OptimizingExpert)
        results.append({
            "task": label, "path": path, "horizon": horizon, "requests": len(starts), "seed": seed,
            "options": {"time_budget_s": expert.time_budget if optimizer else math.nan,
                        "stop": expert.stop if optimizer else "closed form",
                        "max_iterations": expert.max_iterations if optimizer else 0,
                        "values": expert.values if optimizer else "closed form",
                        "planner": expert.settings.describe() if isinstance(expert, PlanningExpert) else None},
            "derivatives_by": expert.optimizer.dynamics.derivatives_by if optimizer else "closed form",
            "success_rule": "not scored: the task states no success criterion" if criterion is None
            else f"{criterion.describe()}; at H = {horizon}, the last {window} steps",
            "seconds": timing, "cpu_seconds": seconds_summary(cpu[path]),
            "phases_s": phases[path], "phase_shares": {k: v / total if total else 0.0 for k, v in phases[path].items()},
            "succeeded": succeeded, "success_fraction": None if succeeded is None else succeeded / len(starts),
            "target_s": target, "met": None if target is None else timing["max_s"] <= target, "detail": rows[path],
        })  # fmt: skip
    return results


def expert_section(args: argparse.Namespace, progress: Progress, command: str) -> dict[str, Any]:
    """Every expert task timed on the s0 of episodes 0 .. N-1 of ``--seed`` (the stream a run sees)."""
    started = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
    load_start = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    tasks = []
    for name in args.expert_tasks:
        task = get_task(name)
        starts = [task.initial_state(args.seed, k) for k in range(args.expert_requests)]
        horizon = task.default_horizon if args.expert_horizon is None else args.expert_horizon
        tasks += time_expert(name, starts, horizon, args.seed, progress, tuple(args.expert_paths))
    return {"command": command, "date": started, "load_average_start": load_start,
            "load_average_end": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
            "tasks": tasks}  # fmt: skip
