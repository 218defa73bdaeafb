"""npp-bench: the exact bound index against plain 1-NN trees and brute force, in one run.

Measures side by side, on real LQR expert trajectories (``LQRExpert.trajectory`` from
``sample_initial_state``) and queries near fresh expert trajectories:

* 12-D lqr_6_2-like data and 4-D lqr_2_1-like data: V_lb (the policy query), V_ub and both,
  against pykdtree and scipy's cKDTree 1-NN on the same points, batched and single;
* brute-force numpy (the reference implementation) against the index at 10^4, 10^5, 10^6 points;
* exactness against the brute force on every run: same values and same indices, ties included
  (a tie-heavy grid case runs every time);
* the first-call cost of the compiled kernels with a cold and a warm numba cache;
* optionally the compression of stored runs (``--runs``) and the ROS loop rate (``--ros``);
* optionally any task's expert (``--experts``; ``--only experts`` runs that part alone; the swing-ups by
  default, any task with ``--expert-tasks``, task files included): seconds per H-step trajectory from
  s0 ~ rho with each task's default expert options and time budget, where the time goes, and the share
  of answers that met the task's success criterion, so that a user checks an expert before a long run;
* optionally the query cost at a 7-joint arm's scale (``--only queries``): V_lb, V_ub and both over 10^4 .. 10^6
  points of a task file's state (the Panda reaching task's 20 entries; a run's expert data first, then rollouts
  on the task's plant), one query per call as percentiles (p50 .. max) and in batches, beside pykdtree and
  cKDTree 1-NN, build times, and exactness against brute force at every size;
* optionally the experts' throughput (``--throughput``; ``--only throughput`` runs that part alone):
  requests per second through the expert pool at 1, 2 and m workers on the same s0, the speed-ups,
  the optimizer's stop reasons (answers the time budget cut named), and whether every worker count
  gave the same answers.

Everything is single-threaded (OMP_NUM_THREADS=1 for pykdtree), so the ratios compare
algorithms, not core counts. Writes ``bench.md`` and ``bench.json`` into the output folder.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before pykdtree loads its OpenMP runtime

from npp_ros.bench.measure import (
    DEFAULT_OUT,
    EXPERT_PATHS,
    EXPERT_TASKS,
    TARGETS,
    TIMEABLE_EXPERT_TASKS,
    Progress,
    compile_cost,
    compression_of_runs,
    expert_data,
    expert_section,
    machine_info,
    near_trajectory_queries,
    run_case,
    run_scaling,
    targets,
    tie_case,
)
from npp_ros.bench.queries import (
    DEFAULT_QUERY_SIZES,
    DEFAULT_QUERY_TASK,
    LARGE_LIPSCHITZ,
    QUICK_QUERY_POINTS,
    ROLLOUT_NOISE,
    query_section,
    query_steps,
)
from npp_ros.bench.report import (
    expert_markdown,
    markdown,
    query_markdown,
    throughput_markdown,
    with_experts,
    with_queries,
    with_ros,
    write_report,
)
from npp_ros.bench.throughput import throughput_section, worker_counts
from npp_ros.cli.args import TASK_HELP, positive_int, task_name
from npp_ros.tasks.builtin.lqr import PAPER_LIPSCHITZ
from npp_ros.tasks.expert_pool import default_workers


# ----------------------------------------------------------------------------- main
def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="npp-bench",
        description=(
            "npp-bench: the exact V_lb/V_ub index against pykdtree and cKDTree 1-NN and against brute force, "
            "on real LQR expert trajectories; exactness is checked on every run. With --experts, also the experts "
            "of pendulum_swingup and cartpole_swingup, or of any task (--expert-tasks, task files too): seconds per "
            "H-step trajectory (median, quartiles, range) from s0 ~ rho with each task's default options and time "
            "budget (a task file's [expert] keys), where the time goes, and how many answers met the task's success "
            "criterion (check an expert before a long run: a certificate is relative to it); --only experts "
            "measures just that (minutes), keeping the rest of OUT's bench.json and bench.md. --only queries: the "
            "query cost at a 7-joint arm's scale (--query-task, --query-sizes, --query-run), one query per call as "
            "p50/p90/p99/max and batched (--single, --queries, --check, --repeats as for the LQR cases), beside "
            "pykdtree and cKDTree, exactness checked at every size, also keeping the rest of OUT's files. Writes "
            "bench.md and bench.json."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output folder")
    parser.add_argument("--quick", action="store_true", help="a short smoke run on small data (seconds, not minutes)")
    parser.add_argument("--trajectories", type=int, default=1000, help="expert trajectories per task (H = 1000 each)")
    parser.add_argument("--queries", type=int, default=1000, help="batched queries near fresh trajectories")
    parser.add_argument("--single", type=int, default=300, help="queries timed one at a time")
    parser.add_argument("--check", type=int, default=100, help="queries checked against brute force per case")
    parser.add_argument("--repeats", type=int, default=7, help="timing repeats (medians and spreads over these)")
    parser.add_argument("--brute-budget", type=float, default=2e6, help="points x queries per brute-force timing")
    parser.add_argument("--seed", type=int, default=0, help="seed of the initial states")
    parser.add_argument("--runs", type=Path, nargs="*", default=[], help="run folders whose compression to report")
    parser.add_argument("--ros", action="store_true", help="also measure the ROS loop rate (npp-bench-ros)")
    parser.add_argument("--no-compile", action="store_true", help="skip the cold-cache compile measurement")
    parser.add_argument("--experts", action="store_true", help="also time the iLQR experts (see --expert-requests)")
    parser.add_argument(
        "--throughput", action="store_true", help="also measure expert requests per second at 1, 2 and m workers"
    )
    parser.add_argument(
        "--only",
        choices=["experts", "throughput", "queries"],
        default=None,
        help="run only this part; its section and target rows go into OUT/bench.json and bench.md, replacing an "
        "earlier run's, and the rest of those files is kept",
    )
    parser.add_argument(
        "--expert-requests", type=int, default=10, help="expert requests per task, from the s0 of episodes 0 .. N-1"
    )
    parser.add_argument(
        "--expert-horizon",
        type=int,
        default=None,
        help="steps per expert trajectory (H) for every task; default: each task's own (1000 for the built-in "
        "tasks, a task file's key horizon)",
    )
    parser.add_argument(
        "--expert-tasks",
        nargs="+",
        type=task_name,
        default=list(EXPERT_TASKS),
        metavar="TASK",
        help=f"tasks whose expert to time and score on its success criterion: {TASK_HELP}",
    )
    parser.add_argument(
        "--expert-paths",
        nargs="+",
        choices=EXPERT_PATHS,
        default=["batch"],
        help="iLQR code paths to time, each s0 asked of one path after the other: batch (derivatives and line "
        "search on mujoco.batch, every core) or reference (the one-at-a-time code); the answers are the same",
    )
    parser.add_argument(
        "--throughput-tasks",
        nargs="+",
        choices=TIMEABLE_EXPERT_TASKS,
        default=list(EXPERT_TASKS),
        help="tasks whose expert throughput to measure (H = --expert-horizon)",
    )
    parser.add_argument(
        "--throughput-requests",
        type=positive_int,
        default=12,
        help="requests per task and worker count, from the s0 of episodes 0 .. N-1, all asked at once",
    )
    parser.add_argument(
        "--throughput-workers",
        type=positive_int,
        default=None,
        metavar="M",
        help="the largest pool measured, beside 1 and 2 workers (default: one per usable core)",
    )
    parser.add_argument(
        "--query-task",
        default=DEFAULT_QUERY_TASK,
        metavar="TASK",
        help="--only queries: the task whose state the points and queries are, its rollouts driven by the torques "
        f"that hold a MuJoCo plant against gravity plus noise: {TASK_HELP}",
    )
    parser.add_argument(
        "--query-sizes",
        nargs="+",
        type=positive_int,
        default=list(DEFAULT_QUERY_SIZES),
        metavar="N",
        help="--only queries: stored points at which to measure (each the first N points of the largest set)",
    )
    parser.add_argument(
        "--query-run",
        type=Path,
        default=None,
        metavar="RUN_DIR",
        help="--only queries: a run folder (run.sqlite) of --query-task whose stored expert data come first, whose "
        "L is measured and whose horizon the rollouts have; without, every point is a rollout's, of the task's "
        "own horizon",
    )
    parser.add_argument(
        "--query-lipschitz",
        type=float,
        default=None,
        metavar="L",
        help="--only queries: the policy's L (besides L = "
        f"{LARGE_LIPSCHITZ:g}, where V_lb is close to 1-NN); default: the run's, else 2 x the steepest slope of "
        "the first 3 rollouts' return-to-go (the 'data' rule on them)",
    )
    args = parser.parse_args(argv)
    if args.only == "queries":
        try:
            task_name(args.query_task)  # refused here with its one-line reason; the name as given is recorded
        except argparse.ArgumentTypeError as exc:
            parser.error(f"--query-task: {exc}")
        if args.query_lipschitz is not None and not args.query_lipschitz > 0:
            parser.error("--query-lipschitz must be > 0")
    if args.expert_requests < 1 or (args.expert_horizon is not None and args.expert_horizon < 2):
        parser.error("--expert-requests must be >= 1 and --expert-horizon >= 2")
    if args.quick:
        args.trajectories = min(args.trajectories, 12)
        args.queries, args.single, args.check, args.repeats = 200, 50, 50, 2
        args.brute_budget = 2e5
        args.expert_requests, args.expert_horizon = min(args.expert_requests, 2), min(args.expert_horizon or 200, 200)
        args.throughput_requests = min(args.throughput_requests, 4)
        args.query_sizes = sorted({min(n, QUICK_QUERY_POINTS) for n in args.query_sizes})
    return args


def header(args: argparse.Namespace, command: str) -> dict[str, Any]:
    return {
        "command": command,
        "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
        "machine": machine_info(),
        "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items() if k != "runs"},
        "targets_spec": TARGETS,
    }


def write(result: dict[str, Any], out: Path) -> None:
    write_report(out, "bench", result, markdown(result))


def experts_only(args: argparse.Namespace, command: str) -> int:
    """``--only experts``: the expert section into OUT's bench files, the index (and ROS) figures kept."""
    progress = Progress(len(args.expert_tasks) * len(args.expert_paths) * args.expert_requests + 1)
    path = args.out / "bench.json"
    result = json.loads(path.read_text()) if path.exists() else header(args, command)
    with_experts(result, expert_section(args, progress, command))
    result.setdefault("load_average_end", result["experts"]["load_average_end"])
    write(result, args.out)
    progress.step(f"wrote the experts into {path} and {args.out / 'bench.md'}")
    sys.stdout.write("\n".join(expert_markdown(result["experts"])))
    return 0


def throughput(args: argparse.Namespace, progress: Progress, command: str) -> dict[str, Any]:
    return throughput_section(args.throughput_tasks, args.throughput_requests, args.expert_horizon, args.seed,
                              args.throughput_workers, progress, command)  # fmt: skip


def throughput_steps(args: argparse.Namespace) -> int:
    """Progress steps of the throughput part: one per task and worker count (1, 2, m: at most three)."""
    most = args.throughput_workers or default_workers()
    return len(args.throughput_tasks) * len(worker_counts(most))


def throughput_only(args: argparse.Namespace, command: str) -> int:
    """``--only throughput``: the throughput section into OUT's bench files, the rest of them kept."""
    progress = Progress(throughput_steps(args) + 1)
    path = args.out / "bench.json"
    result = json.loads(path.read_text()) if path.exists() else header(args, command)
    result["expert_throughput"] = throughput(args, progress, command)
    result.setdefault("targets", [])
    result.setdefault("load_average_end", result["expert_throughput"]["load_average_end"])
    write(result, args.out)
    progress.step(f"wrote the expert throughput into {path} and {args.out / 'bench.md'}")
    sys.stdout.write("\n".join(throughput_markdown(result["expert_throughput"])))
    return 0


def queries_only(args: argparse.Namespace, command: str) -> int:
    """``--only queries``: the query-cost section into OUT's bench files, the rest of them kept."""
    run = None
    if args.query_run is not None:
        from npp_ros.run.read import read_run
        from npp_ros.run.records import RunFileError
        from npp_ros.tasks.registry import get_task

        try:
            run = read_run(args.query_run)
        except RunFileError as exc:
            sys.stderr.write(f"npp-bench: --query-run: {exc}\n")
            return 2
        if run.task.name != get_task(args.query_task).name:
            sys.stderr.write(f"npp-bench: --query-run {args.query_run} is a run of {run.task.name}, not of "
                             f"--query-task {args.query_task}\n")  # fmt: skip
            return 2
    progress = Progress(query_steps(args) + 1)
    progress.note(f"rollouts under gravity-holding torques + {ROLLOUT_NOISE:g} x half-range noise")
    path = args.out / "bench.json"
    result = json.loads(path.read_text()) if path.exists() else header(args, command)
    with_queries(result, query_section(args, run, progress, command))
    result.setdefault("load_average_end", result["queries"]["load_average_end"])
    write(result, args.out)
    progress.step(f"wrote the query cost into {path} and {args.out / 'bench.md'}; exact: {result['queries']['exact']}")
    sys.stdout.write("\n".join(query_markdown(result["queries"])))
    return 0 if result["queries"]["exact"] else 1


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    command = "npp-bench " + " ".join(sys.argv[1:] if argv is None else argv)
    if args.only == "experts":
        return experts_only(args, command)
    if args.only == "throughput":
        return throughput_only(args, command)
    if args.only == "queries":
        return queries_only(args, command)
    n = args.trajectories * 1000
    sizes = [s for s in (10_000, 100_000, 1_000_000) if s <= n] or [n]
    tasks = [("lqr_6_2", "analytic"), ("lqr_2_1", "analytic"), ("lqr_2_1", "paper")]
    experts = len(args.expert_tasks) * len(args.expert_paths) * args.expert_requests if args.experts else 0
    total = 2 + 3 * len(tasks) + 2 * len(sizes) + 1 + (not args.no_compile) + len(args.runs) + args.ros + experts + 1
    total += throughput_steps(args) if args.throughput else 0
    progress = Progress(total)
    result = header(args, command)
    datasets = {}
    for task in ("lqr_6_2", "lqr_2_1"):
        t = time.perf_counter()
        data, expert = expert_data(task, args.trajectories, args.seed)
        queries = near_trajectory_queries(expert, task, args.queries, args.seed)
        datasets[task] = (data, expert, queries)
        progress.step(f"{task}: {len(data):,d} expert points, {len(queries)} queries ({time.perf_counter() - t:.1f}s)")
    cases = []
    for task, choice in tasks:
        data, expert, queries = datasets[task]
        if choice == "analytic":
            lip = expert.analytic_lipschitz()
            L, source = lip.value, "analytic"
        else:
            L, source = PAPER_LIPSCHITZ[task], "paper"
        name = f"{data.state_dim}-D {task}"
        cases.append(run_case(f"{name}, L {source}", task, data, L, source, queries, args, progress))
    scaling = []
    for task in ("lqr_6_2", "lqr_2_1"):
        data, expert, queries = datasets[task]
        L = expert.analytic_lipschitz().value
        scaling += run_scaling(f"{data.state_dim}-D {task}", data, L, queries, sizes, args, progress)
    ties = tie_case(args.seed, 2000 if args.quick else 20_000, 300)
    progress.step(f"tie case: {ties['tied_queries_lower']} tied queries, exact {ties['exact']}")
    result["cases"] = [vars(c) for c in cases]
    result["scaling"] = scaling
    result["ties"] = ties
    if not args.no_compile:
        result["compile"] = compile_cost()
        progress.step(f"compile: cold {result['compile']['cold_first_query_s']:.2f}s, "
                      f"warm {result['compile']['warm_first_query_s']:.2f}s")  # fmt: skip
    result["compression_runs"] = compression_of_runs(args.runs, progress)
    result["targets"] = targets(cases, scaling)
    if args.ros:
        with_ros(result, ros_loop(args, progress))
    if args.experts:
        with_experts(result, expert_section(args, progress, command))
    if args.throughput:
        result["expert_throughput"] = throughput(args, progress, command)
    checks = [c.exact["exact"] for c in cases] + [r["exact"]["exact"] for r in scaling] + [ties["exact"]]
    result["all_exact"] = bool(all(checks))
    result["load_average_end"] = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    write(result, args.out)
    progress.step(f"wrote {args.out / 'bench.md'} and {args.out / 'bench.json'}; all exact: {result['all_exact']}")
    sys.stdout.write(markdown(result))
    return 0 if result["all_exact"] else 1


ROS_BENCH = "npp-bench-ros"  # the ROS side's own command; the core starts it, never imports it


def ros_bench_command() -> str | None:
    """npp-bench-ros beside this interpreter (the same environment), else on PATH; None where it is absent."""
    beside = Path(sys.executable).parent / ROS_BENCH
    return str(beside) if beside.exists() else shutil.which(ROS_BENCH)


def ros_loop(args: argparse.Namespace, progress: Progress) -> dict[str, Any]:
    """The ROS loop rate, measured by npp-bench-ros in a process of its own (its JSON read back).

    The core never imports the ROS package: the measurement is another command's, reached by name.
    """
    command = ros_bench_command()
    if command is None:
        out: dict[str, Any] = {"error": f"--ros needs {ROS_BENCH} (the ROS package and ROS 2), not installed here",
                               "cases": []}  # fmt: skip
    else:
        with tempfile.TemporaryDirectory(prefix="npp-bench-ros-") as folder:
            answer = Path(folder) / "ros.json"
            argv = [command, "--json", str(answer), *(["--quick"] if args.quick else [])]
            done = subprocess.run(argv, capture_output=True, text=True, check=False)
            if done.returncode == 0 and answer.exists():
                out = json.loads(answer.read_text())
            else:  # the index figures above still get written
                last = (done.stderr.strip().splitlines() or [f"exit code {done.returncode}"])[-1]
                out = {"error": f"{ROS_BENCH} failed: {last}", "cases": []}
    done_text = ", ".join(f"{c['task']} {c['ratio']:.2f}" for c in out.get("cases", []))
    progress.step(f"ROS loop: graph / ping-pong {done_text or out.get('error')}")
    return out


if __name__ == "__main__":
    sys.exit(main())
