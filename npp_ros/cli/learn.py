"""npp-learn: run Algorithm 1 in one process on a registered task, to a certificate.

No ROS involved: the plant, the task's expert and the loop run here. The run is stored as it
grows in RUN_DIR/run.sqlite and resumes from there when started again with the same settings.
An option not given takes the task's value: for a task file, its keys horizon, epsilon, lipschitz,
certify and [expert] time_budget and values.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from dataclasses import asdict
from pathlib import Path

from npp_ros.certificate.certifier import L_FREE
from npp_ros.cli.args import ListTasks, add_run_arguments, nonnegative_int, run_request
from npp_ros.policy.lipschitz import LipschitzWarning
from npp_ros.run.held_out import (
    KEPT_ANSWERS,
    LEARN_HELD_OUT_STREAM,
    KeptAnswers,
    answers_identity,
    check_policy,
    check_success,
    held_out_robots,
    held_out_states,
)
from npp_ros.run.loop import NPPLoop, RunResult
from npp_ros.run.progress import Counter, StatusLine, claim_header, unreachable_text
from npp_ros.run.records import RunFileError, UnrecordedSettings, write_episode_log
from npp_ros.run.request import FIELD_NAMES, resolve_run
from npp_ros.run.setup import build_loop, expert_notice, lipschitz_checks
from npp_ros.run.store import RUN_FILE
from npp_ros.tasks.registry import StopsAtTimeBudget, get_task, task_label
from npp_ros.tasks.sources import short_name
from npp_ros.trajopt.batch_steps import default_threads


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="npp-learn",
        description=__doc__,
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    add_run_arguments(ap, ("task",))
    ap.add_argument("--list-tasks", action=ListTasks, help="list every task and where it comes from, then exit")
    add_run_arguments(ap, tuple(name for name in FIELD_NAMES if name != "task"))
    ap.add_argument(
        "--stop-when-unreachable",
        action="store_true",
        help="end the run, uncertified, as soon as no certificate can come within --max-episodes (the episodes "
        "left are fewer than the rule needs at best: a streak's passes still missing); the run says so either way",
    )
    ap.add_argument("--run-dir", type=Path, default=None, help="run folder; default runs/learn-TASK-seedSEED")
    ap.add_argument(
        "--rollouts", action="store_true", help="with --certify surrogate, let the policy drive every episode too"
    )
    ap.add_argument(
        "--evaluate",
        type=nonnegative_int,
        default=100,
        metavar="N",
        help="after the run, N fresh rollouts (0: none); the expert's answers from them are kept in "
        f"RUN_DIR/{KEPT_ANSWERS} as they arrive, and a rerun (or a larger N) asks only for the s0 not yet answered",
    )
    return ap


EVALUATION_CHUNK = 10  # held-out rollouts stepped in lockstep between progress lines (the numbers do not depend on it)
ENDINGS = {
    "certified": "certified",
    "max-episodes": "at --max-episodes",
    "unreachable": "stopped early (--stop-when-unreachable)",
}


def run_to_end(loop: NPPLoop, max_episodes: int, stop_when_unreachable: bool) -> tuple[RunResult, str]:
    """The run to its certificate or ``max_episodes``; with ``stop_when_unreachable``, to the first moment no
    certificate can come within ``max_episodes`` (CertificationStatus.reachable_within). Also says why it ended."""
    while loop.certificate is None and loop.next_episode < max_episodes:
        left = max_episodes - loop.next_episode
        if stop_when_unreachable and loop.certifier.status().reachable_within(left) is False:
            return loop.run(loop.next_episode), "unreachable"
        loop.run_episode()
    result = loop.run(loop.next_episode)  # runs nothing more: the result of the episodes stored
    return result, "certified" if result.certificate else "max-episodes"


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    task = get_task(args.task)
    run_dir = args.run_dir or Path("runs") / f"learn-{short_name(args.task)}-seed{args.seed}"
    try:
        # one expert, alone in this process: its derivatives may take every core
        run = resolve_run(run_request(args), run_file=run_dir / RUN_FILE, threads=default_threads())
        request, config, expert, epsilon, lipschitz = run.request, run.config, run.expert, run.epsilon, run.lipschitz
        kept = KeptAnswers(run_dir / KEPT_ANSWERS, answers_identity(config))
        if args.evaluate > 0:
            kept.check()  # a file of other answers is refused now (StoredReturnsError), before the run makes its file
        status = StatusLine(
            epsilon, args.condition, max_episodes=args.max_episodes, prefix="npp-learn: ", certify=config.spec.certify
        )
        with warnings.catch_warnings(record=True) as notices:
            warnings.simplefilter("always", UnrecordedSettings)
            loop = build_loop(config, expert, store_path=run_dir / RUN_FILE, rollouts=args.rollouts, observers=[status])
    except (ValueError, RunFileError) as exc:
        print(f"npp-learn: {exc}", file=sys.stderr)
        return 2
    for notice in notices:  # a resumed file that never recorded some settings: said at every resume
        if issubclass(notice.category, UnrecordedSettings):
            print(f"npp-learn: note: {notice.message}", file=sys.stderr)
        else:
            warnings.warn_explicit(notice.message, notice.category, notice.filename, notice.lineno)
    args.horizon = request.horizon

    label = task_label(args.task)  # a task file's name key; its path and hash stay in the run file and summary.json
    print(f"npp-learn: {label} seed {args.seed}, {claim_header(config.spec, config.policy_lipschitz)}", file=sys.stderr)
    if loop.rows:
        print(f"npp-learn: resuming {run_dir / 'run.sqlite'} at episode {loop.next_episode}", file=sys.stderr)
    started = time.perf_counter()
    try:
        result, ended = run_to_end(loop, args.max_episodes, args.stop_when_unreachable)
    except KeyboardInterrupt:
        status.close()
        print(f"\nnpp-learn: interrupted; {loop.next_episode} episodes stored, resumed on restart", file=sys.stderr)
        return 130
    except RunFileError as exc:  # e.g. disk full: the reason and the place, not a traceback
        status.close()
        print(f"\nnpp-learn: {exc}", file=sys.stderr)
        return 2
    status.close()
    elapsed = time.perf_counter() - started
    write_episode_log(run_dir / "episodes.csv", result.rows)
    counts = loop.success_counts()
    relative = config.spec.certify != "success"  # the success claim needs no expert: no warning of a failing one
    for line in expert_notice(args.task, counts, result.rows, relative=relative):  # first: where the user looks
        print(f"npp-learn: {line}", file=sys.stderr)
    sys.stderr.flush()

    evaluation = None
    succeeded = None
    if args.evaluate > 0 and len(loop.dataset):
        states = held_out_states(task, args.seed, args.evaluate, LEARN_HELD_OUT_STREAM)
        certificate = result.certificate
        policy = loop.policy if certificate is None else loop.policy_over(certificate.policy_trajectories)
        if config.spec.certify == "success":
            succeeded = check_success(
                policy, task, task.make_plant(args.seed), states, args.horizon, p=args.p, delta=args.delta,
                robots=held_out_robots(config.uncertainty, args.seed, args.evaluate),
                progress=Counter("held-out: policy rollouts"), chunk=EVALUATION_CHUNK,
            )  # fmt: skip
        try:
            evaluation = None if config.spec.certify == "success" else check_policy(
                policy, task, task.make_plant(args.seed), expert, states, args.horizon,
                epsilon=epsilon, p=args.p, delta=args.delta, against_expert=config.spec.certify == "oracle",
                progress=Counter("held-out: policy rollouts"), chunk=EVALUATION_CHUNK,
                expert_progress=Counter("held-out: the expert's returns"),
                robots=held_out_robots(config.uncertainty, args.seed, args.evaluate), expert_model=config.expert_model,
                kept=kept,
            )  # fmt: skip
        except KeyboardInterrupt:
            kept_at = run_dir / KEPT_ANSWERS
            print(f"\nnpp-learn: interrupted in the held-out check; the run is stored and the expert's answers so "
                  f"far are kept in {kept_at}: the same command goes on from there", file=sys.stderr)  # fmt: skip
            return 130
        if evaluation is not None and evaluation.expert_answers_kept:
            print(f"npp-learn: held-out: {evaluation.expert_answers_kept} of the expert's {evaluation.states} returns "
                  f"kept from an earlier check of this run ({run_dir / KEPT_ANSWERS})", file=sys.stderr)  # fmt: skip
    checks = []  # a claim that rests on no L (oracle, success) has no L to check: nothing is recorded of one
    if config.spec.certify not in L_FREE:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", LipschitzWarning)  # reported below, in the summary
            checks = lipschitz_checks(loop, expert, evaluation.visited_slope if evaluation else 0.0)

    summary = {
        "task": args.task,
        "task_label": label,
        "seed": args.seed,
        "episodes": result.episodes,
        "oracle_calls": result.oracle_calls,
        "dataset_size": result.dataset_size,
        "lipschitz": asdict(lipschitz),
        "certificate": result.certificate.record() if result.certificate else None,
        "lipschitz_checks": [{"slope": c.slope, "source": c.source, "ok": c.ok} for c in checks],
        "lipschitz_assumed": config.spec.certify not in L_FREE,  # whether the claim rests on L (the checks matter)
        "success": {"criterion": task.success.describe() if task.success else None, **asdict(counts)},
        "ended": ended,
        "episodes_to_certify": loop.certifier.status().episodes_to_certify,  # at best, after the last episode
        "wall_time_s": elapsed,
    }
    if result.certificate:
        print(result.certificate.summary(label))
    else:
        print(
            f"NOT CERTIFIED ({label}) after {result.episodes} episodes "
            f"({result.oracle_calls} oracle calls, |D| = {result.dataset_size})"
        )
        why = unreachable_text(loop.certifier.status(), result.episodes, args.max_episodes)
        print(f"  ended           {ENDINGS[ended]}" + (f": {why}" if why else ""))
        print(f"  {loop.measured_success().sentence()}")
    print(f"  L source detail  {lipschitz.detail}")
    if config.spec.certify in L_FREE:  # V^E(s0) - R^pi(s0) and success involve no L: no check can break them
        print(f"  L               the policy's choice: {config.spec.certify} mode's claim does not rest on L, so no L "
              "check applies")  # fmt: skip
    else:
        for check in checks:
            print(f"  L check         {'ok  ' if check.ok else 'FAIL'} {check.message()}")
    if succeeded is not None:
        print(
            f"  evaluation      {succeeded.states} fresh draws"
            + (" of (s0, robot)" if config.uncertainty else " of s0")
            + f": the policy succeeded on {succeeded.succeeded} ({succeeded.fraction:.1%}; binomial test of >= "
            f"{args.p:g}: p = {succeeded.p_value:.2g})"
        )
        summary["evaluation"] = {"rollouts": succeeded.states, "succeeded": succeeded.succeeded,
                                 "fraction_succeeded": succeeded.fraction, "binomial_p_value": succeeded.p_value,
                                 "robots": bool(config.uncertainty)}  # fmt: skip
    if evaluation is not None:
        print(
            f"  evaluation      {evaluation.states} fresh s0, gap to {evaluation.reference}: median "
            f"{evaluation.gap_q50:.2f}, max {evaluation.gap_max:.2f}; {evaluation.fraction:.1%} within epsilon "
            f"(binomial test of >= {args.p:g}: p = {evaluation.p_value:.2g}); "
            f"{evaluation.below_v_lb} returns below V_lb(s0)"
        )
        summary["evaluation"] = {
            "rollouts": evaluation.states,
            "reference": evaluation.reference,
            "fraction_within_epsilon": evaluation.fraction,
            "binomial_p_value": evaluation.p_value,
            "true_gap_median": evaluation.gap_q50,
            "true_gap_max": evaluation.gap_max,
            "lower_bound_violations": evaluation.below_v_lb,
        }
    if isinstance(expert, StopsAtTimeBudget):
        summary["expert_budget_stops"] = expert.budget_stops
        if expert.budget_stops:
            print(
                f"  expert          {expert.budget_stops} requests stopped at the time budget "
                f"({expert.time_budget:g} s): their answers depend on this machine's speed; a larger "
                "--time-budget keeps a run reproducible"
            )
    print(f"  run folder      {run_dir} ({elapsed:.1f} s)")
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return 0 if result.certificate else 1


if __name__ == "__main__":
    sys.exit(main())
