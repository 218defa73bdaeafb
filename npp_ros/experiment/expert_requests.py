"""The data expert's H-step returns from many s0, asked for in chunks that run in parallel.

A checkpoint evaluation and a certificate's held-out check need one expert request per s0, and
an optimizer expert's request takes seconds. These returns depend only on the task, the seed, the
expert's options, the horizon and the s0, never on the policy, so a run can ask for them as soon
as it starts. Inside a Dask task (npp-experiment's runs), each chunk of s0 becomes a Dask task of
its own that builds the seed's expert where it runs, so the chunks spread over the cluster's
workers that are free. When the run needs them it answers, in its own slot, every chunk no worker
has started, and waits only for those being answered elsewhere. Outside Dask the chunks are
answered one after the other by the expert given.

A fresh expert answers a state as the run's own expert does (an expert's answer does not depend
on what it answered before), so the returns are the one-at-a-time returns wherever the optimizer
stops by convergence or its iteration cap; an answer the time budget cut depends on the machine's
speed either way, and is counted.

With ``kept`` (npp_ros.run.held_out.KeptAnswers, the one format both commands keep the expert's returns in, named
by the run's identity), every finished chunk appends its s0's lines in one write, so a resumed command asks only for
the s0 still missing.

On a set of robots (a run with uncertainty > 0) s0 k is answered on robot k, as the run's own answers were: the
expert plans on that robot, or its nominal plan runs on it (npp_ros.run.nominal_plan).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from contextlib import suppress
from dataclasses import dataclass

import numpy as np
from distributed import Future, get_client, get_worker, wait

from npp_ros.experiment.arms import Arm, ExperimentSettings, make_expert
from npp_ros.policy.dataset import FloatArray
from npp_ros.run.held_out import KeptAnswers, expert_answers
from npp_ros.run.nominal_plan import DEFAULT_EXPERT_MODEL
from npp_ros.tasks.registry import Expert, Plant, Task, get_task
from npp_ros.tasks.uncertainty import Robot

CHUNK = 10  # s0 per chunk: seconds to a minute of expert work on the swing-up tasks
HELD_OUT_FILE = "heldout-expert.jsonl"  # a run folder's expert returns from its held-out s0 (KeptAnswers)
EVALUATION_FILE = "evaluation-expert.jsonl"  # ... and from its checkpoint evaluation s0
NOW, LATER = 1, -1  # Dask priorities of chunks around the runs' 0: a started run waits for them, or not yet


@dataclass(frozen=True)
class ChunkAnswer:
    """The expert's returns from ``len(returns)`` s0 starting at index ``first``."""

    first: int
    returns: list[float]
    stopped: list[bool]  # per s0: the time budget cut its answer before convergence or the iteration cap
    worker: str  # the Dask worker that answered ("" in process)

    @property
    def budget_stops(self) -> int:
        return sum(self.stopped)


def in_dask_task() -> bool:
    """Whether this code runs inside a task on a Dask worker."""
    try:
        get_worker()
    except ValueError:
        return False
    return True


def answer(
    task: Task,
    expert: Expert,
    plant: Plant,
    first: int,
    states: FloatArray,
    horizon: int,
    worker: str = "",
    progress: Callable[[int, int], None] | None = None,
    robots: Sequence[Robot] | None = None,
    expert_model: str = DEFAULT_EXPERT_MODEL,
) -> ChunkAnswer:
    """``expert``'s H-step returns from ``states`` (the task's own way: requests, or its controller rolled out); with
    ``robots``, from s0 k on robot k, planned there or (``expert_model`` nominal) planned on the nominal model."""
    returns, stopped = expert_answers(task, expert, plant, states, horizon, robots, expert_model, progress)
    return ChunkAnswer(first, [float(r) for r in returns], stopped, worker)


def answer_on_worker(
    arm: Arm,
    seed: int,
    settings: ExperimentSettings,
    first: int,
    states: FloatArray,
    robots: Sequence[Robot] | None = None,
) -> ChunkAnswer:
    """One chunk on a Dask worker (its own task, or the run's): the seed's expert and plant built here."""
    task = get_task(arm.task)
    expert = make_expert(arm, seed, settings)
    worker = f"worker {get_worker().name}"
    return answer(
        task, expert, task.make_plant(seed), first, states, settings.horizon, worker, robots=robots,
        expert_model=arm.expert_model,
    )  # fmt: skip


class ExpertReturns:
    """The data expert of (``arm``, ``seed``)'s H-step returns from ``states``, asked for in chunks.

    ``start()`` submits the chunks still missing when called inside a Dask task and does nothing
    elsewhere; ``result()`` waits for them, or answers them here with ``expert``; ``close()`` keeps
    what finished and drops the rest. ``priority``: the chunks' Dask priority against the runs (0):
    LATER for returns asked for ahead (runs waiting for a worker go first), NOW for returns a
    started run waits for. ``robots``: s0 k is answered on robot k (a run on a set of robots). ``kept``: the run's
    kept answers (its identity's) the returns are taken from where they match, and appended to chunk by chunk; a file
    of other answers is refused (StoredReturnsError) and left untouched.
    """

    def __init__(
        self,
        arm: Arm,
        seed: int,
        settings: ExperimentSettings,
        states: FloatArray,
        expert: Expert,
        kept: KeptAnswers | None = None,
        chunk: int = CHUNK,
        priority: int = NOW,
        robots: Sequence[Robot] | None = None,
    ) -> None:
        if chunk < 1:
            raise ValueError(f"a chunk holds at least one s0, got {chunk}")
        if robots is not None and len(robots) != len(states):
            raise ValueError(f"one robot per s0: {len(robots)} robots for {len(states)} s0")
        self.arm, self.seed, self.settings, self.expert, self.kept, self.chunk, self.priority = (
            arm, seed, settings, expert, kept, chunk, priority
        )  # fmt: skip
        self.robots = None if robots is None else list(robots)
        self.states = np.asarray(states, dtype=np.float64)
        self.returns = np.full(len(self.states), math.nan)
        self.answered = np.zeros(len(self.states), dtype=bool)
        self.budget_stops = 0
        self.workers: set[str] = set()  # the Dask workers that answered chunks in this process's lifetime
        self._futures: dict[tuple[int, int], Future] = {}  # (first, end) of each chunk the cluster was asked for
        if kept is not None:  # the answers an earlier command kept for these s0
            for k, (value, stop) in kept.read(self.states).items():
                self.returns[k], self.answered[k] = value, True
                self.budget_stops += int(stop)

    def _robots(self, lo: int, hi: int) -> list[Robot] | None:
        return None if self.robots is None else self.robots[lo:hi]

    def _keep(self, found: ChunkAnswer) -> None:
        """Takes one chunk's returns, and appends its s0's lines to the kept answers in one write."""
        hi = found.first + len(found.returns)
        self.returns[found.first : hi] = found.returns
        self.answered[found.first : hi] = True
        self.budget_stops += found.budget_stops
        if found.worker:
            self.workers.add(found.worker)
        if self.kept is not None:
            self.kept.append(found.first, self.states[found.first : hi], found.returns, found.stopped)

    # ------------------------------------------------------------------ asking
    def missing_chunks(self) -> list[tuple[int, int]]:
        """The (first, end) index ranges still to ask for, each at most ``chunk`` long."""
        ranges: list[tuple[int, int]] = []
        for index in map(int, np.flatnonzero(~self.answered)):
            if ranges and ranges[-1][1] == index and index - ranges[-1][0] < self.chunk:
                ranges[-1] = (ranges[-1][0], index + 1)
            else:
                ranges.append((index, index + 1))
        return ranges

    def start(self) -> ExpertReturns:
        """Inside a Dask task: the missing chunks go to the cluster now; elsewhere nothing happens yet."""
        if self._futures or not in_dask_task():
            return self
        client = get_client()
        self._futures = {
            (lo, hi): client.submit(
                answer_on_worker, self.arm, self.seed, self.settings, lo, self.states[lo:hi], self._robots(lo, hi),
                priority=self.priority, pure=False,
            )
            for lo, hi in self.missing_chunks()
        }  # fmt: skip
        return self

    def result(self, progress: Callable[[int, int], None] | None = None) -> FloatArray:
        """Every return, waiting for the chunks (or answering them here); ``progress(done, total)`` as they come."""
        total = len(self.states)

        def kept(found: ChunkAnswer) -> None:
            self._keep(found)
            if progress is not None:
                progress(int(self.answered.sum()), total)

        if in_dask_task():
            self.start()
            self._answer_with_the_cluster(kept)
        else:
            chunks = self.missing_chunks()
            task = get_task(self.arm.task)
            plant = task.make_plant(self.seed) if chunks else None
            for lo, hi in chunks:
                done = int(self.answered.sum())
                step = None if progress is None else (lambda k, _n, done=done: progress(done + k, total))
                kept(answer(
                    task, self.expert, plant, lo, self.states[lo:hi], self.settings.horizon, "", step,
                    self._robots(lo, hi), self.arm.expert_model,
                ))  # fmt: skip
        return self.returns.copy()

    def _answer_with_the_cluster(self, kept: Callable[[ChunkAnswer], None]) -> None:
        """Inside the run's task: answers here every chunk no worker has started, and waits for the others.

        The run keeps its worker's slot (it never secedes): a seceded task takes a slot back only when
        another task ends, so on a busy cluster a waiting run would sit behind a whole other run. A
        chunk answered here is the one a worker would have given (:func:`answer_on_worker`, a fresh
        expert); its task is cancelled. A chunk whose task a worker is running is waited for, and
        answered here after all if the cluster drops it (a worker lost, the task back in the queue).
        """
        client = get_client()
        pending = dict(self._futures)

        def answer_here(lo: int, hi: int) -> None:
            del pending[(lo, hi)]
            kept(answer_on_worker(self.arm, self.seed, self.settings, lo, self.states[lo:hi], self._robots(lo, hi)))

        while pending:
            for (lo, hi), future in list(pending.items()):
                if future.status in ("finished", "error"):  # an expert's error fails the run, as in process
                    del pending[(lo, hi)]
                    kept(future.result())
                elif future.status != "pending":  # cancelled or lost by the cluster
                    answer_here(lo, hi)
            if not pending:
                break
            # The chunks workers are running now, from their heartbeats (about 1 s old): not those merely
            # assigned, which a worker busy with a run would not start before that run ends. A chunk
            # started since the last heartbeat looks unstarted, and is answered twice (the same answer).
            # A lambda travels by value: the scheduler need not have npp_ros installed.
            running = set(client.run_on_scheduler(
                lambda dask_scheduler: [ts.key for ws in dask_scheduler.workers.values() for ts in ws.executing]
            ))  # fmt: skip
            idle = [(chunk, future) for chunk, future in pending.items() if future.key not in running]
            if idle:
                (lo, hi), future = idle[0]
                future.cancel()
                answer_here(lo, hi)
            else:
                with suppress(TimeoutError):
                    wait(list(pending.values()), timeout=1.0, return_when="FIRST_COMPLETED")
        self._futures = {}

    def close(self) -> None:
        """Keeps the chunks that finished (a resumed run will not ask again) and cancels the others."""
        for future in self._futures.values():
            if future.status == "finished":
                self._keep(future.result())
            else:
                future.cancel()
        self._futures = {}
