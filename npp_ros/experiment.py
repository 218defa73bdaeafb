"""The paper's Section 5 experiments (and Appendix B with a detuned expert), run in process.

One *arm* is a task, the expert that supplies data (optimal LQR or a detuned one), a choice
of L (the paper's, or one that bounds the expert's value slope) and what certifies (the paper's
surrogate gap and one-shot rule, or a sound mode under the sequential rule). Each (arm, seed) runs the same
:class:`~npp_ros.loop.NPPLoop` as the supervisor node, stored in its own ``run.sqlite``, and is
evaluated at checkpoints on a fixed set of N initial states s0 ~ rho: the policy's return, the
data expert's and the optimal controller's returns from the same s0, and V_lb(s0). Everything is
rebuilt from the files, so a resumed or repeated run gives the same numbers. Every certificate is
also checked on HELD_OUT fresh s0 (a stream of its own): the fraction whose gap, for the value the
certificate speaks of, is within epsilon, and a one-sided binomial test of its claim.
"""

from __future__ import annotations

import csv
import json
import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
from scipy.stats import binom

from npp_ros.bounds import NonparametricPolicy
from npp_ros.certification import CERTIFY_MODES, STOPPING_RULES, Certificate
from npp_ros.dataset import Dataset, FloatArray
from npp_ros.inprocess import build_config, build_loop, resolve_lipschitz
from npp_ros.lipschitz import LipschitzConstant
from npp_ros.loop import NPPLoop, Observer
from npp_ros.lqr import (
    PAPER_EPSILON,
    TASKS,
    DetunedLQRExpert,
    LQRExpert,
    LQRPlant,
    rollout_batch,
    sample_initial_state,
)
from npp_ros.storage import EpisodeRow

EXPERTS = ("optimal", "detuned")
LIPSCHITZ_SETTINGS = ("paper", "analytic")
DEFAULT_CHECKPOINTS = (10, 25, 50, 100, 250, 500, 1000)
DETUNED_CONTROL_WEIGHT = 0.1
EVALUATION_STREAM = 1 << 30  # rng stream for evaluation s0; the run's own s0 use [seed, episode]
VIOLATION_TOLERANCE = 1e-9
EVALUATION_CHUNK = 25  # rollouts stepped in lockstep (batched policy queries)
HELD_OUT = 1000  # fresh s0 on which every certificate is checked
HELD_OUT_STREAM = EVALUATION_STREAM + 1
HELD_OUT_CHUNK = 100


@dataclass(frozen=True)
class Arm:
    """One line of the results table, over seeds."""

    task: str
    expert: str  # "optimal" or "detuned"
    lipschitz: str  # "paper", "analytic" or a number
    certify: str = "surrogate"  # the paper's checked quantity ...
    rule: str = "paper"  # ... and its stopping rule, unless the arm says otherwise

    def __post_init__(self) -> None:
        if self.certify not in CERTIFY_MODES:
            raise ValueError(f"unknown certification mode {self.certify!r}; known: {', '.join(CERTIFY_MODES)}")
        if self.rule not in STOPPING_RULES:
            raise ValueError(f"unknown stopping rule {self.rule!r}; known: {', '.join(STOPPING_RULES)}")
        if self.task not in TASKS:
            raise ValueError(f"unknown task {self.task!r}; known: {', '.join(sorted(TASKS))}")
        if self.expert not in EXPERTS:
            raise ValueError(f"unknown expert {self.expert!r}; known: {', '.join(EXPERTS)}")
        if self.lipschitz not in LIPSCHITZ_SETTINGS:
            try:
                value = float(self.lipschitz)
            except ValueError:
                value = math.nan
            if not (math.isfinite(value) and value > 0):
                known = ", ".join(LIPSCHITZ_SETTINGS)
                raise ValueError(f"L setting must be one of {known} or a number > 0, got {self.lipschitz!r}")

    @property
    def paper_certification(self) -> bool:
        return (self.certify, self.rule) == ("surrogate", "paper")

    @property
    def name(self) -> str:
        base = f"{self.task}-{self.expert}-L{self.lipschitz}"
        return base if self.paper_certification else f"{base}-{self.certify}-{self.rule}"

    @property
    def label(self) -> str:
        expert = "optimal expert" if self.expert == "optimal" else "detuned expert"
        how = "" if self.paper_certification else f", certify={self.certify} ({self.rule})"
        return f"{self.task}, {expert}, {self.lipschitz} L{how}"


@dataclass(frozen=True)
class ExperimentSettings:
    """What every (arm, seed) shares; defaults follow the paper."""

    max_episodes: dict[str, int]
    evaluations: int = 100  # N
    checkpoints: tuple[int, ...] = DEFAULT_CHECKPOINTS
    horizon: int = 1000
    p: float = 0.9
    delta: float = 0.1
    epsilon: dict[str, float] | None = None
    control_weight: float = DETUNED_CONTROL_WEIGHT

    def epsilon_for(self, task: str) -> float:
        return (self.epsilon or {}).get(task, PAPER_EPSILON[task])

    def checkpoints_for(self, task: str) -> list[int]:
        budget = self.max_episodes[task]
        return sorted({c for c in self.checkpoints if 0 < c <= budget} | {budget})


def default_arms(
    tasks: Sequence[str], lipschitz: Sequence[str], experts: Sequence[str], certify: Sequence[str] = ("paper",)
) -> list[Arm]:
    """The detuned expert is not run with the paper's L: the paper gives none for it.

    ``certify`` lists "paper" (the surrogate gap under the paper's one-shot rule) and sound modes
    (rollout, oracle, surrogate) under the sequential rule.
    """
    arms = []
    for task in tasks:
        for expert in experts:
            for setting in lipschitz:
                if expert == "detuned" and setting == "paper":
                    continue
                for mode in certify:
                    if mode == "paper":
                        arms.append(Arm(task, expert, setting))
                    else:
                        arms.append(Arm(task, expert, setting, mode, "sequential"))
    return arms


def make_expert(arm: Arm, seed: int, settings: ExperimentSettings) -> LQRExpert:
    if arm.expert == "detuned":
        return DetunedLQRExpert(arm.task, seed, settings.control_weight, horizon=settings.horizon)
    return LQRExpert(arm.task, seed, horizon=settings.horizon)


def evaluation_states(task: str, seed: int, count: int) -> FloatArray:
    """The fixed N initial states every checkpoint of a seed is evaluated on (common random numbers)."""
    rng = np.random.default_rng([seed, EVALUATION_STREAM])
    return np.array([sample_initial_state(task, rng) for _ in range(count)])


def dataset_prefix(dataset: Dataset, trajectories: int) -> Dataset:
    """The dataset as it was after its first ``trajectories`` oracle calls."""
    prefix = Dataset(dataset.state_dim, dataset.action_dim)
    for index in range(trajectories):
        prefix.append(dataset.trajectory(index))
    return prefix


# ---------------------------------------------------------------------------------- evaluation
@dataclass(frozen=True)
class EvaluationRow:
    """One rollout from one evaluation s0 at one checkpoint."""

    checkpoint: int  # episodes done when evaluated
    rollout: int
    oracle_calls: int
    dataset_size: int
    policy_return: float
    expert_return: float  # the data expert from the same s0
    optimal_return: float  # the optimal LQR controller from the same s0
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

    def __init__(self, arm: Arm, seed: int, settings: ExperimentSettings, expert: LQRExpert) -> None:
        self.settings = settings
        self.expert = expert
        self.plant = LQRPlant(arm.task, seed)
        self.states = evaluation_states(arm.task, seed, settings.evaluations)
        optimal = expert if arm.expert == "optimal" else LQRExpert(arm.task, seed, horizon=settings.horizon)
        self.optimal_returns = self._returns(optimal.action)
        self.expert_returns = self.optimal_returns if optimal is expert else self._returns(expert.action)

    def _returns(self, controller: Callable[[FloatArray], FloatArray]) -> FloatArray:
        def batch(states: FloatArray) -> FloatArray:
            return np.array([controller(x) for x in states])

        runs = rollout_batch(self.plant, batch, self.states, self.settings.horizon)
        return np.array([run.total_return for run in runs])

    def evaluate(
        self, checkpoint: int, policy: NonparametricPolicy, progress: Callable[[int, int], None] | None = None
    ) -> list[EvaluationRow]:
        started = time.perf_counter()
        lower = np.asarray(policy.v_lb(self.states))
        upper = np.asarray(policy.v_ub(self.states))
        returns = np.empty(len(self.states))
        slopes = np.empty(len(self.states))
        for lo in range(0, len(self.states), EVALUATION_CHUNK):
            hi = min(lo + EVALUATION_CHUNK, len(self.states))
            for k, run in enumerate(rollout_batch(self.plant, policy.act, self.states[lo:hi], self.settings.horizon)):
                returns[lo + k] = run.total_return
                slopes[lo + k] = float(np.max(self.expert.slope(run.states)))
            if progress is not None:
                progress(hi, len(self.states))
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


# ---------------------------------------------------------------------------------- one run
@dataclass(frozen=True)
class RunRecord:
    """Everything the plots and the table need from one (arm, seed), read back from its folder."""

    arm: Arm
    seed: int
    lipschitz: LipschitzConstant
    slope_needed: float  # sup of the data expert's value slope over its trajectories from S0
    epsilon: float
    episodes: list[EpisodeRow]
    evaluations: list[EvaluationRow]
    certified_episode: int | None
    wall_time: float
    held_out: HeldOutCheck | None = None


Progress = Callable[[str], None]


class _EpisodeProgress(Observer):
    def __init__(self, report: Progress, key: str, budget: int) -> None:
        self.report, self.key, self.budget = report, key, budget
        self._last = 0.0

    def on_episode(self, row: EpisodeRow, status) -> None:
        now = time.monotonic()
        if now - self._last >= 1.0 or row.certified:
            self._last = now
            gap = "inf" if math.isinf(row.gap) else f"{row.gap:.1f}"
            self.report(f"{self.key}: episode {row.episode + 1}/{self.budget}, gap {gap}, oracle {row.oracle_calls}")


def run_arm_seed(
    arm: Arm, seed: int, settings: ExperimentSettings, out_dir: Path, report: Progress | None = None
) -> RunRecord:
    """Runs (or resumes) one (arm, seed) to certification or budget, evaluating at checkpoints."""
    report = report or (lambda _text: None)
    key = f"{arm.name} seed {seed}"
    run_dir = out_dir / "runs" / f"{arm.name}-seed{seed}"
    run_dir.mkdir(parents=True, exist_ok=True)
    expert = make_expert(arm, seed, settings)
    lipschitz = resolve_lipschitz(arm.task, arm.lipschitz, expert)
    epsilon = settings.epsilon_for(arm.task)
    config = build_config(
        arm.task, seed, lipschitz, epsilon, p=settings.p, delta=settings.delta, horizon=settings.horizon,
        certify=arm.certify, rule=arm.rule,  # type: ignore[arg-type]  # Arm checks both
    )  # fmt: skip
    budget = settings.max_episodes[arm.task]
    loop = build_loop(
        config, expert, store_path=run_dir / "run.sqlite", observers=[_EpisodeProgress(report, key, budget)]
    )
    try:
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
            calls = policy_trajectories_at(loop, reached)
            if calls == loop.policy_data.num_trajectories:
                policy = loop.policy  # its search index is already built
            else:  # resumed past an unevaluated checkpoint: rebuild the data as it was there
                policy = NonparametricPolicy(dataset_prefix(loop.dataset, calls), lipschitz.value)
            if evaluator is None:
                report(f"{key}: reference rollouts")
                evaluator = Evaluator(arm, seed, settings, expert)
            label = f"{key}: evaluating at episode {reached}"
            rows = evaluator.evaluate(reached, policy, lambda k, n, label=label: report(f"{label}: {k}/{n}"))
            append_evaluations(evaluations_path, rows)
            done.add(reached)
            if loop.certificate is not None and reached >= loop.certificate.episodes:
                break
        if loop.certificate is not None and not (run_dir / "heldout.json").exists():
            report(f"{key}: checking the certificate on {HELD_OUT} held-out s0")
            check = check_certificate(loop.certificate, loop.dataset, arm, seed, settings, expert, HELD_OUT)
            (run_dir / "heldout.json").write_text(json.dumps(asdict(check), indent=2) + "\n")
        return read_record(arm, seed, settings, run_dir, loop, expert, lipschitz)
    finally:
        if loop.store is not None:
            loop.store.close()


def policy_trajectories_at(loop: NPPLoop, episodes: int) -> int:
    """How many trajectories the policy acted on after ``episodes`` episodes (held-back data excluded)."""
    if episodes == 0:
        return 0
    if loop.certificate is not None and episodes == loop.certificate.episodes:
        return loop.certificate.policy_trajectories
    calls = sum(row.oracle_called for row in loop.rows[:episodes])
    if loop.config.certify != "oracle":
        return calls
    held = 0
    for row in reversed(loop.rows[:episodes]):
        if row.checked_gap > loop.config.epsilon:
            break
        held += int(row.oracle_called)
    return calls - held


@dataclass(frozen=True)
class HeldOutCheck:
    """A certificate against fresh s0 ~ rho: does its claim P(gap <= epsilon) >= p survive?"""

    states: int
    reference: str  # the value each gap is measured against (the certificate's)
    within: int
    fraction: float
    p_value: float  # P[X <= within] for X ~ Binomial(states, p): small means the claim is contradicted
    rejected: bool  # p_value < delta
    below_v_lb: int  # returns below V_lb(s0) of the certified policy
    gap_q50: float
    gap_max: float
    wall_time: float


def check_certificate(
    certificate: Certificate,
    dataset: Dataset,
    arm: Arm,
    seed: int,
    settings: ExperimentSettings,
    expert: LQRExpert,
    count: int,
) -> HeldOutCheck:
    """Rolls the certified policy out from ``count`` fresh s0 and measures the gap its claim is about.

    The reference is the exact optimal H-step return H - 0.5 s0'P_H s0 where the claim is about V*
    and the expert is optimal; otherwise (oracle mode, or the detuned expert) the expert's own
    H-step return from the same s0, measured in MuJoCo.
    """
    started = time.perf_counter()
    rng = np.random.default_rng([seed, HELD_OUT_STREAM])
    states = np.array([sample_initial_state(arm.task, rng) for _ in range(count)])
    policy = NonparametricPolicy(dataset_prefix(dataset, certificate.policy_trajectories), certificate.lipschitz)
    plant = LQRPlant(arm.task, seed)
    returns = np.empty(count)
    for lo in range(0, count, HELD_OUT_CHUNK):
        chunk = states[lo : lo + HELD_OUT_CHUNK]
        for k, run in enumerate(rollout_batch(plant, policy.act, chunk, settings.horizon)):
            returns[lo + k] = run.total_return
    if certificate.certify == "oracle" or arm.expert == "detuned":
        runs = rollout_batch(plant, lambda xs: np.array([expert.action(x) for x in xs]), states, settings.horizon)
        reference, what = np.array([run.total_return for run in runs]), "the expert's H-step return"
    else:
        p_h = expert.finite_horizon_cost(settings.horizon)
        reference = settings.horizon - 0.5 * np.einsum("bi,ij,bj->b", states, p_h, states)
        what = "the optimal H-step return V*_H"
    gaps = reference - returns
    within = int(np.sum(gaps <= certificate.epsilon))
    p_value = float(binom.cdf(within, count, certificate.p))
    lower = np.asarray(policy.v_lb(states))
    below = int(np.sum(returns < lower - VIOLATION_TOLERANCE * np.maximum(1.0, np.abs(lower))))
    return HeldOutCheck(
        states=count, reference=what, within=within, fraction=within / count, p_value=p_value,
        rejected=p_value < certificate.delta, below_v_lb=below, gap_q50=float(np.median(gaps)),
        gap_max=float(np.max(gaps)), wall_time=time.perf_counter() - started,
    )  # fmt: skip


def read_held_out(run_dir: Path) -> HeldOutCheck | None:
    path = run_dir / "heldout.json"
    return HeldOutCheck(**json.loads(path.read_text())) if path.exists() else None


def read_record(
    arm: Arm,
    seed: int,
    settings: ExperimentSettings,
    run_dir: Path,
    loop: NPPLoop,
    expert: LQRExpert,
    lipschitz: LipschitzConstant,
) -> RunRecord:
    evaluations = read_evaluations(run_dir / "evaluations.csv")
    wall = sum(row.wall_time for row in loop.rows) + sum({r.checkpoint: r.wall_time for r in evaluations}.values())
    return RunRecord(
        arm=arm,
        seed=seed,
        lipschitz=lipschitz,
        slope_needed=expert.analytic_lipschitz().value,
        epsilon=settings.epsilon_for(arm.task),
        episodes=list(loop.rows),
        evaluations=evaluations,
        certified_episode=loop.certificate.episodes if loop.certificate else None,
        wall_time=wall,
        held_out=read_held_out(run_dir),
    )


# ---------------------------------------------------------------------------------- the table
@dataclass(frozen=True)
class ResultRow:
    """One (arm, seed): the measured columns and the verdict they back."""

    task: str
    expert: str
    lipschitz_setting: str
    certify: str
    rule: str
    seed: int
    lipschitz: float
    slope_needed: float
    l_is_bound: bool
    epsilon: float
    certified_episode: int | None
    episodes: int
    oracle_calls: int
    dataset_size: int
    evaluated_at: int
    rollouts: int
    gap_q50: float  # gap to the data expert, V^expert(s0) - V^pi(s0), measured returns
    gap_q90: float
    gap_max: float
    fraction_within_epsilon: float
    gap_to_optimal_q50: float
    lower_bound_violations: int
    crossed_bounds: int  # episodes with V_ub(s0) < V_lb(s0): the data alone prove L is too small
    max_visited_slope: float
    verdict: str
    wall_time_s: float
    held_out_states: int  # fresh s0 the certificate was checked on (0: no certificate)
    held_out_fraction: float  # of those, the share with gap <= epsilon for the certificate's value
    held_out_p_value: float
    held_out_below_v_lb: int
    held_out_verdict: str


def held_out_verdict(check: HeldOutCheck | None, p: float, delta: float) -> str:
    """The certificate's claim against fresh s0: a one-sided binomial test at level delta."""
    if check is None:
        return "no certificate"
    if check.rejected:
        return f"FALSE: {check.fraction:.1%} within eps, claimed >= {p:.0%} (binomial p = {check.p_value:.2g})"
    if check.fraction >= p:
        return f"held ({check.fraction:.1%} within eps)"
    return f"below p, not significant ({check.fraction:.1%} within eps)"


def verdict(certified: bool, fraction: float, rollouts: int, violations: int, p: float, delta: float) -> str:
    """What the measurement says about the certificate's claim P(gap <= eps) >= p.

    "contradicted": a one-sided binomial test rejects P(gap <= eps) >= p at level delta.
    """
    if not certified:
        return "no certificate"
    within = round(fraction * rollouts)
    if fraction >= p:
        if violations:
            return f"held here, but L is not a bound ({violations} returns < V_lb)"
        return "held"
    if binom.cdf(within, rollouts, p) < delta:
        return f"FAILED: {fraction:.0%} within eps, claimed >= {p:.0%}"
    return f"below p, not significant ({fraction:.0%} within eps)"


def result_row(record: RunRecord, p: float, delta: float) -> ResultRow:
    final = max((row.checkpoint for row in record.evaluations), default=0)
    rows = [row for row in record.evaluations if row.checkpoint == final]
    gaps = np.array([row.gap_to_expert for row in rows]) if rows else np.array([np.nan])
    to_optimal = np.array([row.gap_to_optimal for row in rows]) if rows else np.array([np.nan])
    fraction = float(np.mean(gaps <= record.epsilon)) if rows else float("nan")
    violations = sum(row.violates_lower_bound for row in rows)
    last = record.episodes[-1] if record.episodes else None
    check = record.held_out
    return ResultRow(
        task=record.arm.task,
        expert=record.arm.expert,
        lipschitz_setting=record.arm.lipschitz,
        certify=record.arm.certify,
        rule=record.arm.rule,
        seed=record.seed,
        lipschitz=record.lipschitz.value,
        slope_needed=record.slope_needed,
        l_is_bound=record.lipschitz.value >= record.slope_needed,
        epsilon=record.epsilon,
        certified_episode=record.certified_episode,
        episodes=len(record.episodes),
        oracle_calls=last.oracle_calls if last else 0,
        dataset_size=last.dataset_size if last else 0,
        evaluated_at=final,
        rollouts=len(rows),
        gap_q50=float(np.quantile(gaps, 0.5)),
        gap_q90=float(np.quantile(gaps, 0.9)),
        gap_max=float(np.max(gaps)),
        fraction_within_epsilon=fraction,
        gap_to_optimal_q50=float(np.quantile(to_optimal, 0.5)),
        lower_bound_violations=violations,
        crossed_bounds=sum(row.gap < 0 for row in record.episodes),
        max_visited_slope=max((row.visited_slope for row in rows), default=float("nan")),
        verdict=verdict(record.certified_episode is not None, fraction, len(rows), violations, p, delta),
        wall_time_s=record.wall_time,
        held_out_states=check.states if check else 0,
        held_out_fraction=check.fraction if check else float("nan"),
        held_out_p_value=check.p_value if check else float("nan"),
        held_out_below_v_lb=check.below_v_lb if check else 0,
        held_out_verdict=held_out_verdict(check, p, delta),
    )


RESULT_FIELDS = [f.name for f in fields(ResultRow)]


def write_results(rows: Iterable[ResultRow], out_dir: Path) -> list[Path]:
    """results.csv and results.json for tools, results.md for people."""
    rows = list(rows)
    paths = [out_dir / "results.csv", out_dir / "results.json", out_dir / "results.md"]
    with paths[0].open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(RESULT_FIELDS)
        for row in rows:
            writer.writerow(["" if v is None else v for v in (getattr(row, n) for n in RESULT_FIELDS)])
    paths[1].write_text(json.dumps([asdict(row) for row in rows], indent=2) + "\n")
    paths[2].write_text(
        "# npp-experiment results\n\n## Certificates, checked on held-out s0\n\n"
        + certificate_table(rows)
        + "\n## Per arm (seeds pooled)\n\n"
        + summary_table(rows)
        + "\n"
        + COLUMN_NOTES
        + "\n## Per seed\n\n"
        + markdown_table(rows)
    )
    return paths


COLUMN_NOTES = """\
- certificates table: each certificate's policy (the greedy policy over the trajectories it names) rolled out
  from 1,000 fresh s0 ~ rho (a stream of their own), against the value the certificate speaks of: the exact
  optimal H-step return when it claims V* and the expert is optimal, else the expert's own H-step return from
  the same s0. "FALSE" when a one-sided binomial test rejects P(gap <= eps) >= p at level delta.
- gap: V^expert(s0) - V^pi(s0), measured H-step returns from the same s0, at the last evaluation (the
  certificate's episode, or the budget). For the detuned expert this is the gap the certificate is about
  (its data bound V^expert, not V*); "gap to optimum" compares with the optimal LQR controller.
- within eps: the fraction of the N fresh s0 with gap <= epsilon. Condition (i) claims >= p.
- returns < V_lb: rollouts whose return fell below V_lb(s0); impossible when L bounds the value's slope
  (Theorem 3.4, B.1 i).
- V_ub < V_lb at s0: episodes whose bounds crossed, which the data alone show cannot happen with a valid L.
- max slope visited: the largest |grad V^expert| = |P x| along the policy's evaluation rollouts. The analytic L
  is the sup over the expert's own trajectories; where the policy leaves them the slope can exceed it, and the
  guarantees then rest on an assumption this column shows to be false there.
- verdict: "held" when within eps >= p and no return fell below V_lb; "FAILED" when a one-sided binomial
  test rejects P(gap <= eps) >= p at level delta.
"""


def certificate_table(rows: Sequence[ResultRow]) -> str:
    """Per arm: what certified, after how much, and whether the claim survived fresh s0."""
    head = (
        "| task | expert | L | certify (rule) | certified | episodes (median, range) | oracle calls (median) "
        "| held-out within eps (worst seed) | returns < V_lb (held-out) | verdicts |\n"
        "|---|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for (task, expert, setting, certify, rule), group in _arms(rows).items():
        certs = [r.certified_episode for r in group if r.certified_episode is not None]
        episodes = [r.certified_episode if r.certified_episode is not None else r.episodes for r in group]
        span = f"{int(np.median(episodes))} ({min(episodes)}-{max(episodes)})"
        checked = [r for r in group if r.held_out_states]
        worst = f"{min(r.held_out_fraction for r in checked):.1%}" if checked else "-"
        below = f"{sum(r.held_out_below_v_lb for r in checked)}/{sum(r.held_out_states for r in checked)}"
        verdicts: dict[str, int] = {}
        for r in group:
            key = r.held_out_verdict.split(" (")[0].split(":")[0]
            verdicts[key] = verdicts.get(key, 0) + 1
        said = ", ".join(f"{v} x {k}" for k, v in verdicts.items())
        calls = int(np.median([r.oracle_calls for r in group]))
        lines.append(
            f"| {task} | {expert} | {setting} | {certify} ({rule}) | {len(certs)}/{len(group)} | {span} | {calls} "
            f"| {worst} | {below if checked else '-'} | {said} |"
        )
    return head + "\n".join(lines) + "\n"


def _arms(rows: Sequence[ResultRow]) -> dict[tuple[str, str, str, str, str], list[ResultRow]]:
    groups: dict[tuple[str, str, str, str, str], list[ResultRow]] = {}
    for row in rows:
        groups.setdefault((row.task, row.expert, row.lipschitz_setting, row.certify, row.rule), []).append(row)
    return groups


def _expert_cell(row: ResultRow) -> str:
    paper = (row.certify, row.rule) == ("surrogate", "paper")
    return row.expert if paper else f"{row.expert}, {row.certify} ({row.rule})"


def _slope_cell(row: ResultRow) -> str:
    above = row.max_visited_slope > row.lipschitz
    return f"**{row.max_visited_slope:.1f} > L**" if above else f"{row.max_visited_slope:.1f}"


def summary_table(rows: Sequence[ResultRow]) -> str:
    """One line per arm: what a user needs to decide whether to trust the certificates."""
    head = (
        "| task | expert | L used (slope needed) | certified | certified at (median, range) | oracle calls "
        "| within eps (worst seed) | returns < V_lb | V_ub < V_lb episodes | slope visited / L (max) "
        "| verdicts | compute s |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for (task, expert, _, certify, rule), group in _arms(rows).items():
        expert = expert if (certify, rule) == ("surrogate", "paper") else f"{expert}, {certify} ({rule})"
        used = "/".join(f"{r.lipschitz:.0f}" for r in group)
        needed = "/".join(f"{r.slope_needed:.0f}" for r in group)
        bound = "" if all(r.l_is_bound for r in group) else " **not a bound**"
        certs = [r.certified_episode for r in group if r.certified_episode is not None]
        at = f"{int(np.median(certs))} ({min(certs)}-{max(certs)})" if certs else "-"
        calls = int(np.median([r.oracle_calls for r in group]))
        worst = min(r.fraction_within_epsilon for r in group)
        below = sum(r.lower_bound_violations for r in group)
        total = sum(r.rollouts for r in group)
        crossed = sum(r.crossed_bounds for r in group)
        verdicts: dict[str, int] = {}
        for r in group:
            key = r.verdict.split(" (")[0].split(":")[0]
            verdicts[key] = verdicts.get(key, 0) + 1
        said = ", ".join(f"{v} x {k}" for k, v in verdicts.items())
        compute = sum(r.wall_time_s for r in group)
        ratio = f"{max(r.max_visited_slope / r.lipschitz for r in group):.2f}"
        above = sum(r.max_visited_slope > r.lipschitz for r in group)
        ratio += f" (**{above} of {len(group)} seeds above L**)" if above else ""
        lines.append(
            f"| {task} | {expert} | {used} ({needed}){bound} | {len(certs)}/{len(group)} | {at} | {calls} "
            f"| {worst:.0%} | {below}/{total} | {crossed} | {ratio} | {said} | {compute:.0f} |"
        )
    return head + "\n".join(lines) + "\n"


def markdown_table(rows: Sequence[ResultRow]) -> str:
    head = (
        "| task | expert | L (needed) | seed | certified at | oracle calls | \\|D\\| | gap q50 / q90 / max "
        "| within eps | gap to optimum q50 | returns < V_lb | V_ub < V_lb at s0 | max slope visited "
        "| verdict | wall s |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for r in rows:
        bound = "" if r.l_is_bound else " **not a bound**"
        cert = str(r.certified_episode) if r.certified_episode is not None else f"none ({r.episodes})"
        lines.append(
            f"| {r.task} | {_expert_cell(r)} | {r.lipschitz:.0f} ({r.slope_needed:.0f}){bound} | {r.seed} | {cert} "
            f"| {r.oracle_calls} | {r.dataset_size} | {r.gap_q50:.1f} / {r.gap_q90:.1f} / {r.gap_max:.1f} "
            f"| {r.fraction_within_epsilon:.0%} | {r.gap_to_optimal_q50:.1f} | {r.lower_bound_violations}/{r.rollouts} "
            f"| {r.crossed_bounds} | {_slope_cell(r)} | {r.verdict} | {r.wall_time_s:.0f} |"
        )
    return head + "\n".join(lines) + "\n"
