"""npp-experiment: the paper's lqr experiments (Section 5, Figures 4-5) and Appendix B, in process.

Runs Algorithm 1 with the same core loop as the supervisor node for every arm (task x expert x
L setting) and seed, evaluates the policy at checkpoints with N rollouts from s0 ~ rho against
the expert from the same s0, and writes Figure-4 and Figure-5 style PNGs and a results table
(results.md, results.csv, results.json). Runs are stored under OUT/runs/ and resume: a repeated
command recomputes nothing and gives the same numbers.

The runs go to a Dask cluster: by default a local one with --jobs single-threaded worker processes,
or an existing one given by its scheduler's address. Each worker returns its run's record and this
process writes the tables and figures from them.

An option not given takes each task's own value: the paper's, or for a task file its keys horizon,
epsilon, lipschitz, certify and [expert] time_budget, stop, values and max_iterations.

Every (arm, seed) is made and checked as its npp-learn run would be before any worker starts: a value or a
combination a task refuses is one line and exit code 2, and nothing is written.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import queue
import sys
import time
import uuid
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from distributed import Client, Future, LocalCluster, get_worker

import npp_ros
from npp_ros.certificate.certifier import CERTIFY_MODES, CONDITIONS
from npp_ros.cli.args import help_of, nonnegative_int, positive_int, positive_ints, task_name
from npp_ros.experiment import (
    DEFAULT_CHECKPOINTS,
    DETUNED_CONTROL_WEIGHT,
    EXPERTS,
    Arm,
    ExperimentSettings,
    ResultRow,
    RunRecord,
    default_arms,
    result_row,
    run_arm_seed,
    write_results,
)
from npp_ros.experiment.arms import HELD_OUT, arm_request
from npp_ros.policy.feedback import DEFAULT_POLICY, POLICY_KINDS
from npp_ros.run.nominal_plan import DEFAULT_EXPERT_MODEL, EXPERT_MODELS
from npp_ros.run.policy_lipschitz import POLICY_LIPSCHITZ_MODES
from npp_ros.run.request import RunRequest, resolve_run
from npp_ros.run.setup import build_loop
from npp_ros.tasks.builtin.lqr import TASKS
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.sources import short_name
from npp_ros.trajopt.expert import STOP_MODES, VALUE_MODES


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="npp-experiment", description=__doc__, formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    ap.add_argument(
        "--tasks", nargs="+", type=task_name, default=sorted(TASKS), help="tasks (default: the paper's lqr tasks)"
    )
    ap.add_argument(
        "--seeds", nargs="+", type=nonnegative_int, default=[0, 1, 2, 3], help="seeds (plant and s0 streams)"
    )
    ap.add_argument(
        "--lipschitz",
        nargs="+",
        default=None,
        help="L settings side by side, each one of: " + help_of("lipschitz"),
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
        "--max-episodes",
        type=positive_int,
        default=1000,
        help=help_of("max_episodes") + " (per run)",
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
        help="what certifies, side by side: 'paper' (the surrogate gap V_ub - V_lb under the paper's one-shot rule, to "
        "reproduce it) or a mode under a sequentially valid rule (--rules); default: paper for the lqr tasks, else "
        "the task's own. A mode: " + help_of("certify"),
    )
    ap.add_argument(
        "--policies",
        nargs="+",
        choices=POLICY_KINDS,
        default=[DEFAULT_POLICY],
        help="how the policy acts, side by side as arms of one run (same seeds, same s0 streams): " + help_of("policy"),
    )
    ap.add_argument(
        "--explore", nargs="+", type=float, default=[0.0], metavar="RADIUS",
        help="exploration radii, side by side as arms: " + help_of("explore"),
    )  # fmt: skip
    ap.add_argument(
        "--policy-lipschitz", nargs="+", choices=POLICY_LIPSCHITZ_MODES, default=["claim"],
        help="the policy's L, side by side as arms: " + help_of("policy_lipschitz"),
    )  # fmt: skip
    ap.add_argument(
        "--uncertainty", nargs="+", type=float, default=[0.0], metavar="FACTOR",
        help="sets of robots, side by side as arms: " + help_of("uncertainty"),
    )  # fmt: skip
    ap.add_argument(
        "--expert-models", nargs="+", choices=EXPERT_MODELS, default=[DEFAULT_EXPERT_MODEL],
        help="what the expert plans on, side by side as arms of the runs on a set of robots (the exact model runs "
        "with the default only): " + help_of("expert_model"),
    )  # fmt: skip
    ap.add_argument(
        "--rules",
        nargs="+",
        choices=("sequential", "mixture"),
        default=None,
        help="the stopping rules the sound modes run under, side by side (sequential, mixture); default: each mode's "
        "own. " + help_of("rule"),
    )
    ap.add_argument(
        "--epsilon",
        type=float,
        default=None,
        help="for every task: " + help_of("epsilon"),
    )
    ap.add_argument(
        "--horizon", type=positive_int, default=None,
        help="for every task: " + help_of("horizon") + "; the tasks' own must then agree",
    )  # fmt: skip
    ap.add_argument(
        "--condition", choices=CONDITIONS, default="i",
        help=help_of("condition") + "; npp-experiment checks condition (i)'s claim only",
    )  # fmt: skip
    ap.add_argument("--p", type=float, default=0.9, help=help_of("p"))
    ap.add_argument("--delta", type=float, default=0.1, help=help_of("delta"))
    ap.add_argument(
        "--gamma", type=float, default=1.0,
        help=help_of("gamma") + "; npp-experiment measures undiscounted H-step returns, so it takes 1 only",
    )  # fmt: skip
    ap.add_argument(
        "--control-weight", type=float, default=DETUNED_CONTROL_WEIGHT, help="detuned expert: control cost x this"
    )
    ap.add_argument("--time-budget", type=float, default=None, help=help_of("time_budget"))
    ap.add_argument("--expert-stop", choices=STOP_MODES, default=None, help=help_of("expert_stop"))
    ap.add_argument("--values", choices=VALUE_MODES, default=None, help=help_of("values"))
    ap.add_argument("--max-iterations", type=positive_int, default=None, help=help_of("max_iterations"))
    ap.add_argument(
        "--held-out", type=positive_int, default=HELD_OUT, help="fresh s0 on which each certificate is checked"
    )
    ap.add_argument("--out", type=Path, default=Path("results/experiment"), help="output folder")
    ap.add_argument(
        "--jobs",
        type=positive_int,
        default=min(2, os.cpu_count() or 1),
        help="runs in parallel: worker processes of the local cluster (--scheduler local only)",
    )
    ap.add_argument(
        "--scheduler",
        default="local",
        metavar="local|ADDRESS",
        help="where the runs go: 'local' (a Dask cluster on this machine, --jobs single-threaded workers) or "
        "an existing Dask scheduler's address, e.g. tcp://host:8786",
    )
    ap.add_argument(
        "--connect-timeout",
        type=float,
        default=10.0,
        metavar="SECONDS",
        help="give up on a scheduler address that does not answer within this time",
    )
    return ap


PROGRESS_TOPIC = "npp-experiment"  # one scheduler event topic; each command filters on its own token


def _run_on_worker(arm: Arm, seed: int, settings: ExperimentSettings, out: Path, token: str) -> tuple[str, RunRecord]:
    """One run on a Dask worker; progress lines go to the client as scheduler events."""
    worker = get_worker()
    name = f"worker {worker.name}"  # its address unless started with --name
    key = f"{arm.name} seed {seed}"

    def report(text: str) -> None:
        worker.log_event(PROGRESS_TOPIC, {"token": token, "run": key, "text": f"[{name}] {text}"})

    report(f"{key}: started")
    return name, run_arm_seed(arm, seed, settings, out, report)


class SchedulerUnreachable(RuntimeError):
    """The scheduler address did not answer: a one-line reason for the terminal."""


@contextmanager
def dask_client(scheduler: str, jobs: int, connect_timeout: float) -> Iterator[Client]:
    """A client of a local cluster (single-threaded worker processes on loopback) or of a running one."""
    if scheduler == "local":
        # no memory limit: like a plain process, a run's growing data set must not get its worker paused or killed;
        # the scheduler's web server on a free loopback port: commands side by side never collide on 8787
        with LocalCluster(
            n_workers=jobs, threads_per_worker=1, processes=True, host="127.0.0.1", memory_limit=0,
            dashboard_address="127.0.0.1:0",
        ) as cluster, Client(cluster) as client:  # fmt: skip
            yield client
        return
    try:
        client = Client(scheduler, timeout=connect_timeout)
    except (OSError, ValueError, TypeError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise SchedulerUnreachable(f"cannot reach the Dask scheduler at {scheduler}: {reason}") from None
    with client:
        refuse_other_versions(client)
        yield client


class OtherVersion(RuntimeError):
    """Workers that run another npp_ros than this command: their numbers would not be this code's."""


def code_fingerprint() -> str:
    """This npp_ros's source, as a digest: two processes with the same one compute the same numbers."""
    root = Path(npp_ros.__file__).parent
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()[:16]


def refuse_other_versions(client: Client) -> None:
    """Every worker of a running cluster must run this npp_ros (the same source): refuse by name those that do not."""
    mine = code_fingerprint()
    answers = client.run(code_fingerprint, on_error="return")
    others = {worker: ("cannot run npp_ros's check" if isinstance(found, BaseException) else f"npp_ros {found}")
              for worker, found in answers.items() if found != mine}  # fmt: skip
    if others:
        workers = client.scheduler_info()["workers"]
        names = {address: info.get("name", address) for address, info in workers.items()}
        named = ", ".join(
            f"{names.get(worker, worker)} at {worker} ({what})" for worker, what in sorted(others.items())
        )
        raise OtherVersion(f"{len(others)} of {len(answers)} Dask workers run another npp_ros than this one "
                           f"(npp_ros {mine}): {named}; start them from this checkout")  # fmt: skip


class Status:
    """One live line on a terminal; a line every few seconds in a log."""

    def __init__(self, total: int) -> None:
        self.total = total
        self.done = 0
        self.latest: dict[str, str] = {}
        self._finished: set[str] = set()  # a worker's last line may arrive after its result
        self.tty = sys.stderr.isatty()
        self._last = 0.0
        self.started = time.monotonic()

    def update(self, key: str, text: str) -> None:
        if key not in self._finished:
            self.latest[key] = text
        self.show()

    def finished(self, key: str, line: str) -> None:
        self.done += 1
        self._finished.add(key)
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


def common_horizon(tasks: list[str]) -> int:
    """The tasks' own episode length, when they agree; else a ValueError naming them and the flag."""
    own = {short_name(task): get_task(task).default_horizon for task in tasks}
    if len(set(own.values())) > 1:
        named = ", ".join(f"{name} {horizon}" for name, horizon in own.items())
        raise ValueError(f"the tasks' own horizons differ ({named}): pass --horizon")
    return next(iter(own.values()))


def plan(args: argparse.Namespace) -> tuple[ExperimentSettings, list[Arm]]:
    """The settings and arms a command line asks for; ValueError names what is wrong.

    Each (arm, seed) is then checked as npp-learn checks its run before it starts
    (:func:`check_runs`), so that what a task refuses is said here, before any worker starts and any file is made.
    """
    if not 0 < args.p < 1 or not 0 < args.delta < 1:
        raise ValueError("p and delta must lie in (0, 1)")
    if args.condition != "i":
        raise ValueError(
            f"condition ({args.condition}) claims a mean gap, and npp-experiment's evaluations and held-out checks "
            "test condition (i)'s P(gap <= eps) >= p: run it with npp-learn"
        )
    if args.gamma != 1.0:
        RunRequest(gamma=args.gamma)  # a gamma no run takes is refused as the request refuses it
        raise ValueError(
            f"gamma {args.gamma:g}: npp-experiment's evaluations and held-out checks measure undiscounted H-step "
            "returns, which a discounted claim is not about: run it with npp-learn"
        )
    settings = ExperimentSettings(
        max_episodes={task: args.max_episodes for task in args.tasks},
        evaluations=args.evaluate,
        checkpoints=args.checkpoints,
        horizon=args.horizon or common_horizon(args.tasks),
        p=args.p,
        delta=args.delta,
        control_weight=args.control_weight,
        epsilon={task: args.epsilon for task in args.tasks} if args.epsilon is not None else None,
        time_budget=args.time_budget,
        stop=args.expert_stop,
        held_out=args.held_out,
        condition=args.condition,
        gamma=args.gamma,
        values=args.values,
        max_iterations=args.max_iterations,
    )
    arms = default_arms(
        args.tasks,
        args.lipschitz,
        args.experts,
        args.certify,
        args.rules,
        args.policies,
        args.explore,
        args.policy_lipschitz,
        args.uncertainty,
        args.expert_models,
    )
    for task in dict.fromkeys(arm.task for arm in arms if arm.certify != "success"):
        settings.epsilon_for(task)  # a gap claim on a task without the paper's epsilon needs --epsilon
    check_runs(arms, args.seeds, settings)
    return settings, arms


def check_runs(arms: list[Arm], seeds: list[int], settings: ExperimentSettings) -> None:
    """Every (arm, seed)'s run request made, resolved and its loop built, as npp-learn does before its run starts:
    a value the request refuses, a combination its task refuses (an epsilon it lacks, a set of robots it cannot
    draw, a checked quantity it cannot measure) is a ValueError here, not a worker's traceback.

    An L measured from the data ('data') is measured by the expert's first answers (seconds each for an optimizer):
    it is checked as a number here, and measured on the worker."""
    for arm in arms:
        for seed in seeds:
            request = arm_request(arm, seed, settings)
            if arm.lipschitz == "data":
                request = RunRequest.of(request, lipschitz="1")
            try:
                run = resolve_run(request, kind=arm.expert, control_weight=settings.control_weight)
                build_loop(run.config, run.expert)
            except ValueError as exc:
                raise ValueError(f"{arm.name} seed {seed}: {exc}") from None


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        settings, arms = plan(args)
    except ValueError as exc:
        print(f"npp-experiment: {exc}", file=sys.stderr)
        return 2
    jobs = [(arm, seed) for arm in arms for seed in args.seeds]
    args.out.mkdir(parents=True, exist_ok=True)
    print(
        f"npp-experiment: {len(arms)} arms x {len(args.seeds)} seeds = {len(jobs)} runs -> {args.out}", file=sys.stderr
    )

    started = time.perf_counter()
    try:
        records, failures = run_on_cluster(jobs, settings, args)
    except (SchedulerUnreachable, OtherVersion) as exc:
        print(f"npp-experiment: {exc}", file=sys.stderr)
        return 1
    wall = time.perf_counter() - started

    rows = report(records, settings, args.out)
    record_invocation(args.out / "experiment.json", argv, wall, len(jobs), failures)
    for row in rows:
        print(
            f"{row.task:8s} {row.expert:8s} L {row.lipschitz_setting:8s} {row.certify} ({row.rule}){row.acts} "
            f"seed {row.seed}: "
            f"certified at {row.certified_episode}, "
            + ("" if row.certify == "success" else f"{row.fraction_within_epsilon:.0%} within eps, ")  # no gap bounded
            + f"{row.lower_bound_violations}/{row.rollouts} below V_lb -> {row.verdict}"
        )
    print(f"npp-experiment: wrote {args.out}/results.md, figures in {args.out}; {wall:.0f} s")
    for failure in failures:
        print(f"npp-experiment: run failed: {failure}", file=sys.stderr)
    return 1 if failures else 0


def run_on_cluster(
    jobs: list[tuple[Arm, int]], settings: ExperimentSettings, args: argparse.Namespace
) -> tuple[list[RunRecord], list[str]]:
    """Every (arm, seed) as one Dask task; the workers write OUT/runs/ at OUT's absolute path and return records."""
    out = args.out.resolve()
    token = uuid.uuid4().hex
    status = Status(len(jobs))
    messages: queue.Queue[tuple[str, str]] = queue.Queue()
    records: list[RunRecord] = []
    failures: list[str] = []

    def on_event(event: tuple[float, dict[str, str]]) -> None:  # on the client's event loop thread
        msg = event[1]
        if isinstance(msg, dict) and msg.get("token") == token:
            messages.put((msg["run"], msg["text"]))

    with dask_client(args.scheduler, args.jobs, args.connect_timeout) as client:
        if not client.scheduler_info().get("workers"):
            print(f"npp-experiment: {args.scheduler} has no workers yet; runs start when one joins", file=sys.stderr)
        client.subscribe_topic(PROGRESS_TOPIC, on_event)
        futures: dict[Future, tuple[Arm, int]] = {
            client.submit(
                _run_on_worker, arm, seed, settings, out, token, key=f"npp-{arm.name}-seed{seed}-{token[:8]}"
            ): (arm, seed)
            for arm, seed in jobs
        }
        pending = set(futures)
        while pending:
            try:
                status.update(*messages.get(timeout=0.5))
            except queue.Empty:
                status.show()
            for future in [f for f in pending if f.done()]:
                pending.discard(future)
                arm, seed = futures[future]
                key = f"{arm.name} seed {seed}"
                try:
                    worker, record = future.result()
                except Exception as exc:  # one run failing must not lose the others' results
                    failures.append(f"{key}: {type(exc).__name__}: {exc}")
                    status.finished(key, f"{key}: FAILED: {exc}")
                    continue
                records.append(record)
                cert = f"certified at {record.certified_episode}" if record.certified_episode else "not certified"
                status.finished(
                    key, f"{key} on {worker}: {cert}, {len(record.episodes)} episodes, {record.wall_time:.0f} s"
                )
    return records, failures


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
    from npp_ros.experiment.plots import (  # matplotlib: the parent only, not each worker
        gap_distributions,
        training_curves,
    )

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
