"""A run on a robot built from a request, as every door builds a run: its config names the robot, its parts are the
robot's episodes and the expert's plans run on the robot."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

from npp_ros.policy.dataset import Dataset
from npp_ros.run.loop import NPPLoop, Observer, Oracle, RunConfig
from npp_ros.run.nominal_plan import stores_window_values
from npp_ros.run.on_robot.episodes import DEFAULT_MAX_FAULTS, RobotEpisodes
from npp_ros.run.on_robot.identity import RobotIdentity
from npp_ros.run.on_robot.link import RobotLink
from npp_ros.run.on_robot.recorded import RecordedRobot, StoredRobotAnswers
from npp_ros.run.on_robot.robot_expert import RobotPlanOracle
from npp_ros.run.read import read_run
from npp_ros.run.setup import initial_state_fn, task_control_space, value_basis
from npp_ros.run.store import RunStore
from npp_ros.tasks.registry import Expert, get_task


def prior_record(folder: Path, config: RunConfig) -> tuple[str, Dataset]:
    """What a run on a robot starts with from another run of its task (a run on its set of robots, say): that run's
    certified policy's trajectories (all of them when it has no certificate), and the record naming them (its folder's
    name, its seal digest, their count). A ValueError for a run of another task or shape."""
    run = read_run(folder)
    if run.task.name != config.task or int(run.metadata.seed) != config.seed:
        raise ValueError(f"{folder} is a run of {run.task.name} seed {run.metadata.seed}, not {config.task} seed "
                         f"{config.seed}")  # fmt: skip
    count = run.dataset.num_trajectories if run.certificate is None else run.certificate.policy_trajectories
    if count == 0:
        raise ValueError(f"{folder} holds no trajectories to start from")
    data = run.dataset if count == run.dataset.num_trajectories else run.dataset.prefix(count)
    record = {"run": Path(folder).resolve().name, "seal": run.seal.digest, "trajectories": count,
              "certified": run.certificate is not None}  # fmt: skip
    return json.dumps(record, sort_keys=True), data


def prior_words(record: str) -> str:
    """A prior record (prior_record) as the certificate names it; '' for none."""
    if not record:
        return ""
    said = json.loads(record)
    kind = "certified " if said.get("certified") else ""
    return f"{said['trajectories']} trajectories of the {kind}run {said['run']} (seal {said['seal'][:12]}...)"


def robot_run_config(config: RunConfig, identity: RobotIdentity) -> RunConfig:
    """A run's config made a run on ``identity``'s robot; a ValueError for what such a run cannot be."""
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
    if config.policy_lipschitz != "claim":
        raise ValueError(
            "a run on a robot chooses no policy L from its data (policy_lipschitz claim): each candidate's rollout "
            "would be an episode of the robot itself"
        )
    return replace(config, robot_run=identity.record())


def build_robot_loop(
    config: RunConfig,
    expert: Expert,
    link: RobotLink,
    identity: RobotIdentity,
    *,
    store_path: Path | None = None,
    observers: Sequence[Observer] = (),
    max_faults: int = DEFAULT_MAX_FAULTS,
    log: Callable[[str], None] = lambda text: None,
    answers: Dataset | None = None,
    prior_run: Path | None = None,
) -> NPPLoop:
    """Algorithm 1 with the robot as the plant: each check one of its episodes, each answer a plan it ran. ``config``
    and ``expert`` are a resolved request's (npp_ros.run.request.resolve_run), or a stored run's.

    ``answers``: the run's stored answers, with ``link`` its stored robot episodes (recorded.RecordedRobot): the run
    played back from its file, as a gate derives it again (no store, no expert asked, no fault ends it).
    ``prior_run``: a run folder whose trajectories the run starts with (prior_record); the record says which."""
    config = robot_run_config(config, identity)
    prior = None
    if prior_run is not None:
        record, prior = prior_record(prior_run, config)
        config = replace(config, prior=record)
    elif answers is not None and config.prior:  # played back: its first trajectories are the stored ones
        prior = answers.prefix(int(json.loads(config.prior)["trajectories"]))
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
        prior=prior_words(config.prior),
    )
    space = task_control_space(config.task, config.seed)
    window = stores_window_values(expert)
    oracle: Oracle
    if answers is not None:
        assert isinstance(link, RecordedRobot), "a played-back run's link is its stored robot episodes"
        oracle = StoredRobotAnswers(
            link, episodes, answers, window=window, first=0 if prior is None else prior.num_trajectories
        )
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
        prior=prior,
    )
