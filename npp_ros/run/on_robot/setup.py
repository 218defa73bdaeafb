"""A run on a robot built from a request, as every door builds a run: its config names the robot, its parts are the
robot's episodes and the expert's plans run on the robot."""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

from npp_ros.policy.dataset import Dataset
from npp_ros.run.loop import NPPLoop, Observer, Oracle, RunConfig
from npp_ros.run.on_robot.episodes import DEFAULT_MAX_FAULTS, RobotEpisodes
from npp_ros.run.on_robot.expert import RobotPlanOracle
from npp_ros.run.on_robot.identity import RobotIdentity
from npp_ros.run.on_robot.link import RobotLink
from npp_ros.run.on_robot.recorded import RecordedRobot, StoredRobotAnswers
from npp_ros.run.request import ResolvedRun
from npp_ros.run.setup import initial_state_fn, task_control_space, value_basis
from npp_ros.run.store import RunStore
from npp_ros.tasks.nominal_plan import stores_window_values
from npp_ros.tasks.registry import get_task


def robot_run_config(resolved: ResolvedRun, identity: RobotIdentity) -> RunConfig:
    """The resolved run's config made a run on ``identity``'s robot; a ValueError for what such a run cannot be."""
    config = resolved.config
    if config.spec.certify != "success":
        raise ValueError(
            f"a run on a robot certifies the success claim only (certify success), not {config.spec.certify}: its "
            "checks are the robot's own episodes, which give no expert value to compare with"
        )
    if get_task(config.task).success is None:
        raise ValueError(f"the task {config.task} states no success criterion, which a run on a robot is judged on")
    if config.uncertainty:
        raise ValueError("a run on a robot is on that one robot: it takes no set of robots (uncertainty 0)")
    if config.explore > 0:
        raise ValueError("a run on a robot does not explore: every state it asks about is a reset of the robot")
    return replace(config, robot_run=identity.record())


def build_robot_loop(
    resolved: ResolvedRun,
    link: RobotLink,
    identity: RobotIdentity,
    *,
    store_path: Path | None = None,
    observers: Sequence[Observer] = (),
    max_faults: int = DEFAULT_MAX_FAULTS,
    log: Callable[[str], None] = lambda text: None,
    answers: Dataset | None = None,
) -> NPPLoop:
    """Algorithm 1 with the robot as the plant: each check one of its episodes, each answer a plan it ran.

    ``answers``: the run's stored answers, with ``link`` its stored robot episodes (recorded.RecordedRobot): the run
    played back from its file, as a gate derives it again (no store, no expert asked, no fault ends it)."""
    config = robot_run_config(resolved, identity)
    task = get_task(config.task)
    store = None if store_path is None else RunStore.open_or_create(store_path, config.metadata())
    if answers is not None:
        max_faults = sys.maxsize
    draw = initial_state_fn(config.task, config.seed)
    episodes = RobotEpisodes(
        link,
        task.make_plant(config.seed),
        config.horizon,
        identity,
        requested=draw if identity.starts == "rho" else (lambda episode: None),
        success=task.success,
        store=store,
        max_faults=max_faults,
        log=log,
    )
    space = task_control_space(config.task, config.seed)
    expert = resolved.expert
    window = stores_window_values(expert)
    oracle: Oracle
    if answers is not None:
        assert isinstance(link, RecordedRobot), "a played-back run's link is its stored robot episodes"
        oracle = StoredRobotAnswers(link, episodes, answers, window=window)
    else:
        oracle = RobotPlanOracle(expert, episodes, space, planning=identity.planning_robot, window=window)
    return NPPLoop(
        config,
        oracle,
        episodes.initial_state,
        store=store,
        driver=episodes,
        observers=observers,
        basis=value_basis(expert, config.spec.lipschitz.value),
        control=space,
        success=task.success,
        replay=episodes,
        robot_facts=episodes,
    )
