"""npp-robots: the robots inside a set, one by one. Where in the set a run's policy and expert failed (map), where
the expert alone fails before any run (expert), and a claim about the share of robots on which a certified policy
succeeds often enough (claim), which a certificate over (s0, theta) does not make.

Exit codes: 0 done (claim: certified), 1 claim: the checks did not certify it, 2 refused (the reason in one line),
130 stopped by Ctrl-C (a claim's robot checks so far are kept in the run folder; the same command goes on).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from npp_ros.run.per_robot.claim import (
    DEFAULT_BETA,
    DEFAULT_MAX_CHECKS,
    DEFAULT_RULE,
    as_settings,
    claim_file,
    claim_for_run,
    stderr_progress,
    threshold_for,
)
from npp_ros.run.per_robot.success_map import DEFAULT_BINS, SuccessMap
from npp_ros.run.read import read_run
from npp_ros.run.records import RunFileError
from npp_ros.tasks.registry import UnknownTaskError
from npp_ros.tasks.uncertainty import Robot

MAP_FIGURE = "robot-map.png"  # in the run folder, unless --figure says where


def parser() -> argparse.ArgumentParser:
    top = argparse.ArgumentParser(
        prog="npp-robots",
        description="A certificate over a set of robots claims P_((s0, theta)~rho x Theta)[success] >= p: an average "
        "over robots, which allows a policy that fails on a corner of the set. These commands show where in the set "
        "the policy and its expert fail, and certify a claim about the robots themselves: with probability >= "
        "1 - delta, P_theta[r(theta) >= p_r] >= q, r(theta) being the policy's success rate on robot theta.",
        epilog="Exit codes: 0 done (claim: certified), 1 claim not certified, 2 refused, 130 stopped by Ctrl-C.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    commands = top.add_subparsers(dest="command", required=True)

    where = commands.add_parser(
        "map",
        help="where in its set a run's policy (in its checks) and expert (in its answers) failed, per parameter bin",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    where.add_argument("run", type=Path, help="a run folder (holds run.sqlite) of a run on a set (--uncertainty > 0)")
    add_map_options(where, f"the figure's file (default: RUN/{MAP_FIGURE})")

    expert = commands.add_parser(
        "expert",
        help="before a run: where in a set the task's expert itself fails (N draws of (s0, robot); seconds each)",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    expert.add_argument("--task", required=True, help="a registered task or a task file (.toml)")
    expert.add_argument("--uncertainty", type=float, default=1.0, help="the set: the task's ranges times this factor")
    expert.add_argument("--robots", type=int, default=40, help="draws of (s0, robot) to ask the expert about")
    expert.add_argument("--seed", type=int, default=0, help="the plant's seed and the draws' stream")
    expert.add_argument("--horizon", type=int, default=None, help="episode length (default: the task's)")
    add_map_options(expert, "the figure's file (default: none)")

    claim = commands.add_parser(
        "claim",
        help="certify Q(q, p_r): with prob >= 1 - delta, P_theta[r(theta) >= p_r] >= q, by m rollouts per drawn robot",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description="Each robot check draws theta from the run's set and m starts s0 ~ rho (streams of their own), "
        "rolls the run's certified policy out on theta from each, and passes at >= c successes. A robot with "
        "r(theta) < p_r passes with probability <= beta = P(Binomial(m, p_r) >= c), so certifying P(pass) >= "
        "q + beta (1 - q) by a sequentially valid rule gives the claim. No expert is asked. The checks are kept in "
        "the run folder as they are made: a stopped claim goes on from them, and a claim with the same m reuses them.",
    )
    claim.add_argument("run", type=Path, help="a certified run folder of a run on a set (--uncertainty > 0)")
    claim.add_argument("--q", type=float, default=0.9, help="the share of robots claimed")
    claim.add_argument("--p-r", type=float, default=0.8, help="the success rate each of those robots has at least")
    claim.add_argument("--m", type=int, default=50, help="starts (rollouts) per robot check")
    claim.add_argument("--c", type=int, default=None, help="successes of m a check passes at (default: chosen by beta)")
    claim.add_argument("--beta", type=float, default=DEFAULT_BETA,
                       help="without --c: the smallest c with P(Binomial(m, p_r) >= c) <= this")  # fmt: skip
    claim.add_argument("--delta", type=float, default=0.1, help="the claim holds with probability >= 1 - delta")
    claim.add_argument("--rule", choices=("mixture", "sequential"), default=DEFAULT_RULE,
                       help="the stopping rule over robot checks (mixture: a frozen policy learns nothing from a "
                       "failure, and the mixture test tolerates some)")  # fmt: skip
    claim.add_argument("--max-checks", type=int, default=DEFAULT_MAX_CHECKS, help="robot checks at most")
    claim.add_argument("--min-checks", type=int, default=0,
                       help="robot checks to make even once the rule can no longer certify within --max-checks (a "
                       "survey of the set beside the claim; they never make a false claim likelier)")  # fmt: skip
    claim.add_argument("--json", type=Path, default=None, help="also write the claim's record here")

    threshold = commands.add_parser(
        "threshold",
        help="the pass threshold c for m starts at p_r, and its beta",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    threshold.add_argument("--m", type=int, default=50, help="starts per robot check")
    threshold.add_argument("--p-r", type=float, default=0.8, help="the per-robot success rate claimed")
    threshold.add_argument("--beta", type=float, default=DEFAULT_BETA, help="the largest beta allowed")
    return top


def add_map_options(command: argparse.ArgumentParser, figure_help: str) -> None:
    command.add_argument("--bins", type=int, default=DEFAULT_BINS, help="bins per parameter range")
    command.add_argument("--figure", type=Path, default=None, help=figure_help)
    command.add_argument("--json", type=Path, default=None, help="also write the table's counts here (JSON)")


def show_map(success: SuccessMap, figure: Path | None, out: Path | None) -> None:
    from npp_ros.run.per_robot.figure import write_figure

    print(success.table())
    if figure is not None:
        figure.parent.mkdir(parents=True, exist_ok=True)
        print(f"figure: {write_figure(success, figure)}")
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(success.record(), indent=1) + "\n")
        print(f"counts: {out}")


def main(argv: Sequence[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        if args.command == "threshold":
            c, beta = threshold_for(args.m, args.p_r, args.beta)
            print(f"m {args.m}, p_r {args.p_r:g}: pass at >= {c} successes; beta = P(Binomial({args.m}, "
                  f"{args.p_r:g}) >= {c}) = {beta:.4f}")  # fmt: skip
        elif args.command == "map":
            run = read_run(args.run)
            success = run.success_map
            if success is None:
                raise ValueError(f"run {run.folder.name} is on the exact model: one robot, nothing to split")
            show_map(success, args.figure or run.folder / MAP_FIGURE, args.json)
        elif args.command == "expert":
            from npp_ros.run.per_robot.expert_map import expert_map

            def told(done: int, total: int, robot: Robot, met: bool) -> None:
                print(f"expert answer {done:4d}/{total} | {'met' if met else 'FAILED'} | {robot.describe()}",
                      file=sys.stderr, flush=True)  # fmt: skip

            success = expert_map(
                args.task, args.uncertainty, args.robots, seed=args.seed, horizon=args.horizon, bins=args.bins,
                progress=told,
            )  # fmt: skip
            show_map(success, args.figure, args.json)
        else:
            return make_claim(args)
    except (ValueError, RunFileError, UnknownTaskError) as exc:
        print(f"npp-robots: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("npp-robots: stopped", file=sys.stderr)
        return 130
    return 0


def make_claim(args: argparse.Namespace) -> int:
    settings = as_settings(args.q, args.p_r, args.m, args.c, args.beta, args.delta, args.rule)
    run = read_run(args.run)
    try:
        claim = claim_for_run(
            run, settings, max_checks=args.max_checks, min_checks=args.min_checks, progress=stderr_progress
        )
    except KeyboardInterrupt:
        print(f"npp-robots: stopped; the robot checks made so far are kept in {claim_file(run.folder, settings)}: "
              "the same command goes on from them", file=sys.stderr)  # fmt: skip
        return 130
    print(claim.text())
    print(f"kept: {claim_file(run.folder, settings)}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(claim.__dict__, indent=1) + "\n")
        print(f"record: {args.json}")
    return 0 if claim.certified else 1


if __name__ == "__main__":
    sys.exit(main())
