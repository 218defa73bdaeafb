"""Before a run: where in a set the task's expert itself fails, on robots and starts drawn for this alone.

A policy learns from its expert, and a certificate compares with it or counts on its answers: a corner of the set
where the privileged expert (planning on the robot it is asked about) cannot do the task is a corner no policy of
this run will learn. This asks the expert on ``count`` draws of (s0, theta) from the set, judges each answer on the
task's success criterion and tables the outcomes as the run's map does (npp_ros.run.per_robot.success_map).

The draws are a function of (seed, k) only, at episode indices no run, held-out check or robot claim reaches.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from npp_ros.run.per_robot.success_map import DEFAULT_BINS, SuccessMap, model_bodies, success_map
from npp_ros.run.setup import PrivilegedExpert, uncertainty_record
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.uncertainty import Robot, UncertaintySet

EXPERT_MAP_INDEX = 3 << 30  # draw k sits at episode index EXPERT_MAP_INDEX + k
START_STREAM = 2  # its s0's spawn key beside theta's (1)


def expert_draw(task_name: str, robots: UncertaintySet, seed: int, k: int) -> tuple[Robot, np.ndarray]:
    """Draw k: its robot and its s0."""
    robot = robots.draw(seed, EXPERT_MAP_INDEX + k)
    rng = np.random.default_rng([int(seed), EXPERT_MAP_INDEX + int(k), START_STREAM])
    return robot, get_task(task_name).sample_initial_state(rng)


def expert_map(
    task_name: str,
    factor: float,
    count: int,
    *,
    seed: int = 0,
    horizon: int | None = None,
    bins: int = DEFAULT_BINS,
    progress: Callable[[int, int, Robot, bool], None] | None = None,
) -> SuccessMap:
    """The expert's success on ``count`` draws from the task's set widened by ``factor``; a ValueError (one line)
    for a task without a set, a success criterion or an expert that plans on a robot."""
    if count < 1:
        raise ValueError(f"the number of robots must be >= 1, got {count}")
    task = get_task(task_name)
    if task.success is None:
        raise ValueError(f"{task.name} states no success criterion: there is nothing to judge its expert's answers on")
    record = uncertainty_record(task_name, seed, factor, "robot")
    if not record:
        raise ValueError("uncertainty 0 is the exact model: one robot, nothing to split (give --uncertainty > 0)")
    robots = UncertaintySet.from_record(record)
    horizon = task.default_horizon if horizon is None else horizon
    expert = PrivilegedExpert(task.make_expert(seed, horizon))
    draws: list[tuple[Robot, bool | None, bool | None]] = []
    for k in range(count):
        robot, s0 = expert_draw(task_name, robots, seed, k)
        met = task.success.met(expert.trajectory(s0, robot).states)
        draws.append((robot, None, met))
        if progress is not None:
            progress(k + 1, count, robot, met)
    source = (
        f"{task.name}'s expert on {count} draws of (s0, robot), uncertainty {factor:g}, seed {seed} (it plans on "
        "each robot's model: its answers do not feel the delay, as in a run)"
    )
    return success_map(robots, draws, source, bins=bins, bodies=model_bodies(task, seed))
