"""A stored run derived again from its own seed and stored answers: an untouched run agrees with itself, in oracle
mode and on a set of robots with success checks; every edit sealed again (as anyone with this code can seal) of what
the run derives is refused by the gate, naming the first episode that differs."""

from __future__ import annotations

import dataclasses
import json
import sqlite3
from pathlib import Path

import numpy as np
import pytest
from deploy_runs import FINGERPRINT, altered_copy, make_run

from npp_ros.deployment.gate import Acceptance, GateRefusal, load_deployment
from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.run.read import read_run
from npp_ros.run.rederive import rederive
from npp_ros.run.seal import SEAL_TABLE, write_seal
from npp_ros.run.setup import build_config, build_loop
from npp_ros.run.trajectory_checksum import trajectory_digest
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.task import ExpertOptions

ACCEPT = Acceptance(model_fingerprint=FINGERPRINT)


@pytest.fixture(scope="module")
def good(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_run(tmp_path_factory.mktemp("rederive") / "good")


@pytest.fixture(scope="module")
def on_a_set(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A short pendulum run on its set of robots with success checks: each episode draws its robot."""
    folder = tmp_path_factory.mktemp("set") / "run"
    task = get_task("pendulum_swingup")
    expert = task.make_expert(0, 60, ExpertOptions(max_iterations=3))
    config = build_config(
        "pendulum_swingup", 0, LipschitzConstant(50.0, "user"), 130.0, horizon=60, uncertainty=1.0, certify="success"
    )
    loop = build_loop(config, expert, store_path=folder / "run.sqlite")
    try:
        loop.run(6)
    finally:
        assert loop.store is not None
        loop.store.close()
    return folder


def test_an_untouched_run_follows_from_its_seed_and_answers(good: Path, on_a_set: Path) -> None:
    seen: list[tuple[int, int]] = []
    found = rederive(read_run(good), progress=lambda done, total: seen.append((done, total)))
    assert found.agrees, found.differences
    assert found.episodes == len(read_run(good).episodes) == seen[-1][0] == seen[-1][1]
    on_set = read_run(on_a_set)
    assert {row.robot for row in on_set.episodes} != {None}
    assert rederive(on_set).agrees
    deployment = load_deployment(good, ACCEPT)
    assert deployment.derived.startswith(f"derived again from its seed and answers: {found.episodes} episodes agree")


def _edit_row(folder: Path, episode: int, column: str, value: object) -> tuple[str, tuple[object, ...]]:
    return (f"UPDATE episodes SET {column} = ? WHERE episode = ?", (value, episode))


def test_each_edit_sealed_again_is_refused_naming_the_first_episode_that_differs(good: Path, tmp_path: Path) -> None:
    run = read_run(good)
    row = run.episodes[5]
    s0 = json.dumps([v + 1e-3 for v in row.initial_state])
    with sqlite3.connect(good / "run.sqlite") as conn:
        steps = conn.execute("SELECT steps FROM trajectories WHERE id = 2").fetchone()[0]
    assert steps > 10
    cases = {
        "an episode's s0": ([_edit_row(good, 5, "initial_state", s0)], "episode 5: initial_state is"),
        "a check's outcome": ([_edit_row(good, 7, "checked_gap", row.checked_gap + 5.0)], "episode 7: checked_gap"),
        "a policy return": ([_edit_row(good, 8, "policy_return", 123.0)], "episode 8: policy_return"),
        "an episode's robot": ([_edit_row(good, 3, "robot", '{"scales": []}')], "episode 3: robot is"),
        "a bound": ([_edit_row(good, 4, "v_lb", 0.0)], "episode 4: v_lb"),
    }  # fmt: skip
    for k, (edits, named) in enumerate(cases.values()):
        with pytest.raises(GateRefusal, match="does not follow from its own seed") as refusal:
            load_deployment(altered_copy(good, tmp_path / f"case{k}", *edits, resealed=True), ACCEPT)
        assert named in str(refusal.value), (named, str(refusal.value))


def test_a_trajectory_edited_with_its_checksum_recomputed_is_refused(good: Path, tmp_path: Path) -> None:
    """A stored answer nudged in the middle, its checksum and the seal recomputed: the policy over it acts otherwise,
    so an episode after it differs; nudged at its start, the answer no longer starts where the run asked."""
    run = read_run(good)
    for step, named in ((40, "episode"), (0, "the run asks for trajectory 3 from")):
        folder = altered_copy(good, tmp_path / f"step{step}")
        with sqlite3.connect(folder / "run.sqlite") as conn:
            conn.execute(
                "UPDATE points SET a_0 = a_0 + 0.5, s_1 = s_1 + 0.5 WHERE trajectory = 3 AND step = ?", (step,)
            )
            traj = run.dataset.trajectory(3)
            states, actions = traj.states.copy(), traj.actions.copy()
            states[step, 1] += 0.5
            actions[step, 0] += 0.5
            edited = dataclasses.replace(traj, states=states, actions=actions)
            conn.execute("UPDATE trajectories SET sha256 = ? WHERE id = 3", (trajectory_digest(edited),))
            conn.execute(f"DELETE FROM {SEAL_TABLE}")  # the points chains hashed anew from the first trajectory
            write_seal(conn)
        assert read_run(folder).dataset.num_trajectories == run.dataset.num_trajectories  # it reads as intact
        with pytest.raises(GateRefusal, match="does not follow from its own seed") as refusal:
            load_deployment(folder, ACCEPT)
        assert named in str(refusal.value), str(refusal.value)


def test_a_set_widened_or_a_robot_or_success_edited_is_refused(on_a_set: Path, tmp_path: Path) -> None:
    run = read_run(on_a_set)
    assert run.robots is not None
    wider = run.robots.widened(1.5)
    widened = ("UPDATE meta SET value = ? WHERE key = 'uncertainty'", (json.dumps(wider.record()),))
    success = next(row for row in run.episodes if row.policy_success is not None)
    flipped = _edit_row(on_a_set, success.episode, "policy_success", int(not success.policy_success))
    robot = json.loads(str(run.episodes[2].robot))
    robot["scales"][0][2] = 1.0
    moved = _edit_row(on_a_set, 2, "robot", json.dumps(robot, sort_keys=True))
    for k, (edit, named) in enumerate(
        (
            (widened, "episode 0: robot is"),
            (flipped, f"episode {success.episode}: policy_success"),
            (moved, "episode 2"),
        )
    ):
        found = rederive(read_run(altered_copy(on_a_set, tmp_path / f"case{k}", edit, resealed=True)))
        assert not found.agrees and named in found.differences[0], (named, found.differences)


def test_the_re_derivation_may_be_turned_off_by_name_and_says_so(good: Path, tmp_path: Path) -> None:
    edited = altered_copy(good, tmp_path / "edited", _edit_row(good, 8, "policy_return", 123.0), resealed=True)
    deployment = load_deployment(edited, dataclasses.replace(ACCEPT, rederive=False))
    assert deployment.derived == "not derived again (rederive is off)"
    assert np.isfinite(deployment.policy.lipschitz)


def test_an_agreement_is_remembered_on_this_machine_for_exactly_that_content(
    good: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Derived again once, the same unchanged file passes at once at its next deployment; the agreement is kept in
    the operator's cache folder (never in the run folder), under the file's seal digest, so it holds for exactly that
    content: the same run edited and sealed again is derived again, and refused."""
    monkeypatch.setenv("NPP_ROS_CACHE", str(tmp_path / "cache"))
    run = altered_copy(good, tmp_path / "run")
    first = load_deployment(run, ACCEPT)
    assert first.derived.startswith("derived again from its seed and answers:"), first.derived
    again = load_deployment(run, ACCEPT)
    assert "on this machine at" in again.derived and "episodes agreed (this content, unchanged since)" in again.derived
    assert (tmp_path / "cache" / "rederived" / f"{read_run(run).seal.digest}.json").is_file()
    assert sorted(path.name for path in run.iterdir()) == sorted(path.name for path in good.iterdir())
    edited = altered_copy(run, tmp_path / "edited", _edit_row(run, 8, "policy_return", 123.0), resealed=True)
    with pytest.raises(GateRefusal, match="episode 8: policy_return"):
        load_deployment(edited, ACCEPT)


def test_epsilon_changed_in_the_metadata_and_the_certificate_alike_is_refused(good: Path, tmp_path: Path) -> None:
    """The edit the certificate's own replay cannot see (the run's epsilon and its certificate's changed together,
    sealed again): derived again against the new epsilon, the run no longer gives the stored rows and certificate."""
    with sqlite3.connect(good / "run.sqlite") as conn:
        record = json.loads(conn.execute("SELECT value FROM meta WHERE key = 'certificate'").fetchone()[0])
    record["epsilon"] = 1.0
    both = (
        ("UPDATE meta SET value = '1.0' WHERE key = 'epsilon'", ()),
        ("UPDATE meta SET value = ? WHERE key = 'certificate'", (json.dumps(record),)),
    )
    edited = altered_copy(good, tmp_path / "eps", *both, resealed=True)
    found = rederive(read_run(edited))
    assert not found.agrees, found  # here the checks' outcomes agree, and the certificate issued again does not
    with pytest.raises(GateRefusal, match="does not follow from its own seed"):
        load_deployment(edited, ACCEPT)
