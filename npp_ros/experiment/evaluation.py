"""Rollouts from fresh s0: checkpoint evaluations and the held-out check of a certificate.

A run on a set of robots drew a robot per episode, and its claim is over (s0, robot): its evaluations and its
held-out check then draw a fresh robot for each fresh s0 (npp_ros.run.held_out.held_out_robots, npp-learn's
draw), the policy and the expert both on it. The held-out check itself, its s0 draw and the expert's kept answers are
npp_ros.run.held_out's, npp-learn's too; what is here is npp-experiment's own: its arms, its checkpoint evaluations
and the files of its run folders.
"""

from __future__ import annotations

import csv
import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from npp_ros.certificate.certifier import Certificate
from npp_ros.experiment.arms import EVALUATION_CHUNK, Arm, ExperimentSettings, evaluation_states
from npp_ros.experiment.expert_requests import ExpertReturns
from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import Dataset, FloatArray
from npp_ros.run.evaluation import VIOLATION_TOLERANCE, policy_rollouts
from npp_ros.run.held_out import (
    EXPERIMENT_HELD_OUT_STREAM,
    HeldOutCheck,
    KeptAnswers,
    check_policy,
    check_success,
    held_out_states,
)
from npp_ros.run.policy_lipschitz import certified_lipschitz
from npp_ros.run.setup import policy_for
from npp_ros.tasks.registry import Expert, get_task
from npp_ros.tasks.uncertainty import Robot

SUCCESS_REFERENCE = "the task's success criterion"  # a success claim's held-out check: no gap, no V_lb


@dataclass(frozen=True)
class EvaluationRow:
    """One rollout from one evaluation s0 at one checkpoint."""

    checkpoint: int  # episodes done when evaluated
    rollout: int
    oracle_calls: int
    dataset_size: int
    policy_return: float
    expert_return: float  # the data expert from the same s0
    optimal_return: float  # the optimal controller from the same s0 (NaN where the task knows none)
    v_lb: float
    v_ub: float
    visited_slope: float  # max |grad V^expert| over the states the policy visited
    wall_time: float  # seconds for this checkpoint's whole evaluation (same on every row)

    @property
    def gap_to_expert(self) -> float:
        return self.expert_return - self.policy_return

    @property
    def gap_to_optimal(self) -> float:
        return self.optimal_return - self.policy_return

    @property
    def violates_lower_bound(self) -> bool:
        """Theorem 3.4 (B.1 i): the return can never fall below V_lb(s0) when L is a true bound."""
        return self.policy_return < self.v_lb - VIOLATION_TOLERANCE * max(1.0, abs(self.v_lb))


EVALUATION_FIELDS = [f.name for f in fields(EvaluationRow)]


def read_evaluations(path: Path) -> list[EvaluationRow]:
    if not path.exists():
        return []
    with path.open(newline="") as fh:
        reader = csv.DictReader(fh)
        if reader.fieldnames != EVALUATION_FIELDS:
            raise ValueError(f"{path}: unexpected columns {reader.fieldnames}; expected {EVALUATION_FIELDS}")
        rows = []
        for line in reader:
            rows.append(
                EvaluationRow(
                    **{
                        name: int(line[name])
                        if name in ("checkpoint", "rollout", "oracle_calls", "dataset_size")
                        else float(line[name])
                        for name in EVALUATION_FIELDS
                    }
                )
            )
    return rows


def append_evaluations(path: Path, rows: Sequence[EvaluationRow]) -> None:
    """Appends one checkpoint's rows in one write, so a crash leaves whole checkpoints only."""
    new = not path.exists()
    lines = []
    if new:
        lines.append(",".join(EVALUATION_FIELDS))
    for row in rows:
        lines.append(
            ",".join(repr(v) if isinstance(v, float) else str(v) for v in (getattr(row, n) for n in EVALUATION_FIELDS))
        )
    with path.open("a") as fh:
        fh.write("\n".join(lines) + "\n")
        fh.flush()


class Evaluator:
    """Rolls the policy and both reference controllers out in MuJoCo from the evaluation s0."""

    def __init__(
        self,
        arm: Arm,
        seed: int,
        settings: ExperimentSettings,
        expert: Expert,
        progress: Callable[[int, int], None] | None = None,
        kept: KeptAnswers | None = None,
        robots: Sequence[Robot] | None = None,
    ) -> None:
        """``kept``: the run's kept expert returns from the evaluation s0, for a resumed run. ``robots``
        (a run on a set of robots): evaluation s0 k is rolled out on robot k, and the expert answers on it."""
        self.settings = settings
        self.expert = expert
        self.robots = robots
        task = self.task = get_task(arm.task)
        self.plant = task.make_plant(seed)
        self.states = evaluation_states(arm.task, seed, settings.evaluations)
        self.expert_returns = ExpertReturns(arm, seed, settings, self.states, expert, kept, robots=robots).result(
            progress
        )
        if not task.optimal_expert or robots is not None:  # no optimum is known on a drawn robot
            self.optimal_returns = np.full(len(self.states), np.nan)
        elif arm.expert == task.experts[0]:
            self.optimal_returns = self.expert_returns
        else:
            optimal = task.make_expert(seed, settings.horizon)
            self.optimal_returns = task.expert_returns(optimal, self.plant, self.states, settings.horizon)

    def evaluate(
        self, checkpoint: int, policy: NonparametricPolicy, progress: Callable[[int, int], None] | None = None
    ) -> list[EvaluationRow]:
        started = time.perf_counter()
        lower = np.asarray(policy.v_lb(self.states))
        upper = np.asarray(policy.v_ub(self.states))
        returns, slopes = policy_rollouts(
            self.plant,
            policy,
            self.states,
            self.settings.horizon,
            self.task.value_slope(self.expert),
            chunk=EVALUATION_CHUNK,
            progress=progress,
            robots=self.robots,
        )
        wall = time.perf_counter() - started
        data = policy.dataset
        return [
            EvaluationRow(
                checkpoint,
                k,
                data.num_trajectories,
                len(data),
                float(returns[k]),
                float(self.expert_returns[k]),
                float(self.optimal_returns[k]),
                float(lower[k]),
                float(upper[k]),
                float(slopes[k]),
                wall,
            )
            for k in range(len(self.states))
        ]


def check_certificate(
    certificate: Certificate,
    dataset: Dataset,
    arm: Arm,
    seed: int,
    settings: ExperimentSettings,
    expert: Expert,
    count: int,
    progress: Callable[[str, int, int], None] | None = None,
    expert_returns: FloatArray | None = None,
    expert_budget_stops: int = 0,
    robots: Sequence[Robot] | None = None,
) -> HeldOutCheck:
    """The certified policy (the greedy policy over the trajectories it names) on ``count`` fresh s0.

    ``progress(phase, done, total)``: phase "policy" (the rollouts), then "expert" (its requests).

    The gap is to the exact optimal H-step return where the claim is about V* and the expert is
    optimal; otherwise (oracle mode, the detuned expert, an optimizer expert, a set of robots) to the expert's own
    H-step return from the same s0. ``expert_returns``: the expert's returns from the held-out s0 (npp-experiment's
    stream, EXPERIMENT_HELD_OUT_STREAM) where already asked for (in parallel; ``expert_budget_stops`` of them cut
    by its time budget); else asked here one at a time. ``robots``: held-out s0 k is checked on robot k (a run on a
    set of robots), the expert planning as the arm's did. A success claim is checked as npp-learn checks it: the
    share of rollouts that met the task's criterion (``within``; no gap, no V_lb), asking no expert.
    """
    task = get_task(arm.task)
    states = held_out_states(arm.task, seed, count, EXPERIMENT_HELD_OUT_STREAM)
    spec = certificate.spec
    policy = policy_for(
        dataset.prefix(certificate.policy_trajectories), spec, arm.task, seed, certified_lipschitz(certificate)
    )
    policy_progress = None if progress is None else lambda k, n: progress("policy", k, n)
    if spec.certify == "success":
        met = check_success(
            policy, task, task.make_plant(seed), states, settings.horizon, p=spec.p, delta=spec.delta, robots=robots,
            progress=policy_progress,
        )  # fmt: skip
        return HeldOutCheck(
            states=met.states, reference=SUCCESS_REFERENCE, within=met.succeeded, fraction=met.fraction,
            p_value=met.p_value, rejected=met.rejected, below_v_lb=0, gap_q50=math.nan, gap_max=math.nan,
            wall_time=met.wall_time,
        )  # fmt: skip
    return check_policy(
        policy, task, task.make_plant(seed), expert, states, settings.horizon,
        epsilon=spec.epsilon, p=spec.p, delta=spec.delta,
        against_expert=compares_with_expert(arm, spec.certify),
        progress=policy_progress,
        expert_progress=None if progress is None else lambda k, n: progress("expert", k, n),
        expert_returns=expert_returns, expert_budget_stops=expert_budget_stops,
        robots=robots, expert_model=arm.expert_model,
    )  # fmt: skip


def compares_with_expert(arm: Arm, certify: str) -> bool:
    """Whether a certificate's claim is about the expert's own returns (oracle mode, a suboptimal expert, a set of
    robots, on which no optimum is known)."""
    return certify == "oracle" or arm.expert != get_task(arm.task).experts[0] or arm.uncertainty > 0


def held_out_asks_expert(arm: Arm, certify: str) -> bool:
    """Whether the held-out check needs expert requests: it compares with the expert, or the task knows no optimum
    (a success claim's check asks none: it counts the policy's successes)."""
    if certify == "success":
        return False
    return compares_with_expert(arm, certify) or not get_task(arm.task).optimal_expert


def read_held_out(run_dir: Path) -> HeldOutCheck | None:
    path = run_dir / "heldout.json"
    return HeldOutCheck(**json.loads(path.read_text())) if path.exists() else None
