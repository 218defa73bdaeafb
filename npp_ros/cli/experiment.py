"""npp-experiment: the paper's lqr experiments (Section 5, Figures 4-5) and Appendix B, in process.

Runs Algorithm 1 with the same core loop as the supervisor node for every arm (task x expert x
L setting) and seed, evaluates the policy at checkpoints with N rollouts from s0 ~ rho against
the expert from the same s0, and writes Figure-4 and Figure-5 style PNGs and a results table
(results.md, results.csv, results.json). Runs are stored under OUT/runs/ and resume: a repeated
command recomputes nothing and gives the same numbers.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import platform
import queue
import sys
import time
from collections import defaultdict
from concurrent.futures import Future, ProcessPoolExecutor
from pathlib import Path
from typing import Any

from npp_ros.certification import CERTIFY_MODES
from npp_ros.cli.args import nonnegative_int, positive_int, positive_ints
from npp_ros.experiment import (
    DEFAULT_CHECKPOINTS,
    DETUNED_CONTROL_WEIGHT,
    EXPERTS,
    LIPSCHITZ_SETTINGS,
    Arm,
    ExperimentSettings,
    ResultRow,
    RunRecord,
    default_arms,
    result_row,
    run_arm_seed,
    write_results,
)
from npp_ros.experiment.arms import HELD_OUT
from npp_ros.lqr import TASKS
from npp_ros.tasks import TASK_NAMES


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="npp-experiment", description=__doc__, formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    ap.add_argument(
        "--tasks", nargs="+", choices=TASK_NAMES, default=sorted(TASKS), help="tasks (default: the paper's lqr tasks)"
    )
    ap.add_argument(
        "--seeds", nargs="+", type=nonnegative_int, default=[0, 1, 2, 3], help="seeds (plant and s0 streams)"
    )
    ap.add_argument(
        "--lipschitz",
        nargs="+",
        default=list(LIPSCHITZ_SETTINGS),
        help="L settings side by side: 'paper' (50 / 200, not a bound here), 'analytic' (sup of the expert's "
        "value slope |Px|, a true bound) or a number",
    )
    ap.add_argument(
        "--experts",
        nargs="+",
        choices=EXPERTS,
        default=None,
        help="data source, where a task has it: the optimal LQR, a detuned LQR (Appendix B; run with the analytic "
        "L only), ilqr (the swing-up tasks' optimizer); default: every expert of each task",
    )
    ap.add_argument(
        "--max-episodes", type=positive_int, default=1000, help="episode budget per run (stops earlier if certified)"
    )
    ap.add_argument(
        "--evaluate", type=positive_int, default=100, metavar="N", help="rollouts from s0 ~ rho per checkpoint"
    )
    ap.add_argument(
        "--checkpoints",
        type=positive_ints,
        default=DEFAULT_CHECKPOINTS,
        help="episodes at which to evaluate (comma separated); the last episode is always evaluated",
    )
    ap.add_argument(
        "--certify",
        nargs="+",
        choices=("paper", *CERTIFY_MODES),
        default=None,
        help="what certifies, side by side: 'paper' (the surrogate gap V_ub - V_lb under the paper's one-shot "
        "rule, to reproduce it) or a mode under the sequentially valid rule: rollout (V_ub + tail - the "
        "policy's return), oracle (the expert's return - the policy's), surrogate; default: paper for the lqr "
        "tasks, the task's own sound mode (oracle) for tasks with a suboptimal optimizer expert",
    )
    ap.add_argument(
        "--epsilon",
        type=float,
        default=None,
        help="epsilon for every task (default: the paper's, 50 for lqr_2_1 and 300 for lqr_6_2)",
    )
    ap.add_argument("--horizon", type=positive_int, default=1000, help="episode length H")
    ap.add_argument("--p", type=float, default=0.9, help="condition (i): probability level p")
    ap.add_argument("--delta", type=float, default=0.1, help="condition (i): confidence delta")
    ap.add_argument(
        "--control-weight", type=float, default=DETUNED_CONTROL_WEIGHT, help="detuned expert: control cost x this"
    )
    ap.add_argument(
        "--time-budget", type=float, default=None, help="seconds per expert request (optimizer experts; default 5)"
    )
    ap.add_argument(
        "--held-out", type=positive_int, default=HELD_OUT, help="fresh s0 on which each certificate is checked"
    )
    ap.add_argument("--out", type=Path, default=Path("results/experiment"), help="output folder")
    ap.add_argument(
        "--jobs", type=positive_int, default=min(2, os.cpu_count() or 1), help="runs in parallel (processes)"
    )
    return ap


def _worker(arm: Arm, seed: int, settings: ExperimentSettings, out: Path, messages: Any) -> RunRecord:
    return run_arm_seed(arm, seed, settings, out, lambda text: messages.put(text))


class Status:
    """One live line on a terminal; a line every few seconds in a log."""

    def __init__(self, total: int) -> None:
        self.total = total
        self.done = 0
        self.latest: dict[str, str] = {}
        self.tty = sys.stderr.isatty()
        self._last = 0.0
        self.started = time.monotonic()

    def update(self, text: str) -> None:
        key = text.split(":", 1)[0]
        self.latest[key] = text
        self.show()

    def finished(self, key: str, line: str) -> None:
        self.done += 1
        self.latest.pop(key, None)
        self._write(f"[{self.done}/{self.total}] {line}", permanent=True)

    def show(self, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._last < (0.2 if self.tty else 10.0):
            return
        self._last = now
        running = " | ".join(self.latest.values()) or "starting"
        self._write(f"{self.done}/{self.total} runs done, {now - self.started:.0f} s | {running}", permanent=False)

    def _write(self, text: str, permanent: bool) -> None:
        if self.tty:
            width = os.get_terminal_size(sys.stderr.fileno()).columns - 1
            sys.stderr.write("\r" + text[:width].ljust(width) + ("\n" if permanent else ""))
        else:
            sys.stderr.write(text + "\n")
        sys.stderr.flush()


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    if not 0 < args.p < 1 or not 0 < args.delta < 1:
        print("npp-experiment: p and delta must lie in (0, 1)", file=sys.stderr)
        return 2
    settings = ExperimentSettings(
        max_episodes={task: args.max_episodes for task in args.tasks},
        evaluations=args.evaluate,
        checkpoints=args.checkpoints,
        horizon=args.horizon,
        p=args.p,
        delta=args.delta,
        control_weight=args.control_weight,
        epsilon={task: args.epsilon for task in args.tasks} if args.epsilon is not None else None,
        time_budget=args.time_budget,
        held_out=args.held_out,
    )
    try:
        for task in args.tasks:
            settings.epsilon_for(task)  # a task without the paper's epsilon needs --epsilon
        arms = default_arms(args.tasks, args.lipschitz, args.experts, args.certify)
    except ValueError as exc:
        print(f"npp-experiment: {exc}", file=sys.stderr)
        return 2
    jobs = [(arm, seed) for arm in arms for seed in args.seeds]
    args.out.mkdir(parents=True, exist_ok=True)
    print(
        f"npp-experiment: {len(arms)} arms x {len(args.seeds)} seeds = {len(jobs)} runs -> {args.out}", file=sys.stderr
    )

    started = time.perf_counter()
    status = Status(len(jobs))
    records: list[RunRecord] = []
    context = multiprocessing.get_context("spawn")
    with context.Manager() as manager, ProcessPoolExecutor(args.jobs, mp_context=context) as pool:
        messages = manager.Queue()
        futures: dict[Future[RunRecord], tuple[Arm, int]] = {
            pool.submit(_worker, arm, seed, settings, args.out, messages): (arm, seed) for arm, seed in jobs
        }
        pending = set(futures)
        failures = []
        while pending:
            try:
                status.update(messages.get(timeout=0.5))
            except queue.Empty:
                status.show()
            for future in [f for f in pending if f.done()]:
                pending.discard(future)
                arm, seed = futures[future]
                key = f"{arm.name} seed {seed}"
                try:
                    record = future.result()
                except Exception as exc:  # one run failing must not lose the others' results
                    failures.append(f"{key}: {type(exc).__name__}: {exc}")
                    status.finished(key, f"{key}: FAILED: {exc}")
                    continue
                records.append(record)
                cert = f"certified at {record.certified_episode}" if record.certified_episode else "not certified"
                status.finished(key, f"{key}: {cert}, {len(record.episodes)} episodes, {record.wall_time:.0f} s")
    wall = time.perf_counter() - started

    rows = report(records, settings, args.out)
    record_invocation(args.out / "experiment.json", argv, wall, len(jobs), failures)
    for row in rows:
        print(
            f"{row.task:8s} {row.expert:8s} L {row.lipschitz_setting:8s} seed {row.seed}: "
            f"certified at {row.certified_episode}, {row.fraction_within_epsilon:.0%} within eps, "
            f"{row.lower_bound_violations}/{row.rollouts} below V_lb -> {row.verdict}"
        )
    print(f"npp-experiment: wrote {args.out}/results.md, figures in {args.out}; {wall:.0f} s")
    for failure in failures:
        print(f"npp-experiment: run failed: {failure}", file=sys.stderr)
    return 1 if failures else 0


def record_invocation(path: Path, argv: list[str] | None, wall: float, runs: int, failures: list[str]) -> None:
    """Appends this command to the folder's history: a resumed run keeps the first one's wall time."""
    history = json.loads(path.read_text()).get("invocations", []) if path.exists() else []
    history.append(
        {
            "command": " ".join(["npp-experiment", *(argv if argv is not None else sys.argv[1:])]),
            "finished": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "wall_time_s": round(wall, 1),
            "runs": runs,
            "failed": failures,
        }
    )
    machine = {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()}
    path.write_text(json.dumps({"machine": machine, "invocations": history}, indent=2) + "\n")


def report(records: list[RunRecord], settings: ExperimentSettings, out: Path) -> list[ResultRow]:
    """Figures per arm, then the table; the table's order is the arms' then the seeds'."""
    from npp_ros.plots import gap_distributions, training_curves  # matplotlib: the parent only, not each worker

    by_arm: dict[Arm, list[RunRecord]] = defaultdict(list)
    for record in sorted(records, key=lambda r: (r.arm.task, r.arm.expert, r.arm.lipschitz, r.seed)):
        by_arm[record.arm].append(record)
    rows: list[ResultRow] = []
    for arm, group in by_arm.items():
        if any(r.evaluations for r in group):
            training_curves(group, out / f"fig4-{arm.name}.png")
            gap_distributions(group, out / f"fig5-{arm.name}.png")
        rows.extend(result_row(record, settings.p, settings.delta) for record in group)
    write_results(rows, out)
    return rows


if __name__ == "__main__":
    sys.exit(main())
