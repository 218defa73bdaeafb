"""Expert trajectories from a pool of worker processes, each with its own copy of the task's expert.

An optimizer expert's request is seconds of single-threaded iLQR, and requests are independent: an
expert answers a state the same whatever it answered before (its counters aside), so several worker
processes can answer several requests at once. Each answer is the one-at-a-time answer bit for bit
whenever the optimizer stops by convergence or its iteration cap; an answer the time budget cut
depends on the machine's speed either way, and comes back named as such.

Workers are started fresh ("spawn"), never forked from a process that runs threads. Each worker's
iLQR takes its derivatives on ``threads`` threads (ExpertOptions.threads; by default the cores over
the workers, at least 1), so the pool never runs more threads than there are cores.

A request may name a drawn robot (npp_ros.tasks.uncertainty): its worker plans on it, the worker's model made into
that robot for the request and nominal again after it, so the answer is the in-process privileged expert's.
"""

from __future__ import annotations

import multiprocessing
import os
import time
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, replace

import numpy as np

from npp_ros.policy.dataset import FloatArray, Trajectory
from npp_ros.tasks.registry import Expert, ExpertOptions, StopsAtTimeBudget, get_task
from npp_ros.tasks.uncertainty import Robot, as_robot
from npp_ros.trajopt.batch_steps import default_threads
from npp_ros.trajopt.expert import OptimizingExpert

_EXPERT: Expert | None = None  # a worker process's own expert


def default_workers() -> int:
    """One worker per core this process may run on."""
    return max(1, len(os.sched_getaffinity(0)))


@dataclass(frozen=True)
class PooledAnswer:
    """A worker's trajectory, and whether the time budget stopped the optimizer before it converged."""

    trajectory: Trajectory
    budget_stopped: bool
    stop_reason: str | None = None  # why the optimizer stopped ("converged", "max iterations", ...); None: no optimizer
    cpu_seconds: float = 0.0  # the worker's CPU time for this request: on a busy machine, less than its wall time


def _build_expert(task: str, seed: int, horizon: int, options: ExpertOptions) -> None:
    global _EXPERT
    _EXPERT = get_task(task).make_expert(seed, horizon, options)


def _answer(state: FloatArray, horizon: int, robot: Robot | None = None) -> PooledAnswer:
    expert = _EXPERT
    assert expert is not None, "the worker's initializer builds its expert"
    with as_robot(expert.plant, robot):
        return _planned(expert, state, horizon)


def _planned(expert: Expert, state: FloatArray, horizon: int) -> PooledAnswer:
    stops = expert.budget_stops if isinstance(expert, StopsAtTimeBudget) else 0
    reason, started = None, time.process_time()
    if isinstance(expert, OptimizingExpert):  # trajectory() is solve()'s trajectory; solve() also says why it stopped
        solution = expert.solve(state, horizon or expert.horizon)
        trajectory, reason = solution.trajectory, solution.optimization.stop_reason
    else:
        trajectory = expert.trajectory(state, horizon or expert.horizon)
    stopped = isinstance(expert, StopsAtTimeBudget) and expert.budget_stops > stops
    return PooledAnswer(trajectory, stopped, reason, time.process_time() - started)


class ExpertPool:
    """``workers`` processes, each with the expert ``get_task(task).make_expert(seed, horizon, options)``."""

    def __init__(self, task: str, seed: int, horizon: int, options: ExpertOptions, workers: int) -> None:
        if workers < 1:
            raise ValueError(f"an expert pool needs at least one worker, got {workers}")
        self.workers = workers
        if options.threads is None:  # threads x workers <= cores
            options = replace(options, threads=default_threads(workers))
        self.threads = options.threads
        self._pool = ProcessPoolExecutor(
            workers,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=_build_expert,
            initargs=(task, int(seed), int(horizon), options),
        )

    def submit(self, state: FloatArray, horizon: int = 0, robot: Robot | None = None) -> Future[PooledAnswer]:
        """The trajectory from ``state`` (``horizon`` 0: the expert's own), computed by a free worker, planned on
        ``robot`` (None: the nominal model)."""
        return self._pool.submit(_answer, np.asarray(state, dtype=np.float64), int(horizon), robot)

    def close(self) -> None:
        """Drop waiting requests and let the workers go; a running request finishes in its worker."""
        self._pool.shutdown(wait=False, cancel_futures=True)

    def __enter__(self) -> ExpertPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)
