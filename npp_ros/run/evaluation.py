"""The policy against fresh initial states: one evaluator for npp-learn and npp-experiment.

``policy_rollouts`` steps N rollouts of the greedy policy in lockstep on plant clones (batched
policy queries, bit-identical to one-at-a-time rollouts) and records the largest value slope the
policy visited. ``check_policy`` turns them into the test of a certificate's claim: the share of
s0 whose gap to the value the claim speaks of is within epsilon, and a one-sided binomial test of
P(gap <= epsilon) >= p at level delta. The expert's returns it asks for are the slow part (seconds each): with
:class:`KeptAnswers` each is written to the run folder as it arrives, so a check stopped at any moment loses none
and a later, larger check asks only for the s0 it adds.
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

import numpy as np
from numpy.typing import ArrayLike
from scipy.stats import binom

from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import FloatArray
from npp_ros.run.nominal_plan import DEFAULT_EXPERT_MODEL, check_expert_model, nominal_plan_returns
from npp_ros.tasks.registry import Expert, Plant, StopsAtTimeBudget, Task
from npp_ros.tasks.rollout import rollout, rollout_batch
from npp_ros.tasks.success import SuccessCriterion
from npp_ros.tasks.uncertainty import Robot, UncertaintySet

CHUNK = 100  # rollouts stepped in lockstep
VIOLATION_TOLERANCE = 1e-9  # relative: a return below V_lb(s0) by more than rounding


def policy_rollouts(
    plant: Plant,
    policy: NonparametricPolicy,
    states: FloatArray,
    horizon: int,
    slope: Callable[[ArrayLike], FloatArray] | None,
    *,
    chunk: int = CHUNK,
    progress: Callable[[int, int], None] | None = None,
    robots: Sequence[Robot] | None = None,
    met: FloatArray | None = None,
    criterion: SuccessCriterion | None = None,
) -> tuple[FloatArray, FloatArray]:
    """The policy's H-step return from each s0, and the largest |grad V^expert| along each rollout
    (NaN where the expert's value slope is not known in closed form). With ``robots``, s0 k is rolled out on
    robot k (one at a time: each robot is its own model). With ``criterion``, ``met[k]`` is 1 where rollout k met it,
    else 0."""
    returns = np.empty(len(states))
    slopes = np.empty(len(states))
    if progress is not None:
        progress(0, len(states))  # the phase has begun: a chunk of long rollouts says nothing until it ends
    for lo in range(0, len(states), chunk):
        hi = min(lo + chunk, len(states))
        if robots is None:
            runs = rollout_batch(plant, policy.controller(), states[lo:hi], horizon)
        else:
            runs = [rollout(plant, policy.controller(), states[k], horizon, robots[k]) for k in range(lo, hi)]
        for k, run in enumerate(runs):
            returns[lo + k] = run.total_return
            slopes[lo + k] = math.nan if slope is None else float(np.max(slope(run.states)))
            if met is not None and criterion is not None:
                met[lo + k] = float(criterion.met(run.states))
        if progress is not None:
            progress(hi, len(states))
    return returns, slopes


def below_lower_bound(returns: FloatArray, lower: FloatArray) -> FloatArray:
    """Returns below V_lb(s0): impossible where Theorem 3.4 holds (and so a sign that it does not)."""
    return returns < lower - VIOLATION_TOLERANCE * np.maximum(1.0, np.abs(lower))


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


KEPT_ANSWERS = "held-out-expert.jsonl"  # in the run folder, beside run.sqlite


class KeptAnswers:
    """The expert's returns of a run's held-out checks, one JSON line per s0, appended as each answer arrives.

    The first line names what the answers depend on, by its hash (``identity``: npp-learn gives the run's own,
    RunConfig.identity, every setting its run file records, the expert's as its expert resolved them); a file
    naming anything else is of other answers and is started afresh. Line k holds s0 k of the held-out stream and
    the expert's return from it, and is used again only for the same s0, bit for bit. Written with flush and fsync
    per line: a kill at any moment leaves every answer before it (a torn last line is dropped on reading).
    """

    def __init__(self, path: Path, identity: str) -> None:
        self.path = Path(path)
        self.identity = hashlib.sha256(identity.encode()).hexdigest()

    def _read(self) -> dict[int, tuple[list[float], float, bool]] | None:
        """The kept answers by index (later lines win); None when there is no file of these answers."""
        if not self.path.is_file():
            return None
        text = self.path.read_text()
        if text and not text.endswith("\n"):  # a torn last line: the next answer must start a line of its own
            with self.path.open("a") as f:
                f.write("\n")
        lines = text.splitlines()
        try:
            header = json.loads(lines[0]) if lines else None
        except json.JSONDecodeError:
            return None
        if not isinstance(header, dict) or header.get("identity") != self.identity:
            return None
        kept: dict[int, tuple[list[float], float, bool]] = {}
        for line in lines[1:]:
            try:
                row = json.loads(line)
                value = math.nan if row["return"] is None else float(row["return"])
                kept[int(row["k"])] = ([float(x) for x in row["s0"]], value, bool(row["budget_stop"]))
            except (json.JSONDecodeError, KeyError, TypeError, ValueError):
                continue  # a line torn by a kill: its s0 is asked for again
        return kept

    def returns(
        self,
        states: FloatArray,
        ask: Callable[[int], float],
        stopped: Callable[[], int],
        progress: Callable[[int, int], None] | None = None,
    ) -> tuple[FloatArray, int, int]:
        """The expert's return from each of ``states``: kept where an earlier check asked for the same s0, else
        ``ask(k)`` now, appended at once. ``stopped()`` is the expert's count of answers its time budget cut.
        Returns (returns, how many of them the budget cut, how many were kept)."""
        kept = self._read()
        if kept is None:  # no file, or one of other answers: start it with this identity
            self.path.write_text(json.dumps({"identity": self.identity}) + "\n")
            kept = {}
        usable = {k for k, row in kept.items() if k < len(states) and row[0] == states[k].tolist()}
        out = np.empty(len(states))
        cut = 0
        if progress is not None:
            progress(0, len(states))
        with self.path.open("a") as f:
            for k, s0 in enumerate(states):
                if k in usable:
                    out[k], stop = kept[k][1], kept[k][2]
                else:
                    before = stopped()
                    out[k] = ask(k)
                    stop = stopped() > before
                    value = None if math.isnan(out[k]) else float(out[k])
                    f.write(json.dumps({"k": k, "s0": s0.tolist(), "return": value, "budget_stop": stop}) + "\n")
                    f.flush()
                    os.fsync(f.fileno())
                cut += int(stop)
                if progress is not None:
                    progress(k + 1, len(states))
        return out, cut, len(usable)


def budget_stops(expert: Expert) -> int:
    """How many of ``expert``'s answers so far its time budget cut (0 for an expert without one)."""
    return expert.budget_stops if isinstance(expert, StopsAtTimeBudget) else 0


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
        if expert_returns is None:
            nominal = robots is not None and check_expert_model(expert_model) == "nominal"

            def ask(
                chosen: FloatArray, on: Sequence[Robot] | None, told: Callable[[int, int], None] | None
            ) -> FloatArray:
                if nominal:
                    assert on is not None
                    return nominal_plan_returns(expert, plant, chosen, horizon, on, told)
                return task.expert_returns(expert, plant, chosen, horizon, told, on)

            if kept is None:
                before = budget_stops(expert)
                if expert_progress is not None:
                    expert_progress(0, len(states))
                reference = ask(states, robots, expert_progress)
                expert_budget_stops = budget_stops(expert) - before
            else:
                reference, expert_budget_stops, answers_kept = kept.returns(
                    states,
                    lambda k: float(ask(states[k : k + 1], None if robots is None else robots[k : k + 1], None)[0]),
                    lambda: budget_stops(expert),
                    expert_progress,
                )
        else:
            reference = np.asarray(expert_returns, dtype=np.float64)
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


HELD_OUT_EPISODES = 1 << 30  # the first episode index of held-out draws: no run gets this far
HELD_OUT_S0_STREAM = 1 << 30  # the rng stream of npp-learn's held-out s0 (a run's own s0 use [seed, episode])


def held_out_initial_states(task: Task, seed: int, count: int) -> FloatArray:
    """The first ``count`` s0 of npp-learn's held-out check of a run of ``seed``: a stream no run draws its s0 from,
    the same at every rerun, so a later look at a run's held-out check sees the states it saw."""
    rng = np.random.default_rng([seed, HELD_OUT_S0_STREAM])
    return np.array([task.sample_initial_state(rng) for _ in range(count)])


def held_out_robots(uncertainty: str, seed: int, count: int) -> list[Robot] | None:
    """The robots of ``count`` held-out checks of a run whose set is ``uncertainty`` (its record; '' = the exact
    model, None), drawn as the run draws, at episode indices no run reaches: fresh, and the same at every rerun."""
    if not uncertainty:
        return None
    robots = UncertaintySet.from_record(uncertainty)
    return [robots.draw(seed, HELD_OUT_EPISODES + k) for k in range(count)]


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
