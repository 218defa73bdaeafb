"""A run whose plant is a robot (npp_ros.run.on_robot), on simulated robots whose parameters the run is not told:
an exact robot gives the run on the model check for check; a fault is stored and marked and never a check; a stop
between a robot's episode and its row takes that episode up again; the certificate names the robot and rests on no
model; the run refuses what it cannot be."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
from deploy_runs import altered_copy

from npp_ros.deployment.gate import Acceptance, GateRefusal, load_deployment
from npp_ros.run.loop import NPPLoop
from npp_ros.run.on_robot.identity import RobotIdentity
from npp_ros.run.on_robot.link import RobotGone
from npp_ros.run.on_robot.setup import build_robot_loop
from npp_ros.run.on_robot.simulated import SimulatedRobot
from npp_ros.run.read import read_run
from npp_ros.run.records import RobotEpisode, RunFileError
from npp_ros.run.rederive import rederive
from npp_ros.run.request import RunRequest, resolve_run
from npp_ros.run.setup import build_loop
from npp_ros.run.store import RunStore
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.uncertainty import Robot

TASK = "lqr_2_1"  # a closed-form expert and a success criterion: robot runs of a few seconds
HORIZON = 150  # too short for the expert to succeed: every check fails and asks it (the faults and stops below)
CERTIFYING_HORIZON = 1000  # the task's own: its policy certifies after about 30 checks


def resolved(horizon: int = HORIZON):
    return resolve_run(RunRequest(task=TASK, seed=0, certify="success", horizon=horizon))


def simulated(robot: Robot | None = None, **how: object) -> SimulatedRobot:
    return SimulatedRobot(get_task(TASK).make_plant(0), robot, **how)  # type: ignore[arg-type]


def identity() -> RobotIdentity:
    return RobotIdentity(fingerprint=get_task(TASK).make_plant(0).model_sha256())


def robot_loop(link: SimulatedRobot, path: Path | None, horizon: int = HORIZON, **how: object) -> NPPLoop:
    run = resolved(horizon)
    return build_robot_loop(run.config, run.expert, link, identity(), store_path=path, **how)  # type: ignore[arg-type]


def test_an_exact_robot_gives_the_run_on_the_model_check_for_check(tmp_path: Path) -> None:
    """On a robot that is the model, without noise or delay, the robot's own episodes are the model's rollouts and
    the expert's plans, run by their feedback law, are its plans: the same starts, checks and data."""
    model_run = build_loop(resolved().config, resolved().expert)
    robot_run = robot_loop(simulated(), tmp_path / "run.sqlite")
    for _ in range(8):
        a, b = model_run.run_episode(), robot_run.run_episode()
        np.testing.assert_allclose(a.initial_state, b.initial_state, atol=1e-12)
        assert (a.oracle_called, a.policy_success, a.checked_gap) == (b.oracle_called, b.policy_success, b.checked_gap)
        assert (a.policy_return is None) == (b.policy_return is None)
        if a.policy_return is not None:
            assert a.policy_return == pytest.approx(b.policy_return, rel=1e-9, abs=1e-9)
    assert model_run.dataset.num_trajectories == robot_run.dataset.num_trajectories >= 1
    for k in range(model_run.dataset.num_trajectories):
        np.testing.assert_allclose(model_run.dataset.trajectory(k).states, robot_run.dataset.trajectory(k).states,
                                   atol=1e-9)  # fmt: skip
        np.testing.assert_allclose(model_run.dataset.trajectory(k).actions, robot_run.dataset.trajectory(k).actions,
                                   atol=1e-9)  # fmt: skip
    kept = RunStore.open(tmp_path / "run.sqlite").robot_episodes()
    assert [k.role for k in kept].count("check") == 8 - 1  # the first episode has no policy to check
    assert all(k.fault is None for k in kept)
    assert {k.steps for k in kept if k.role == "check"} == {HORIZON}


def test_a_fault_is_stored_and_marked_never_a_check_and_the_episode_runs_again(tmp_path: Path) -> None:
    link = simulated(faults={(3, 40)})  # the third reset's episode loses its states at step 40
    loop = robot_loop(link, tmp_path / "run.sqlite")
    loop.run(6)
    kept = RunStore.open(tmp_path / "run.sqlite").robot_episodes()
    cut = [k for k in kept if k.fault is not None]
    assert len(cut) == 1 and cut[0].steps == 40 and "dropout" in cut[0].fault
    assert cut[0].success is None and cut[0].policy_return is None
    episodes = [row.episode for row in loop.rows]
    assert episodes == list(range(len(loop.rows)))  # the cut episode was run again under the same index
    checks = [k for k in kept if k.role == "check" and k.fault is None]
    assert len({k.episode for k in checks}) == len(checks)  # one counted check per episode
    assert cut[0].episode in {k.episode for k in checks}  # the episode the fault cut ran again, and counted once


def test_a_robot_faulting_in_a_row_stops_the_run_which_resumes_where_it_stopped(tmp_path: Path) -> None:
    path = tmp_path / "run.sqlite"
    loop = robot_loop(simulated(faults={(k, 5) for k in range(3, 6)}), path, max_faults=3)
    with pytest.raises(RobotGone, match="3 times in a row"):
        loop.run(10)
    stopped = len(loop.rows)
    loop.store.close()  # type: ignore[union-attr]
    again = robot_loop(simulated(), path)
    assert len(again.rows) == stopped
    again.run(stopped + 2)
    assert [row.episode for row in again.rows] == list(range(stopped + 2))
    assert sum(k.fault is not None for k in again.store.robot_episodes()) == 3  # type: ignore[union-attr]


def test_a_stop_between_the_robots_episode_and_its_row_takes_that_episode_up_again(tmp_path: Path) -> None:
    """The check the robot ran is stored before its row: a resumed run judges that same episode, and the robot does
    not run it anew (a stop must never decide a check)."""
    path = tmp_path / "run.sqlite"
    loop = robot_loop(simulated(), path)
    loop.run(3)
    loop.store.close()  # type: ignore[union-attr]
    # Stop inside the next episode, after the robot's check and before its row: the expert's reset is where it stops.
    link = simulated()
    stopping = robot_loop(link, path)

    def stop(*_: object) -> None:
        raise KeyboardInterrupt

    stopping.oracle.trajectory = stop  # type: ignore[method-assign]
    with pytest.raises(KeyboardInterrupt):
        while True:
            stopping.run_episode()
    stopping.store.close()  # type: ignore[union-attr]
    kept_before = RunStore.open(path).robot_episodes()
    pending = kept_before[-1]
    assert pending.role == "check" and pending.success is False
    resumed_link = simulated()
    resumed = robot_loop(resumed_link, path)
    row = resumed.run_episode()
    assert row.episode == pending.episode and row.oracle_called
    assert row.initial_state == pending.start
    checks = [k for k in resumed.store.robot_episodes() if k.role == "check" and k.episode == pending.episode]  # type: ignore[union-attr]
    assert len(checks) == 1  # judged once, on the robot's one episode


HIDDEN = Robot((("damping", "joint_0", 1.3),), 0, 1e-4, 7)  # what the run is not told: a damper, a noisy sensor


@pytest.fixture(scope="module")
def certified_on_robot(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A run certified on a simulated robot unlike the model, its resets off by up to 1e-3 per entry."""
    folder = tmp_path_factory.mktemp("on-robot")
    loop = robot_loop(simulated(HIDDEN, reset_spread=1e-3, seed=1), folder / "run.sqlite", CERTIFYING_HORIZON)
    try:
        result = loop.run(200)
    finally:
        loop.store.close()  # type: ignore[union-attr]
    assert result.certified, "the lqr robot run did not certify in 200 episodes"
    return folder


def test_the_certificate_names_the_robot_and_rests_on_no_model(certified_on_robot: Path) -> None:
    run = read_run(certified_on_robot)
    cert = run.certificate
    assert cert is not None and cert.proven and run.on_robot
    assert "P_(s0~this robot's resets)[" in cert.statement
    assert "model fingerprint" in cert.statement and "episodes a fault cut short" in cert.statement
    words = " ".join(cert.assumptions)
    assert "deterministic" not in words and "robot itself" in words and "drifts" in words
    assert "damping" not in cert.statement  # the robot's hidden parameters are nobody's but the robot's
    checks = [k for k in run.robot_episodes if k.role == "check"]
    assert len(checks) == cert.episodes - 1  # every episode but the first (no policy yet) was the robot's own
    assert all(row.initial_state == k.start for row, k in zip(run.episodes[1:], checks, strict=True))


def test_a_run_on_a_robot_is_played_back_by_the_gate_and_an_edit_sealed_again_is_refused(
    certified_on_robot: Path, tmp_path: Path
) -> None:
    run = read_run(certified_on_robot)
    fingerprint = RobotIdentity.from_record(run.metadata.robot_run).fingerprint
    deployment = load_deployment(certified_on_robot, Acceptance(model_fingerprint=fingerprint))  # re-derives it
    assert deployment.derived.startswith("derived again")
    with pytest.raises(GateRefusal, match="certified on the robot itself"):
        load_deployment(certified_on_robot, Acceptance(model_fingerprint="f" * 64, rederive=False))
    check = next(k for k in run.robot_episodes if k.role == "check" and k.success)
    states, actions, rewards = check.arrays(4, 1)
    actions[10, 0] += 0.25  # a command the policy did not give
    edits = {
        "a check's success": (("UPDATE robot_episodes SET success = 0 WHERE id = ?", (check.id,)), "success"),
        "a command": (("UPDATE robot_episodes SET rollout = ? WHERE id = ?",
                       (RobotEpisode.pack(states, actions, rewards), check.id)), "the policy commands"),
        "a start": (("UPDATE episodes SET initial_state = ? WHERE episode = ?", ("[0.1, 0.1, 0.0, 0.0]", 3)),
                    "episode 3"),
    }  # fmt: skip
    for k, (edit, named) in enumerate(edits.values()):
        folder = altered_copy(certified_on_robot, tmp_path / f"edit{k}", edit, resealed=True)
        with pytest.raises(GateRefusal, match="does not follow from its own seed") as refusal:
            load_deployment(folder, Acceptance(model_fingerprint=fingerprint))
        assert named in str(refusal.value), (named, str(refusal.value))


def test_a_run_on_a_robot_resumes_only_on_that_robot(tmp_path: Path) -> None:
    path = tmp_path / "run.sqlite"
    loop = robot_loop(simulated(), path)
    loop.run(2)
    loop.store.close()  # type: ignore[union-attr]
    other = RobotIdentity(fingerprint="0" * 64)
    with pytest.raises(RunFileError, match="robot_run"):
        build_robot_loop(resolved().config, resolved().expert, simulated(), other, store_path=path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(RunFileError, match="robot_run"):
            build_loop(resolved().config, resolved().expert, store_path=path)  # the model run is another run


def test_what_a_run_on_a_robot_cannot_be_is_refused_before_the_robot_moves() -> None:
    link = simulated()
    for given, reason in (
        ({"certify": "oracle"}, "success claim only"),
        ({"explore": 0.2}, "does not explore"),
        ({"policy_lipschitz": "select"}, "chooses no policy L from its data"),
    ):
        request = RunRequest(task=TASK, seed=0, horizon=HORIZON, **({"certify": "success"} | given))  # type: ignore[arg-type]
        with pytest.raises(ValueError, match=reason):
            build_robot_loop(resolve_run(request).config, resolve_run(request).expert, link, identity())
    assert link.resets == 0
    with pytest.raises(ValueError, match="fingerprint"):
        RobotIdentity(fingerprint="")
    with pytest.raises(ValueError, match="starts must be one of"):
        RobotIdentity(fingerprint="ab", starts="anywhere")  # type: ignore[arg-type]


def test_a_run_on_a_robot_may_start_from_another_runs_data_which_are_data_never_checks(tmp_path: Path) -> None:
    """Started from a run certified on the model: its trajectories are the robot run's first data (stored, named in
    the record and the certificate, never counted as the run's expert calls or checks), and the first episode is
    already a check of the policy over them; the run resumes, and the gate plays it back."""
    model = build_loop(resolved(CERTIFYING_HORIZON).config, resolved(CERTIFYING_HORIZON).expert,
                       store_path=tmp_path / "model" / "run.sqlite")  # fmt: skip
    model.run(200)
    model.store.close()  # type: ignore[union-attr]
    assert model.certificate is not None
    path = tmp_path / "robot" / "run.sqlite"
    start = {"prior_run": tmp_path / "model"}
    loop = robot_loop(simulated(HIDDEN), path, CERTIFYING_HORIZON, **start)
    first = loop.run_episode()
    assert first.policy_success is not None and loop.oracle_calls == int(first.oracle_called)
    loop.store.close()  # type: ignore[union-attr]
    again = robot_loop(simulated(HIDDEN), path, CERTIFYING_HORIZON, **start)
    assert again.run(200).certified
    again.store.close()  # type: ignore[union-attr]
    run = read_run(path.parent)
    said = json.loads(run.metadata.prior)
    assert said["trajectories"] == model.certificate.policy_trajectories and said["certified"]
    assert f"began with {said['trajectories']} trajectories of the certified run model" in run.certificate.statement  # type: ignore[union-attr]
    assert run.dataset.num_trajectories == said["trajectories"] + sum(r.trajectories_stored for r in run.episodes)
    assert rederive(run).agrees
    with pytest.raises(RunFileError, match="prior"):  # resumed without its start is another run
        robot_loop(simulated(HIDDEN), path, CERTIFYING_HORIZON)
