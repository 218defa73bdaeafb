"""A certificate against fresh starts: the one held-out mechanism of npp-learn and npp-experiment.

Both commands check a certificate the same way: fresh s0 (:func:`held_out_states`, on the command's own rng
stream) and, on a set of robots, a fresh robot for each (:func:`held_out_robots`); the policy rolled out from them
and measured against the value its claim speaks of (:func:`check_policy`), or counted against the task's success
criterion (:func:`check_success`). The expert's returns such a check asks for are the slow part (seconds each): both
commands keep them in their run folder with :class:`KeptAnswers`, one JSON line per s0, named by the run's own
identity (:func:`answers_identity`), so a check stopped at any moment loses none and a later, larger one asks only
for the s0 it adds. npp-experiment asks them in parallel chunks over Dask (npp_ros.experiment.expert_requests), each
chunk appending its s0's lines through the same class.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.stats import binom

from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import FloatArray
from npp_ros.run.evaluation import CHUNK, below_lower_bound, policy_rollouts
from npp_ros.run.nominal_plan import DEFAULT_EXPERT_MODEL, check_expert_model, nominal_plan_returns
from npp_ros.tasks.registry import Expert, Plant, StopsAtTimeBudget, Task, get_task
from npp_ros.tasks.uncertainty import Robot, UncertaintySet

if TYPE_CHECKING:
    from npp_ros.run.loop import RunConfig

# ---------------------------------------------------------------------------------------------- the draws
# The rng streams of the held-out s0, [seed, stream]; a run's own s0 use [seed, episode], episodes far below both.
# npp-learn draws its held-out s0 from 1 << 30. npp-experiment draws its checkpoint evaluations' fixed s0 from that
# stream (npp_ros.experiment.arms.EVALUATION_STREAM), so its certificates are checked on the next one, on s0 no
# evaluation saw. Both values are those the committed results were made with: changing one changes every held-out
# number its command reports.
LEARN_HELD_OUT_STREAM = 1 << 30  # npp-learn --evaluate N
EXPERIMENT_HELD_OUT_STREAM = (1 << 30) + 1  # npp-experiment --held-out N
HELD_OUT_EPISODES = 1 << 30  # the first episode index of held-out robot draws: no run gets this far


def held_out_states(task: Task | str, seed: int, count: int, stream: int) -> FloatArray:
    """The first ``count`` held-out s0 of a run of ``seed`` on ``stream`` (one of the streams above): a stream no
    run draws its s0 from, the same at every rerun, so a later look at a run's held-out check sees the states it
    saw."""
    definition = get_task(task) if isinstance(task, str) else task
    rng = np.random.default_rng([seed, stream])
    return np.array([definition.sample_initial_state(rng) for _ in range(count)])


def held_out_robots(uncertainty: str, seed: int, count: int) -> list[Robot] | None:
    """The robots of ``count`` held-out checks of a run whose set is ``uncertainty`` (its record; '' = the exact
    model, None), drawn as the run draws, at episode indices no run reaches: fresh, and the same at every rerun.
    Both commands draw the same robots; each pairs robot k with its own s0 k."""
    if not uncertainty:
        return None
    robots = UncertaintySet.from_record(uncertainty)
    return [robots.draw(seed, HELD_OUT_EPISODES + k) for k in range(count)]


# ---------------------------------------------------------------------------------------------- the kept answers
KEPT_ANSWERS = "held-out-expert.jsonl"  # npp-learn's, in the run folder beside run.sqlite


class StoredReturnsError(ValueError):
    """A kept-answers file of other answers (another run's, or an earlier format naming no run identity): refused,
    left untouched, so that answers which cost hours are never used for the wrong run nor thrown away."""


def answers_identity(config: RunConfig) -> str:
    """What the expert's kept answers of a run depend on: the run's own identity (RunConfig.identity, every setting
    its file records, the expert's as its expert resolved them), the same string whichever command made the run."""
    return json.dumps(config.identity(), sort_keys=True)


def _described(header: object) -> str:
    """What a first line that is not this run's header holds, in a few words, for the refusal."""
    if isinstance(header, dict) and isinstance(header.get("identity"), str):
        return f"the expert's returns of another run (identity {header['identity'][:12]}...)"
    if isinstance(header, dict) and "task" in header:  # npp-experiment's files before they were named by the run
        named = ", ".join(f"{k} {header[k]}" for k in ("task", "seed", "horizon") if k in header)
        return f"expert returns in the earlier per-chunk format, named by no run identity ({named})"
    return "an unreadable first line"


class KeptAnswers:
    """The expert's returns from a run's held-out (or evaluation) s0, one JSON line per s0, appended as they arrive.

    The first line names the run, ``{"identity": sha256 of its identity string}`` (:func:`answers_identity`). Each
    further line is ``{"k", "s0", "return", "budget_stop"}``: s0 k of the caller's states, the expert's return from it
    (null for none) and whether its time budget cut that answer; it is used again only for the same k and the same
    s0, bit for bit, and a later line for the same k wins. A file naming anything else is refused
    (:class:`StoredReturnsError`) and left as it is. Every append is one write, flushed and synced: a kill at any
    moment leaves every answer before it, and a line it tore is skipped on reading (its s0 asked again) and kept
    apart from the next.
    """

    def __init__(self, path: Path, identity: str) -> None:
        self.path = Path(path)
        self.identity = hashlib.sha256(identity.encode()).hexdigest()
        self._ours = False  # the file on disk is known to start with this run's header

    @property
    def header(self) -> str:
        return json.dumps({"identity": self.identity})

    def _text(self) -> str:
        """The file's text when it holds this run's answers; '' when there is none yet (no file, an empty one, or a
        first write torn inside this run's header). Refuses a file of other answers."""
        if not self.path.is_file():
            return ""
        text = self.path.read_text()
        first, newline, _ = text.partition("\n")
        if not newline and self.header.startswith(text):
            return ""
        try:
            header = json.loads(first)
        except json.JSONDecodeError:
            header = None
        if header != {"identity": self.identity}:
            raise StoredReturnsError(
                f"{self.path} holds {_described(header)}, not this run's (identity {self.identity[:12]}...), and was "
                "left untouched: move it away for the expert to be asked again"
            )
        return text

    def check(self) -> None:
        """Refuses a file of other answers now, before any work that would need it."""
        self._ours = bool(self._text())

    def read(self, states: FloatArray) -> dict[int, tuple[float, bool]]:
        """The kept (return, budget cut) of each of ``states`` an earlier ask answered, by index."""
        text = self._text()
        self._ours = bool(text)
        kept: dict[int, tuple[float, bool]] = {}
        for line in text.splitlines()[1:]:
            try:
                row = json.loads(line)
                k, s0 = int(row["k"]), [float(x) for x in row["s0"]]
                value = math.nan if row["return"] is None else float(row["return"])
                stop = bool(row["budget_stop"])
            except (json.JSONDecodeError, KeyError, TypeError, ValueError):
                continue  # a line torn by a kill: its s0 is asked for again
            if 0 <= k < len(states) and s0 == states[k].tolist():
                kept[k] = (value, stop)
        return kept

    def append(self, first: int, states: FloatArray, returns: Sequence[float], stopped: Sequence[bool]) -> None:
        """Appends the answers from ``states``, s0 ``first`` onwards, in one synced write (the header first in a
        file not yet begun)."""
        fresh = not self._ours and not self._text()
        lines = [self.header] if fresh else []
        if not fresh and self.path.stat().st_size:
            with self.path.open("rb") as fh:
                fh.seek(-1, os.SEEK_END)
                if fh.read(1) != b"\n":  # a line torn by a kill stays apart from the next
                    lines.append("")
        for k, (s0, value, stop) in enumerate(zip(states, returns, stopped, strict=True), start=first):
            answer = None if math.isnan(value) else float(value)
            row = {"k": k, "s0": np.asarray(s0).tolist(), "return": answer, "budget_stop": bool(stop)}
            lines.append(json.dumps(row))
        with self.path.open("w" if fresh else "a") as fh:
            fh.write("\n".join(lines) + "\n")
            fh.flush()
            os.fsync(fh.fileno())
        self._ours = True

    def returns(
        self,
        states: FloatArray,
        ask: Callable[[int], tuple[float, bool]],
        progress: Callable[[int, int], None] | None = None,
    ) -> tuple[FloatArray, int, int]:
        """The expert's return from each of ``states``, one at a time: kept where an earlier ask answered the same
        s0, else ``ask(k)`` (the return, and whether the time budget cut it) now, appended at once.
        Returns (returns, how many of them the budget cut, how many were kept)."""
        kept = self.read(states)
        out = np.empty(len(states))
        cut = 0
        if progress is not None:
            progress(0, len(states))
        for k in range(len(states)):
            if k in kept:
                out[k], stop = kept[k]
            else:
                out[k], stop = ask(k)
                self.append(k, states[k : k + 1], [out[k]], [stop])
            cut += int(stop)
            if progress is not None:
                progress(k + 1, len(states))
        return out, cut, len(kept)


# ---------------------------------------------------------------------------------------------- the expert's returns
def budget_stops(expert: Expert) -> int:
    """How many of ``expert``'s answers so far its time budget cut (0 for an expert without one)."""
    return expert.budget_stops if isinstance(expert, StopsAtTimeBudget) else 0


def expert_answers(
    task: Task,
    expert: Expert,
    plant: Plant,
    states: FloatArray,
    horizon: int,
    robots: Sequence[Robot] | None = None,
    expert_model: str = DEFAULT_EXPERT_MODEL,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[FloatArray, list[bool]]:
    """``expert``'s H-step returns from ``states`` (the task's own way: requests, or its controller rolled out), and
    which of them its time budget cut. With ``robots``, s0 k is answered on robot k as the run's own answers were:
    planned there, or (``expert_model`` nominal, npp_ros.run.nominal_plan) planned on the nominal model and run there.

    Which answer the budget cut is read between the task's per-request progress reports; a task that answers in one
    batch without them (lqr's controller) has no budget to cut."""
    seen = {0: budget_stops(expert)}

    def heard(done: int, total: int) -> None:
        seen[done] = budget_stops(expert)
        if progress is not None:
            progress(done, total)

    if robots is not None and check_expert_model(expert_model) == "nominal":
        returns = nominal_plan_returns(expert, plant, states, horizon, robots, heard)
    else:
        returns = task.expert_returns(expert, plant, states, horizon, heard, robots)
    cut = budget_stops(expert) - seen[0]
    if all(k in seen for k in range(len(states) + 1)):
        stopped = [seen[k + 1] > seen[k] for k in range(len(states))]
    else:  # no report per request: the count stays exact, laid on the first answers
        stopped = [k < cut for k in range(len(states))]
    return np.asarray(returns, dtype=np.float64), stopped


# ---------------------------------------------------------------------------------------------- the checks
@dataclass(frozen=True)
class HeldOutCheck:
    """A policy against fresh s0 ~ rho: does the claim P(gap <= epsilon) >= p survive?"""

    states: int
    reference: str  # the value each gap is measured against (the certificate's)
    within: int
    fraction: float
    p_value: float  # P[X <= within] for X ~ Binomial(states, p): small means the claim is contradicted
    rejected: bool  # p_value < delta
    below_v_lb: int  # returns below V_lb(s0) of the policy
    gap_q50: float
    gap_max: float
    wall_time: float
    visited_slope: float = float("nan")  # the largest |grad V^expert| the policy visited
    expert_budget_stops: int = 0  # reference answers the expert's time budget cut: they depend on the machine's speed
    expert_answers_kept: int = 0  # reference answers an earlier check of the same run had asked for (KeptAnswers)


def check_policy(
    policy: NonparametricPolicy,
    task: Task,
    plant: Plant,
    expert: Expert,
    states: FloatArray,
    horizon: int,
    *,
    epsilon: float,
    p: float,
    delta: float,
    against_expert: bool,
    progress: Callable[[int, int], None] | None = None,
    expert_progress: Callable[[int, int], None] | None = None,
    expert_returns: FloatArray | None = None,
    expert_budget_stops: int = 0,
    chunk: int = CHUNK,
    robots: Sequence[Robot] | None = None,
    expert_model: str = DEFAULT_EXPERT_MODEL,
    kept: KeptAnswers | None = None,
) -> HeldOutCheck:
    """Rolls ``policy`` out from ``states`` and measures the gap a certificate's claim is about.

    ``against_expert``: the expert's own H-step return from the same s0 (oracle mode, or a
    suboptimal expert); otherwise the task's optimal H-step return (lqr: H - 0.5 s0'P_H s0). A task
    that knows no optimum is always checked against its expert. ``expert_returns``: the expert's
    returns from ``states`` where the caller already asked for them (in parallel), with
    ``expert_budget_stops`` of them cut by its time budget; else asked here, and counted here. ``progress`` and
    ``expert_progress`` hear (done, total) of the policy's rollouts (after every ``chunk``) and of the expert's
    requests, each from (0, total) on: an optimizer's requests take seconds each.

    ``robots`` (a run under model uncertainty): s0 k is checked on robot k, the policy's rollout and the expert's
    answer both, so the check is of the claim over (s0, theta); a held-out check of such a claim must draw both.
    ``expert_model`` (npp_ros.run.nominal_plan): the expert plans on robot k, or on the nominal model with its plan
    then run on robot k, as the run's own answers were. ``kept``: the expert's answers are kept there as they
    arrive and taken from there where an earlier check of the same run asked for the same s0.
    """
    started = time.perf_counter()
    answers_kept = 0
    returns, slopes = policy_rollouts(
        plant, policy, states, horizon, task.value_slope(expert), chunk=chunk, progress=progress, robots=robots
    )
    optimal = None if against_expert or robots is not None else task.optimal_returns(expert, plant, states, horizon)
    if optimal is None:
        if expert_returns is not None:
            reference = np.asarray(expert_returns, dtype=np.float64)
        elif kept is None:
            if expert_progress is not None:
                expert_progress(0, len(states))
            reference, stopped = expert_answers(
                task, expert, plant, states, horizon, robots, expert_model, expert_progress
            )
            expert_budget_stops = sum(stopped)
        else:

            def ask(k: int) -> tuple[float, bool]:
                on = None if robots is None else robots[k : k + 1]
                value, stopped = expert_answers(task, expert, plant, states[k : k + 1], horizon, on, expert_model)
                return float(value[0]), stopped[0]

            reference, expert_budget_stops, answers_kept = kept.returns(states, ask, expert_progress)
        what = "the expert's H-step return"
    else:
        reference, what = optimal, "the optimal H-step return V*_H"
    gaps = reference - returns
    count = len(states)
    within = int(np.sum(gaps <= epsilon))
    p_value = float(binom.cdf(within, count, p))
    below = int(np.sum(below_lower_bound(returns, np.asarray(policy.v_lb(states)))))
    return HeldOutCheck(
        states=count, reference=what, within=within, fraction=within / count, p_value=p_value,
        rejected=p_value < delta, below_v_lb=below, gap_q50=float(np.median(gaps)), gap_max=float(np.max(gaps)),
        wall_time=time.perf_counter() - started, visited_slope=float(np.max(slopes)) if len(slopes) else math.nan,
        expert_budget_stops=expert_budget_stops if optimal is None else 0, expert_answers_kept=answers_kept,
    )  # fmt: skip


@dataclass(frozen=True)
class SuccessCheck:
    """A policy against fresh draws for the success claim: does P[the rollout meets the criterion] >= p survive?"""

    states: int
    succeeded: int
    fraction: float
    p_value: float  # P[X <= succeeded] for X ~ Binomial(states, p): small means the claim is contradicted
    rejected: bool  # p_value < delta
    wall_time: float


def check_success(
    policy: NonparametricPolicy,
    task: Task,
    plant: Plant,
    states: FloatArray,
    horizon: int,
    *,
    p: float,
    delta: float,
    robots: Sequence[Robot] | None = None,
    progress: Callable[[int, int], None] | None = None,
    chunk: int = CHUNK,
) -> SuccessCheck:
    """Rolls ``policy`` out from ``states`` (on ``robots``, one each, where given) and counts the rollouts that met
    the task's success criterion: the held-out test of a success claim, which asks no expert anything."""
    if task.success is None:
        raise ValueError(f"{task.name} states no success criterion: there is no success claim to check")
    started = time.perf_counter()
    met = np.zeros(len(states))
    policy_rollouts(
        plant, policy, states, horizon, None, chunk=chunk, progress=progress, robots=robots, met=met,
        criterion=task.success,
    )  # fmt: skip
    succeeded = int(met.sum())
    p_value = float(binom.cdf(succeeded, len(states), p))
    return SuccessCheck(
        len(states), succeeded, succeeded / len(states), p_value, p_value < delta, time.perf_counter() - started
    )
