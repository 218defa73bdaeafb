"""npp-identify: which robot of a set this one is, from a recording of its own motion.

Reads a recording of the robot (a bag of its joint states and its commands, or an .npz of the arrays a
:class:`~npp_ros.identification.recording.Recording` saves), fits the set's parameters by least squares on one-step
predictions through the task's MuJoCo model, and prints what the motion determines (the identifiable combinations,
with intervals), the delay, and where the robot lies against the set. With --check (and --run), the certified
policy is then simulated at the identified robot and the robot may move or not.

The core reads .npz recordings; a bag is read by the ROS package's command of the same name
(npp_ros_graph.tools.identify), which converts it to a Recording in one place and runs this one.

Exit codes: 0 done (with --check: the robot may move), 1 with --check: it must not, 2 a refusal (bad input).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from npp_ros.cli.args import nonnegative_int, positive_int, task_name
from npp_ros.identification.check import check_before_move
from npp_ros.identification.fit import identify
from npp_ros.identification.recording import Recording
from npp_ros.run.read import Run, read_run
from npp_ros.run.records import RunFileError
from npp_ros.tasks.registry import Plant, Task, get_task
from npp_ros.tasks.uncertainty import UncertaintySet

# (source, plant, args) -> the recording; the ROS package's command gives one that reads bags
Reader = Callable[[Path, Plant, argparse.Namespace], Recording]


def parser(bag_topics: tuple[str, str] | None = None) -> argparse.ArgumentParser:
    """The options; ``bag_topics`` (the joint states' and the commands' default topics) adds a bag's options."""
    ap = argparse.ArgumentParser(
        prog="npp-identify",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="e.g. npp-identify robot.bag --run runs/pendulum --check   (the set, task and seed from the run)",
    )
    bags = bag_topics is not None
    what = "a bag folder (joint states and commands, as recorded) or an .npz recording" if bags else "an .npz recording"
    ap.add_argument("source", type=Path, help=what)
    ap.add_argument("--run", type=Path, default=None, help="a certified run folder: its task, seed and set of robots")
    ap.add_argument("--task", type=task_name, default=None, help="the task (a name or a task file), without --run")
    ap.add_argument("--seed", type=nonnegative_int, default=None, help="the task's plant seed (default: the run's, 0)")
    ap.add_argument(
        "--uncertainty", type=float, default=1.0, metavar="FACTOR",
        help="the set to place the robot in, without --run: the task's own widened by FACTOR (default 1)",
    )  # fmt: skip
    ap.add_argument("--max-delay", type=nonnegative_int, default=None,
                    help="the largest delay tried, in control steps (default: the set's + 2)")  # fmt: skip
    ap.add_argument("--steps", type=positive_int, default=1, help="control steps per prediction (default 1)")
    ap.add_argument("--confidence", type=float, default=0.95, help="the intervals' level (default 0.95)")
    ap.add_argument("--start", type=float, default=0.0, metavar="S", help="skip the first S seconds")
    ap.add_argument("--seconds", type=float, default=None, metavar="S", help="use S seconds (default: all)")
    ap.add_argument("--json", action="store_true", help="print the result as one JSON object")
    ap.add_argument(
        "--out",
        type=Path,
        default=None,
        metavar="FILE",
        help="also write the result as JSON to FILE (npp-deploy's identified_robot reads it)",
    )
    if bag_topics is not None:
        bag = ap.add_argument_group("a bag's topics")
        bag.add_argument("--joint-states-topic", default=bag_topics[0], help=f"default {bag_topics[0]}")
        bag.add_argument("--command-topic", default=bag_topics[1], help=f"default {bag_topics[1]}")
        bag.add_argument("--command-joints", default="", metavar="A,B",
                         help="the command's joints in its order (default: the task's actuated joints)")  # fmt: skip
    check = ap.add_argument_group("the check before it moves (needs --run)")
    check.add_argument("--check", action="store_true", help="simulate the certified policy at the identified robot")
    check.add_argument("--n", type=positive_int, default=200, help="s0 ~ rho per point (default 200)")
    check.add_argument("--p", type=float, default=None, help="the success it needs (default: the run's p)")
    check.add_argument("--delta-g", type=float, default=0.05, help="the check's level (default 0.05)")
    return ap


def say(text: str) -> None:
    print(f"npp-identify: {text}", file=sys.stderr, flush=True)


def read_npz(source: Path, plant: Plant, args: argparse.Namespace) -> Recording:
    del plant, args
    if source.suffix != ".npz":
        raise ValueError(f"{source}: this command reads .npz recordings; a bag needs ROS's npp-identify")
    return Recording.load(source)


def main(
    argv: Sequence[str] | None = None, reader: Reader = read_npz, bag_topics: tuple[str, str] | None = None
) -> int:
    """The command; the ROS package's npp-identify gives a ``reader`` of bags and their default topics."""
    args = parser(bag_topics).parse_args(argv)
    try:
        task, seed, robots, run = _target(args)
        recording = reader(args.source, task.make_plant(seed), args)
        if args.start or args.seconds is not None:
            recording = recording.window(args.start, float("inf") if args.seconds is None else args.seconds)
        say(f"{len(recording)} states over {recording.seconds:.1f} s of {task.name}; fitting "
            f"{robots.describe()}")  # fmt: skip
        started = time.perf_counter()

        def progress(text: str) -> None:
            say(f"{text} ({time.perf_counter() - started:.1f} s)")

        found = identify(task, recording, robots, seed=seed, max_delay=args.max_delay, steps=args.steps,
                         confidence=args.confidence, progress=progress)  # fmt: skip
    except (ValueError, OSError, RunFileError) as exc:
        say(str(exc))
        return 2
    out: dict[str, object] = {"identification": found.record()}
    text = [found.summary()]
    status = 0
    if run is not None and args.check:
        say(f"checking the certified policy at {len(found.region())} robots, {args.n} s0 each")
        try:
            move = check_before_move(run, found, n=args.n, p=args.p, delta_g=args.delta_g,
                                     progress=lambda k, total: say(f"check: point {k} of {total} done"))  # fmt: skip
        except ValueError as exc:
            say(str(exc))
            return 2
        out["check"] = move.record()
        text.append(move.summary())
        status = 0 if move.accepted else 1
    print(json.dumps(out, indent=1) if args.json else "\n".join(text))
    if args.out is not None:
        args.out.write_text(json.dumps(out, indent=1) + "\n")
        say(f"wrote {args.out}")
    return status


def _target(args: argparse.Namespace) -> tuple[Task, int, UncertaintySet, Run | None]:
    """The task, seed, set and run the options name (a run's own, or the task's set widened)."""
    if args.check and args.run is None:
        raise ValueError("--check needs --run: the certified run whose policy is checked")
    if not 0 < args.confidence < 1:
        raise ValueError(f"--confidence must lie in (0, 1), got {args.confidence}")
    if args.run is not None:
        run = read_run(args.run)
        if run.robots is None:
            raise ValueError(f"{args.run} was certified on the exact model: there is no set to place a robot in")
        seed = int(run.metadata.seed) if args.seed is None else args.seed
        return run.task, seed, run.robots, run
    if args.task is None:
        raise ValueError("name the task (--task) or a run (--run)")
    task = get_task(args.task)
    return task, 0 if args.seed is None else args.seed, task.uncertainty.widened(args.uncertainty), None
