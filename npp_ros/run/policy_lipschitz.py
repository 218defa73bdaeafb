"""The L the policy acts by, chosen from the run's own data by what the policy does at the run's own starts.

The policy's L decides one thing: which stored point the greedy choice on V_lb follows (V_lb(s) = max_i Q_i - L
|s - s_i|). A small L favours a high value far away, a large one the nearest point; which serves the policy best
depends on the task and the data, and the L a claim rests on (a bound on V*'s slope) says nothing about it. So a
run may keep the two apart (``policy_lipschitz = "select"``): the claim's L stays the spec's, and the policy's is
chosen here, on the run's data, by the successes of the policy's own rollouts.

Sound where the claim checks the policy's own rollouts: the success claim (it rests on no L), the oracle claim (the
expert's return minus the policy's) and the rollout claim (V_ub with the claim's L, plus a tail, minus the policy's
return) hold for any policy, so for one that acts by any L. The surrogate claim's V_ub - V_lb speaks of the policy
greedy on the claim's L and refuses a selected one.

The rule, deterministic so that a resumed or re-derived run chooses the same:

- when the policy's data first holds 4, 8, 16, ... trajectories (each doubling), a choice is made on exactly that
  many (the first ``count`` stored) and on the starts of the last :data:`STARTS` episodes up to the one that stored
  the last of them, each on its own drawn robot;
- each candidate (the claim's L times :data:`LADDER`) is rolled out from each start, by the policy over the data
  without the trajectories that start's own episode stored (held out: a start is never followed by its own answer);
- the candidate with the most successes on the task's criterion wins; among those tied, the claim's L if it is one
  of them (a return a fraction higher on a few starts is no evidence to move on), else the higher mean return, then
  the smaller L. A task without a success criterion is decided by mean return, then the smaller L.

Until the first choice the policy acts by the claim's L. The run file records each choice with its scores, and the
certificate names the L its policy acts by.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from npp_ros.certificate.certifier import Certificate
from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import Dataset, FloatArray
from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.run.records import EpisodeRow
from npp_ros.tasks.success import SuccessCriterion
from npp_ros.tasks.uncertainty import Robot

POLICY_LIPSCHITZ_MODES = ("claim", "select")
POLICY_LIPSCHITZ_HELP = (
    "the L the policy chooses its data point by: claim (the claim's own L, as the paper's policy does) or select "
    "(chosen from the run's own data: at 4, 8, 16, ... trajectories, the claim's L times 1, 10, 100, 1e3 or 1e8, "
    "whichever makes the policy succeed most often from the last 32 episodes' starts, each start's own answer held "
    "out; the claim's L stays the claim's). select needs a claim that checks the policy's own rollouts (success, "
    "oracle, rollout)"
)
LADDER = (1.0, 10.0, 100.0, 1e3, 1e8)  # multiples of the claim's L; 1e8 stands for "the nearest point"
FIRST_CHOICE = 4  # trajectories: fewer leave too few starts to tell candidates apart
STARTS = 32  # the most recent episodes' starts a choice is scored on


def check_policy_lipschitz(mode: str, certify: str | None = None) -> str:
    """The mode, or a ValueError naming the choices (and why a surrogate claim refuses a selected L)."""
    if mode not in POLICY_LIPSCHITZ_MODES:
        raise ValueError(f"policy_lipschitz must be one of {', '.join(POLICY_LIPSCHITZ_MODES)}; got {mode!r}")
    if mode == "select" and certify == "surrogate":
        raise ValueError(
            "policy_lipschitz select needs a claim that checks the policy's own rollouts (success, oracle or rollout): "
            "the surrogate claim's V_ub - V_lb speaks of the policy greedy on the claim's own L"
        )
    return mode


def choice_point(count: int) -> int:
    """The data size (in trajectories) whose choice a policy over ``count`` trajectories acts by; 0: none yet."""
    if count < FIRST_CHOICE:
        return 0
    return 1 << (int(count).bit_length() - 1)


@dataclass(frozen=True)
class HeldOutStart:
    """One episode's start, its drawn robot, and the trajectories its episode stored (held out of its policy)."""

    state: FloatArray
    robot: Robot | None
    own: tuple[int, ...]


@dataclass(frozen=True)
class CandidateScore:
    lipschitz: float
    successes: int
    mean_return: float


@dataclass(frozen=True)
class LipschitzChoice:
    """The L chosen for the policy over the first ``trajectories`` trajectories, with every candidate's score."""

    trajectories: int
    value: float
    starts: int
    scores: tuple[CandidateScore, ...]

    def describe(self) -> str:
        shown = "; ".join(f"{s.lipschitz:.3g}: {s.successes} met, return {s.mean_return:.4g}" for s in self.scores)
        return (
            f"L = {self.value:.6g}, chosen at {self.trajectories} trajectories from {self.starts} held-out starts "
            f"({shown})"
        )

    def constant(self) -> LipschitzConstant:
        """The chosen L as the policy carries it, with where it came from."""
        return LipschitzConstant(self.value, "selected", self.describe())

    def record(self) -> str:
        """The scores as the run file stores them (JSON)."""
        return json.dumps([[s.lipschitz, s.successes, s.mean_return] for s in self.scores])

    @classmethod
    def from_record(cls, trajectories: int, value: float, starts: int, scores: str) -> LipschitzChoice:
        parsed = tuple(CandidateScore(float(a), int(b), float(c)) for a, b, c in json.loads(scores))
        return cls(int(trajectories), float(value), int(starts), parsed)


def acted_by(choices: Mapping[int, LipschitzChoice], count: int) -> LipschitzConstant | None:
    """The L a run's policy over its first ``count`` trajectories acts by, from the choices it made (None: the
    claim's): the one at that size's choice point; for data the policy never held whole (a test's trajectories held
    back), the last choice made below it."""
    point = choice_point(count)
    made = [made for made in choices if made <= point]
    return choices[max(made)].constant() if made else None


def certified_lipschitz(certificate: Certificate) -> LipschitzConstant | None:
    """The L a certificate's policy acts by where its run chose its own (None: the claim's)."""
    value = certificate.policy_lipschitz
    return None if value is None else LipschitzConstant(value, "selected", "chosen from the run's data")


def held_out(data: Dataset, own: tuple[int, ...]) -> Dataset:
    """The data without the trajectories ``own`` (a start's own answers), the rest in stored order."""
    out = Dataset(data.state_dim, data.action_dim, capacity=max(len(data), 1))
    for index in range(data.num_trajectories):
        if index not in own:
            out.append(data.trajectory(index))
    return out


def _start_data(data: Dataset, start: HeldOutStart) -> Dataset:
    """The data a start is rolled out on: without its own answers, or the whole data where it has none among them."""
    own = tuple(index for index in start.own if index < data.num_trajectories)
    return held_out(data, own) if own else data


def choose_lipschitz(
    data: Dataset,
    starts: Sequence[HeldOutStart],
    claim: float,
    build: Callable[[Dataset, float], NonparametricPolicy],
    run: Callable[[FloatArray, NonparametricPolicy, Robot | None], tuple[FloatArray, float]],
    success: SuccessCriterion | None,
) -> LipschitzChoice:
    """Score every candidate L on ``starts`` (``run`` rolls a policy out: its states and return) and keep the best.

    ``build(data, L)`` makes the run's policy over data with that L. A start whose own answers are all outside
    ``data`` shares the policy over the whole of it; a task without a success criterion is scored by return only."""
    own_data = [_start_data(data, start) for start in starts]  # built once, for every candidate alike
    scores = []
    for lipschitz in (claim * factor for factor in LADDER):
        shared = build(data, lipschitz)
        successes, total = 0, 0.0
        for start, start_data in zip(starts, own_data, strict=True):
            if len(start_data) == 0:
                continue
            policy = shared if start_data is data else build(start_data, lipschitz)
            states, ret = run(start.state, policy, start.robot)
            successes += int(success is not None and success.met(states))
            total += ret
        mean = total / len(starts) if starts else 0.0
        scores.append(CandidateScore(lipschitz, successes, mean if math.isfinite(mean) else -math.inf))

    def rank(k: int) -> tuple[float, ...]:
        score = scores[k]
        if success is None:
            return (score.mean_return, -k)
        return (score.successes, k == 0, score.mean_return, -k)  # k 0: the claim's own L (LADDER[0] = 1)

    best = max(range(len(scores)), key=rank)
    return LipschitzChoice(data.num_trajectories, scores[best].lipschitz, len(starts), tuple(scores))


def recent_starts(rows: Sequence[EpisodeRow], last_episode: int, count: int = STARTS) -> list[HeldOutStart]:
    """The starts of the last ``count`` episodes up to ``last_episode``, each with its robot and its own answers."""
    starts = []
    for row in [row for row in rows if row.episode <= last_episode][-count:]:
        first = row.trajectory
        own = () if first is None else tuple(range(first, first + 1 + int(row.explored or 0)))
        robot = Robot.from_record(str(row.robot)) if row.robot else None
        starts.append(HeldOutStart(np.asarray(row.initial_state, dtype=np.float64), robot, own))
    return starts
