"""One (arm, seed): run or resume it to its certificate or budget, evaluating at checkpoints."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

from npp_ros.certificate.certifier import CertificationStatus
from npp_ros.experiment.arms import Arm, ExperimentSettings, arm_request
from npp_ros.experiment.evaluation import (
    EvaluationRow,
    Evaluator,
    HeldOutCheck,
    append_evaluations,
    check_certificate,
    held_out_asks_expert,
    read_evaluations,
    read_held_out,
)
from npp_ros.experiment.expert_requests import EVALUATION_FILE, HELD_OUT_FILE, LATER, ExpertReturns
from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.run.held_out import (
    EXPERIMENT_HELD_OUT_STREAM,
    KeptAnswers,
    answers_identity,
    held_out_robots,
    held_out_states,
)
from npp_ros.run.loop import NPPLoop, Observer
from npp_ros.run.progress import status_text
from npp_ros.run.records import EpisodeRow
from npp_ros.run.request import resolve_run
from npp_ros.run.setup import build_loop
from npp_ros.run.store import RUN_FILE
from npp_ros.tasks.registry import Expert, get_task


@dataclass(frozen=True)
class RunRecord:
    """Everything the plots and the table need from one (arm, seed), read back from its folder."""

    arm: Arm
    seed: int
    lipschitz: LipschitzConstant
    slope_needed: float  # sup of the data expert's value slope over its trajectories from S0 (NaN: unknown)
    epsilon: float
    episodes: list[EpisodeRow]
    evaluations: list[EvaluationRow]
    certified_episode: int | None
    wall_time: float
    held_out: HeldOutCheck | None = None


Progress = Callable[[str], None]


class _EpisodeProgress(Observer):
    """The worker's status line for one run: npp-learn's text (checked gap, streak), once a second."""

    def __init__(self, report: Progress, key: str, budget: int, epsilon: float, condition: str) -> None:
        self.report, self.key, self.budget = report, key, budget
        self.epsilon, self.condition = epsilon, condition
        self._last = 0.0

    def on_episode(self, row: EpisodeRow, status: CertificationStatus) -> None:
        now = time.monotonic()
        if now - self._last >= 1.0 or status.certified:
            self._last = now
            self.report(f"{self.key} (budget {self.budget}): {status_text(row, self.epsilon, status, self.condition)}")


def run_arm_seed(
    arm: Arm, seed: int, settings: ExperimentSettings, out_dir: Path, report: Progress | None = None
) -> RunRecord:
    """Runs (or resumes) one (arm, seed) to certification or budget, evaluating at checkpoints."""
    report = report or (lambda _text: None)
    key = f"{arm.name} seed {seed}"
    run_dir = out_dir / "runs" / f"{arm.name}-seed{seed}"
    run_dir.mkdir(parents=True, exist_ok=True)
    run = resolve_run(
        arm_request(arm, seed, settings), run_file=run_dir / RUN_FILE, kind=arm.expert,
        control_weight=settings.control_weight,
    )  # fmt: skip
    config, expert, epsilon, lipschitz = run.config, run.expert, run.epsilon, run.lipschitz
    budget = settings.max_episodes[arm.task]
    progress = _EpisodeProgress(report, key, budget, epsilon, config.spec.condition)
    loop = build_loop(config, expert, store_path=run_dir / RUN_FILE, observers=[progress])
    # A run on a set of robots claims over (s0, robot): each fresh s0 is checked on a fresh robot, drawn as npp-learn
    # draws its held-out robots (None on the exact model); the evaluations draw the first of the same robots, each
    # paired with an evaluation s0 (a stream of its own), so each set of pairs is fresh. The expert's returns from
    # both are kept in the run folder under the run's own identity, as npp-learn keeps its held-out ones.
    held_out_on = held_out_robots(config.uncertainty, seed, settings.held_out)
    identity = answers_identity(config)
    held_out_returns: ExpertReturns | None = None
    try:
        may_certify = loop.certificate is not None or loop.next_episode < budget  # else no held-out check follows
        if may_certify and not (run_dir / "heldout.json").exists() and held_out_asks_expert(arm, config.spec.certify):
            # they do not depend on the certificate: on a Dask cluster, idle workers answer them while the run runs
            states = held_out_states(arm.task, seed, settings.held_out, EXPERIMENT_HELD_OUT_STREAM)
            kept = KeptAnswers(run_dir / HELD_OUT_FILE, identity)
            held_out_returns = ExpertReturns(
                arm, seed, settings, states, expert, kept, priority=LATER, robots=held_out_on
            ).start()
        evaluations_path = run_dir / "evaluations.csv"
        done = {row.checkpoint for row in read_evaluations(evaluations_path)}
        evaluator: Evaluator | None = None
        for checkpoint in settings.checkpoints_for(arm.task):
            if loop.certificate is not None and loop.certificate.episodes < checkpoint:
                checkpoint = loop.certificate.episodes  # the run ended here: evaluate what it certified
            if checkpoint in done:
                continue
            loop.run(checkpoint)
            reached = min(checkpoint, loop.next_episode)
            if reached in done:
                continue
            # Resumed past an unevaluated checkpoint: the data (and the policy's L) as they were there.
            policy = loop.policy_over(policy_trajectories_at(loop, reached))
            if evaluator is None:
                asked = lambda k, n: report(f"{key}: the expert from evaluation s0 {k}/{n}")  # noqa: E731
                evaluator = Evaluator(
                    arm, seed, settings, expert, asked, kept=KeptAnswers(run_dir / EVALUATION_FILE, identity),
                    robots=held_out_robots(config.uncertainty, seed, settings.evaluations),
                )  # fmt: skip
            label = f"{key}: evaluating at episode {reached}"
            rows = evaluator.evaluate(reached, policy, lambda k, n, label=label: report(f"{label}: {k}/{n}"))
            append_evaluations(evaluations_path, rows)
            done.add(reached)
            if loop.certificate is not None and reached >= loop.certificate.episodes:
                break
        if loop.certificate is not None and not (run_dir / "heldout.json").exists():

            def held_out(phase: str, done: int, total: int) -> None:
                report(f"{key}: checking the certificate on held-out s0: {phase} {done}/{total}")

            returns, stops = None, 0
            if held_out_returns is not None:  # asked for ahead: what no worker started is answered here
                returns = held_out_returns.result(lambda k, n: held_out("expert", k, n))
                stops = held_out_returns.budget_stops
            check = check_certificate(
                loop.certificate, loop.dataset, arm, seed, settings, expert, settings.held_out, held_out,
                returns, stops, held_out_on,
            )  # fmt: skip
            (run_dir / "heldout.json").write_text(json.dumps(asdict(check), indent=2) + "\n")
        return read_record(arm, seed, epsilon, run_dir, loop, expert, lipschitz)
    finally:
        if held_out_returns is not None:
            held_out_returns.close()  # keeps what finished, drops what a run without a certificate asked for
        if loop.store is not None:
            loop.store.close()


def policy_trajectories_at(loop: NPPLoop, episodes: int) -> int:
    """How many trajectories the policy acted on after ``episodes`` episodes (held-back data excluded)."""
    if episodes == 0:
        return 0
    if loop.certificate is not None and episodes == loop.certificate.episodes:
        return loop.certificate.policy_trajectories
    return sum(row.oracle_called for row in loop.rows[:episodes]) - loop.held_back_after(episodes)


def read_record(
    arm: Arm,
    seed: int,
    epsilon: float,
    run_dir: Path,
    loop: NPPLoop,
    expert: Expert,
    lipschitz: LipschitzConstant,
) -> RunRecord:
    evaluations = read_evaluations(run_dir / "evaluations.csv")
    wall = sum(row.wall_time for row in loop.rows) + sum({r.checkpoint: r.wall_time for r in evaluations}.values())
    return RunRecord(
        arm=arm,
        seed=seed,
        lipschitz=lipschitz,
        slope_needed=slope_needed(arm.task, expert),
        epsilon=epsilon,  # the run's (a success claim on a task without one: a stand-in never read)
        episodes=list(loop.rows),
        evaluations=evaluations,
        certified_episode=loop.certificate.episodes if loop.certificate else None,
        wall_time=wall,
        held_out=read_held_out(run_dir),
    )


def slope_needed(task: str, expert: Expert) -> float:
    """The analytic bound on the expert's value slope where the task computes one, else NaN."""
    spec = get_task(task)
    return spec.analytic_lipschitz(expert).value if "analytic" in spec.lipschitz_choices() else math.nan
