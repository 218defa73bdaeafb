"""Expert throughput: requests per second through the expert pool at 1, 2 and m workers, side by side.

Every worker count answers the same s0 (episodes 0 .. N-1 of the seed, the stream a run sees)
with the task's default expert options, so the ratios compare worker counts on one machine in one
run. A pool's start (spawning its processes, building each worker's expert) and one short warm-up
request per worker stay out of the timing: a serving expert node pays them once. Answers that the
time budget cut are counted and named: they depend on the machine's speed and load, so they are
left out of the check that every worker count gave the same answers.
"""

from __future__ import annotations

import hashlib
import os
import time
from collections import Counter
from collections.abc import Sequence
from typing import Any

import numpy as np

from npp_ros.bench.measure import Progress
from npp_ros.tasks.expert_pool import ExpertPool, PooledAnswer, default_workers
from npp_ros.tasks.registry import DEFAULT_OPTIONS, ExpertOptions, get_task

WARM_UP_HORIZON = 20  # steps of each worker's warm-up request


def worker_counts(most: int) -> list[int]:
    """1, 2 and ``most`` (the cores by default), each once, in increasing order."""
    if most < 1:
        raise ValueError(f"the pool needs at least one worker, got {most}")
    return sorted({1, min(2, most), most})


def answer_digest(answer: PooledAnswer) -> str:
    """One answer's states, actions and values as a digest: equal digests are equal answers, bit for bit."""
    digest = hashlib.sha256()
    for array in (answer.trajectory.states, answer.trajectory.actions, answer.trajectory.values):
        digest.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
    return digest.hexdigest()[:16]


def time_pool(
    name: str, starts: Sequence[np.ndarray], horizon: int, seed: int, workers: int, options: ExpertOptions
) -> dict[str, Any]:
    """All of ``starts`` asked of a pool of ``workers`` at once; the wall time from the first ask to the last answer."""
    with ExpertPool(name, seed, horizon, options, workers) as pool:
        warm = [pool.submit(starts[k % len(starts)], min(WARM_UP_HORIZON, horizon)) for k in range(workers)]
        for future in warm:
            future.result()
        tick = time.perf_counter()
        futures = [pool.submit(s0) for s0 in starts]
        answers = [future.result() for future in futures]
        wall = time.perf_counter() - tick
        threads = pool.threads
    reasons = Counter(
        "time budget" if a.budget_stopped else (a.stop_reason or "closed form") for a in answers
    )  # the pool names a budget cut even where the optimizer's result was replaced by a kept warm start
    return {
        "workers": workers,
        "threads_per_worker": threads,  # iLQR derivative threads in each worker (cores over workers by default)
        "seconds": wall,
        "requests_per_s": len(answers) / wall if wall > 0 else float("inf"),
        "cpu_seconds": sum(a.cpu_seconds for a in answers),  # what the workers got of the cores meanwhile
        "cores_used": sum(a.cpu_seconds for a in answers) / wall if wall > 0 else float("nan"),
        "answered": sum(len(a.trajectory) == horizon for a in answers),
        "budget_stopped": sum(a.budget_stopped for a in answers),
        "stop_reasons": dict(sorted(reasons.items())),
        "digests": [answer_digest(a) for a in answers],
        "budget_stopped_requests": [k for k, a in enumerate(answers) if a.budget_stopped],
        "expert_returns": [a.trajectory.expert_return for a in answers],
    }


def task_throughput(
    name: str, requests: int, horizon: int | None, seed: int, counts: Sequence[int], progress: Progress,
    options: ExpertOptions = DEFAULT_OPTIONS,
) -> dict[str, Any]:  # fmt: skip
    """One task at every worker count on the same s0, with the speed-ups over one worker (horizon None: the
    task's own)."""
    task = get_task(name)
    horizon = task.default_horizon if horizon is None else horizon
    starts = [task.initial_state(seed, k) for k in range(requests)]
    runs = []
    for workers in counts:
        run = time_pool(name, starts, horizon, seed, workers, options)
        runs.append(run)
        progress.step(
            f"{name} through {workers} worker{'s' if workers > 1 else ''}: {run['requests_per_s']:.2f} requests/s "
            f"({requests} in {run['seconds']:.1f}s; {', '.join(f'{r} {n}' for r, n in run['stop_reasons'].items())})"
        )
    base = runs[0]["requests_per_s"]
    for run in runs:
        run["speedup"] = run["requests_per_s"] / base if base > 0 else float("nan")
    cut = set().union(*(run["budget_stopped_requests"] for run in runs))
    compared = [k for k in range(requests) if k not in cut]
    equal = all(len({run["digests"][k] for run in runs}) == 1 for k in compared)
    return {
        "task": name, "horizon": horizon, "requests": requests, "seed": seed, "runs": runs,
        "compared_requests": len(compared), "answers_equal": equal,
    }  # fmt: skip


def throughput_section(
    tasks: Sequence[str], requests: int, horizon: int | None, seed: int, most: int | None, progress: Progress,
    command: str,
) -> dict[str, Any]:  # fmt: skip
    """Every task at 1, 2 and ``most`` workers (None: one per core this process may use)."""
    started = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
    load_start = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    counts = worker_counts(default_workers() if most is None else most)
    results = [task_throughput(name, requests, horizon, seed, counts, progress) for name in tasks]
    return {"command": command, "date": started, "usable_cores": default_workers(), "worker_counts": counts,
            "load_average_start": load_start,
            "load_average_end": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
            "tasks": results}  # fmt: skip
