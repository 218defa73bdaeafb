"""The results table: measured columns per (arm, seed), the verdicts they back, Markdown and CSV."""

from __future__ import annotations

import csv
import json
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
from scipy.stats import binom

from npp_ros.certificate.authoring import LOW_EXPERT_SUCCESS
from npp_ros.experiment.evaluation import SUCCESS_REFERENCE, HeldOutCheck
from npp_ros.experiment.runs import RunRecord
from npp_ros.run.records import SuccessCounts


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
    policy_return_q50: float  # median H-step return of the policy over the rollouts at evaluated_at
    expert_return_q50: float  # median H-step return of the data expert from the same s0
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
    # The task's success criterion over the run's episodes (npp_ros.tasks.success; 0 of 0: not judged)
    expert_successes: int = 0  # of the expert's answers from s0 ...
    expert_answers: int = 0  # ... judged
    policy_successes: int = 0  # of the policy's rollouts in episodes whose check measured them ...
    policy_checked: int = 0  # ... judged (a surrogate check measures none)
    acts: str = ""  # how the arm's policy acts where it is not the paper's (Arm.acts): arms differ by it too


def held_out_verdict(check: HeldOutCheck | None, p: float, delta: float) -> str:
    """The certificate's claim against fresh s0: a one-sided binomial test at level delta (of the share within
    epsilon, or for a success claim of the share that met the task's criterion)."""
    if check is None:
        return "no certificate"
    measure = "succeeded" if check.reference == SUCCESS_REFERENCE else "within eps"
    if check.rejected:
        return f"FALSE: {check.fraction:.1%} {measure}, claimed >= {p:.0%} (binomial p = {check.p_value:.2g})"
    if check.fraction >= p:
        return f"held ({check.fraction:.1%} {measure})"
    return f"below p, not significant ({check.fraction:.1%} {measure})"


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
    success = SuccessCounts.of(record.episodes, policy=record.arm.certify != "surrogate")
    certified = record.certified_episode is not None
    judged = verdict(certified, fraction, len(rows), violations, p, delta)
    judged = SUCCESS_VERDICT if certified and record.arm.certify == "success" else judged
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
        policy_return_q50=float(np.median([row.policy_return for row in rows])) if rows else float("nan"),
        expert_return_q50=float(np.median([row.expert_return for row in rows])) if rows else float("nan"),
        gap_q50=float(np.quantile(gaps, 0.5)),
        gap_q90=float(np.quantile(gaps, 0.9)),
        gap_max=float(np.max(gaps)),
        fraction_within_epsilon=fraction,
        gap_to_optimal_q50=float(np.quantile(to_optimal, 0.5)),
        lower_bound_violations=violations,
        crossed_bounds=sum(row.gap < 0 for row in record.episodes),
        max_visited_slope=max((row.visited_slope for row in rows), default=float("nan")),
        verdict=judged,
        wall_time_s=record.wall_time,
        held_out_states=check.states if check else 0,
        held_out_fraction=check.fraction if check else float("nan"),
        held_out_p_value=check.p_value if check else float("nan"),
        held_out_below_v_lb=check.below_v_lb if check else 0,
        held_out_verdict=held_out_verdict(check, p, delta),
        expert_successes=success.expert_successes,
        expert_answers=success.expert_answers,
        policy_successes=success.policy_successes,
        policy_checked=success.policy_checked,
        acts=record.arm.acts,
    )


RESULT_FIELDS = [f.name for f in fields(ResultRow)]
SUCCESS_VERDICT = "a success claim: see the held-out check"  # it bounds no gap: the evaluations' gaps judge nothing


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
  the same s0. "FALSE" when a one-sided binomial test rejects P(gap <= eps) >= p at level delta. A success
  claim is checked on the share of those rollouts that met the task's success criterion (no gap, no V_lb). An
  arm on a set of robots draws a fresh robot for each fresh s0 (its evaluations too), the policy and the expert
  both on it, and compares with the expert: no optimum is known on a drawn robot.
- gap: V^expert(s0) - V^pi(s0), measured H-step returns from the same s0, at the last evaluation (the
  certificate's episode, or the budget). For the detuned expert this is the gap the certificate is about
  (its data bound V^expert, not V*); "gap to optimum" compares with the optimal LQR controller.
- within eps: the fraction of the N fresh s0 with gap <= epsilon. Condition (i) claims >= p ("-": a success
  claim, which bounds no gap).
- returns < V_lb: rollouts whose return fell below V_lb(s0); impossible when L bounds the value's slope
  (Theorem 3.4, B.1 i).
- V_ub < V_lb at s0: episodes whose bounds crossed, which the data alone show cannot happen with a valid L.
- max slope visited: the largest |grad V^expert| = |P x| along the policy's evaluation rollouts. The analytic L
  is the sup over the expert's own trajectories; where the policy leaves them the slope can exceed it, and the
  guarantees then rest on an assumption this column shows to be false there.
- verdict: "held" when within eps >= p and no return fell below V_lb; "FAILED" when a one-sided binomial
  test rejects P(gap <= eps) >= p at level delta. A success claim bounds no gap: its verdict is the held-out
  check's.
- expert success, policy success: how often the expert's answers from s0, and the policy's rollouts in the
  episodes whose check measured them, met the task's success criterion, over the run's episodes (summed over
  the seeds per arm). A certificate is relative to its expert: one over an expert that rarely succeeds says
  nothing about doing the task. "-": not judged (the task states no criterion; a surrogate check measures no
  rollout).
"""


def certificate_table(rows: Sequence[ResultRow]) -> str:
    """Per arm: what certified, after how much, and whether the claim survived fresh s0."""
    head = (
        "| task | expert | L | certify (rule) | certified | episodes (median, range) | oracle calls (median) "
        "| held-out within eps (worst seed) | returns < V_lb (held-out) | verdicts |\n"
        "|---|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for (task, expert, setting, certify, rule, acts), group in _arms(rows).items():
        certs = [r.certified_episode for r in group if r.certified_episode is not None]
        episodes = [r.certified_episode if r.certified_episode is not None else r.episodes for r in group]
        span = f"{int(np.median(episodes))} ({min(episodes)}-{max(episodes)})"
        checked = [r for r in group if r.held_out_states]
        worst = f"{min(r.held_out_fraction for r in checked):.1%}" if checked else "-"
        worst += " succeeded" if checked and certify == "success" else ""
        below = f"{sum(r.held_out_below_v_lb for r in checked)}/{sum(r.held_out_states for r in checked)}"
        below = below if certify != "success" else "-"  # a success check measures no return against V_lb
        verdicts: dict[str, int] = {}
        for r in group:
            key = r.held_out_verdict.split(" (")[0].split(":")[0]
            verdicts[key] = verdicts.get(key, 0) + 1
        said = ", ".join(f"{v} x {k}" for k, v in verdicts.items())
        calls = int(np.median([r.oracle_calls for r in group]))
        lines.append(
            f"| {task} | {expert} | {setting} | {certify} ({rule}){acts} | {len(certs)}/{len(group)} | {span} "
            f"| {calls} | {worst} | {below if checked else '-'} | {said} |"
        )
    return head + "\n".join(lines) + "\n"


def _arms(rows: Sequence[ResultRow]) -> dict[tuple[str, str, str, str, str, str], list[ResultRow]]:
    """The rows by arm (seeds pooled); ``acts`` is the arm's policy as a cell's suffix ('' for the paper's)."""
    groups: dict[tuple[str, str, str, str, str, str], list[ResultRow]] = {}
    for row in rows:
        key = (row.task, row.expert, row.lipschitz_setting, row.certify, row.rule, row.acts)
        groups.setdefault(key, []).append(row)
    return groups


def _expert_cell(row: ResultRow) -> str:
    paper = (row.certify, row.rule) == ("surrogate", "paper")
    return (row.expert if paper else f"{row.expert}, {row.certify} ({row.rule})") + row.acts


def _within_cell(certify: str, fraction: float) -> str:
    """The share of evaluation gaps within epsilon; '-' for a success claim, which bounds no gap."""
    return "-" if certify == "success" else f"{fraction:.0%}"


def _slope_cell(row: ResultRow) -> str:
    above = row.max_visited_slope > row.lipschitz
    return f"**{row.max_visited_slope:.1f} > L**" if above else f"{row.max_visited_slope:.1f}"


def _success_cells(group: Sequence[ResultRow]) -> str:
    """The expert's and the policy's successes over the rows' episodes, as two table cells ("-": not judged)."""
    cells = []
    for done, judged in (("expert_successes", "expert_answers"), ("policy_successes", "policy_checked")):
        total = sum(getattr(r, judged) for r in group)
        count = sum(getattr(r, done) for r in group)
        low = done == "expert_successes" and count < LOW_EXPERT_SUCCESS * total
        cells.append(f"{count}/{total}{' **low**' if low else ''}" if total else "-")
    return " | ".join(cells)


def summary_table(rows: Sequence[ResultRow]) -> str:
    """One line per arm: what a user needs to decide whether to trust the certificates."""
    head = (
        "| task | expert | L used (slope needed) | certified | certified at (median, range) | oracle calls "
        "| return policy / expert (median) | within eps (worst seed) | returns < V_lb | V_ub < V_lb episodes "
        "| slope visited / L (max) | expert success | policy success | verdicts | compute s |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for (task, expert, _, certify, rule, acts), group in _arms(rows).items():
        expert = expert if (certify, rule) == ("surrogate", "paper") else f"{expert}, {certify} ({rule})"
        expert += acts
        used = "/".join(f"{r.lipschitz:.0f}" for r in group)
        needed = "/".join(f"{r.slope_needed:.0f}" for r in group)
        bound = "" if all(r.l_is_bound for r in group) else " **not a bound**"
        certs = [r.certified_episode for r in group if r.certified_episode is not None]
        at = f"{int(np.median(certs))} ({min(certs)}-{max(certs)})" if certs else "-"
        calls = int(np.median([r.oracle_calls for r in group]))
        policy = np.median([r.policy_return_q50 for r in group])
        returns = f"{policy:.0f} / {np.median([r.expert_return_q50 for r in group]):.0f}"
        worst = _within_cell(certify, min(r.fraction_within_epsilon for r in group))
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
        successes = _success_cells(group)
        lines.append(
            f"| {task} | {expert} | {used} ({needed}){bound} | {len(certs)}/{len(group)} | {at} | {calls} "
            f"| {returns} | {worst} | {below}/{total} | {crossed} | {ratio} | {successes} | {said} "
            f"| {compute:.0f} |"
        )
    return head + "\n".join(lines) + "\n"


def markdown_table(rows: Sequence[ResultRow]) -> str:
    head = (
        "| task | expert | L (needed) | seed | certified at | oracle calls | \\|D\\| | return q50 policy / expert "
        "| gap q50 / q90 / max | within eps | gap to optimum q50 | returns < V_lb | V_ub < V_lb at s0 "
        "| max slope visited | expert success | policy success | verdict | wall s |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for r in rows:
        bound = "" if r.l_is_bound else " **not a bound**"
        cert = str(r.certified_episode) if r.certified_episode is not None else f"none ({r.episodes})"
        within = _within_cell(r.certify, r.fraction_within_epsilon)
        lines.append(
            f"| {r.task} | {_expert_cell(r)} | {r.lipschitz:.0f} ({r.slope_needed:.0f}){bound} | {r.seed} | {cert} "
            f"| {r.oracle_calls} | {r.dataset_size} | {r.policy_return_q50:.1f} / {r.expert_return_q50:.1f} "
            f"| {r.gap_q50:.1f} / {r.gap_q90:.1f} / {r.gap_max:.1f} "
            f"| {within} | {r.gap_to_optimal_q50:.1f} | {r.lower_bound_violations}/{r.rollouts} "
            f"| {r.crossed_bounds} | {_slope_cell(r)} | {_success_cells([r])} | {r.verdict} | {r.wall_time_s:.0f} |"
        )
    return head + "\n".join(lines) + "\n"
