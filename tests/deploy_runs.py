"""Run folders for npp-deploy's tests: real short-horizon lqr_2_1 runs made with the core loop, copies of them
altered the ways the gate must catch, and a run of a reach whose state holds a target (tests/fixtures/point_reach)."""

from __future__ import annotations

import dataclasses
import json
import shutil
import sqlite3
from pathlib import Path

from npp_ros.certificate.certifier import SUCCESS_EPSILON, StoppingRule
from npp_ros.policy.feedback import PolicyKind
from npp_ros.run.loop import RunConfig, RunResult
from npp_ros.run.seal import write_seal
from npp_ros.run.setup import build_config, build_loop, plant_fingerprint, resolve_lipschitz
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.task import Expert
from npp_ros.tasks.uncertainty import ScaleRange, UncertaintySet

TASK, SEED, HORIZON, EPSILON = "lqr_2_1", 0, 100, 2.0
REACH = str(Path(__file__).resolve().parent / "fixtures" / "point_reach" / "task.toml")
FINGERPRINT = plant_fingerprint(TASK, SEED)
NUDGE_ONE_POINT = "UPDATE points SET s_0 = s_0 + 1e-9 WHERE trajectory = 0 AND step = 3"
NUDGE_ONE_POINT = "UPDATE points SET s_0 = s_0 + 1e-9 WHERE trajectory = 0 AND step = 3"


def stored_run(config: RunConfig, expert: Expert, folder: Path, max_episodes: int) -> RunResult:
    """Algorithm 1 with ``config`` to at most ``max_episodes``, stored in ``folder``'s run file, closed after."""
    loop = build_loop(config, expert, store_path=folder / "run.sqlite")
    try:
        return loop.run(max_episodes)
    finally:
        assert loop.store is not None
        loop.store.close()


def make_run(
    folder: Path, *, rule: StoppingRule = "sequential", max_episodes: int = 300, policy: PolicyKind = "open-loop"
) -> Path:
    """An lqr_2_1 run at H = 100 (oracle checks, epsilon 2): certifies in about 30 episodes, in a second.

    Open loop by default: its checks fail now and then, which the gate's replay of the log needs to tell an edit
    apart (the feedback policy is the LQR expert's own law here, and passes every check)."""
    expert = get_task(TASK).make_expert(SEED, HORIZON)
    lipschitz = resolve_lipschitz(TASK, "analytic", expert)
    config = build_config(TASK, SEED, lipschitz, EPSILON, horizon=HORIZON, certify="oracle", rule=rule, policy=policy)
    stored_run(config, expert, folder, max_episodes)
    return folder


def make_reach_run(folder: Path) -> Path:
    """A certified run of the point-mass reach (its state holds a target): success claimed, the feedback policy, L
    from the data, the file's horizon. Its expert's plan is a linear feedback law, so the policy certifies on one
    expert call, in about 30 episodes and a few seconds."""
    horizon = get_task(REACH).default_horizon
    expert = get_task(REACH).make_expert(SEED, horizon)
    lipschitz = resolve_lipschitz(REACH, None, expert, seed=SEED, horizon=horizon, run_file=folder / "run.sqlite")
    config = build_config(REACH, SEED, lipschitz, SUCCESS_EPSILON, horizon=horizon, certify="success",
                          policy="feedback", expert=expert)  # fmt: skip
    assert stored_run(config, expert, folder, 300).certified
    return folder


def altered_copy(
    source: Path, folder: Path, *statements: tuple[str, tuple[object, ...]], resealed: bool = False
) -> Path:
    """A copy of a run folder with SQL statements applied to its run file (what an edit from outside does);
    ``resealed``: and its seal written again over the edit, as an editor with npp_ros's code can (the gate's
    other checks, and a signature, must then catch it)."""
    shutil.copytree(source, folder)
    with sqlite3.connect(folder / "run.sqlite") as conn:
        for sql, args in statements:
            conn.execute(sql, args)
        if resealed:
            write_seal(conn)
    return folder


def edited_certificate(source: Path, folder: Path, resealed: bool = False, **changes: object) -> Path:
    """A copy whose certificate record has some fields changed."""
    with sqlite3.connect(source / "run.sqlite") as conn:
        record = json.loads(conn.execute("SELECT value FROM meta WHERE key = 'certificate'").fetchone()[0])
    record.update(changes)
    edit = ("UPDATE meta SET value = ? WHERE key = 'certificate'", (json.dumps(record),))
    return altered_copy(source, folder, edit, resealed=resealed)


def bad_folders(good: Path, root: Path) -> dict[str, tuple[Path, str]]:
    """Each way a folder must be refused: name -> (folder, words the refusal must contain)."""
    return {
        "missing": (root / "nothing-here", "does not exist"),
        "uncertified": (make_run(root / "uncertified", max_episodes=5), "no certificate"),
        "not proven": (make_run(root / "paper-rule", rule="paper"), "not proven"),
        "altered data": (altered_copy(good, root / "altered-data", (NUDGE_ONE_POINT, ())), "points.s_0"),
        "altered certificate": (edited_certificate(good, root / "altered-certificate", epsilon=50.0), "altered"),
        "another policy": (edited_certificate(good, root / "another-policy", policy="feedback"), "altered"),
        "deleted certificate": (
            altered_copy(good, root / "deleted-certificate", ("DELETE FROM meta WHERE key = 'certificate'", ())),
            "meta 'certificate' \\(removed\\)",
        ),
    }


# The set a test run is said to be certified on: lqr_2_1 declares none, and a certified run under uncertainty on a
# swing-up takes minutes, so the tests record the swing-ups' ranges in a short lqr run's metadata and seal it again.
LQR_ROBOTS = UncertaintySet(
    (ScaleRange("mass", 0.8, 1.2), ScaleRange("gear", 0.8, 1.2), ScaleRange("damping", 0.5, 1.5))
)


def with_robots(folder: Path, robots: UncertaintySet = LQR_ROBOTS, horizon: int = HORIZON) -> Path:
    """A real lqr_2_1 run on a set of robots (``robots``, resolved on the run's model): each episode draws its robot
    and the expert plans on it. The feedback policy (the LQR law) certifies it in about 30 episodes, in seconds; at
    the task's own horizon (1000) its rollouts settle, as lqr_2_1's success criterion asks."""
    expert = get_task(TASK).make_expert(SEED, horizon)
    lipschitz = resolve_lipschitz(TASK, "analytic", expert)
    config = build_config(TASK, SEED, lipschitz, EPSILON, horizon=horizon, certify="oracle", policy="feedback")
    record = robots.resolved(get_task(TASK).make_plant(SEED).physics.model).record()
    assert stored_run(dataclasses.replace(config, uncertainty=record), expert, folder, 300).certified
    return folder
