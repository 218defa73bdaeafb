"""npp-deploy's core (npp_ros/deploy.py), without ROS: the gate on real run folders, the robot's joints, the
command limits, coverage and the watchdog."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from deploy_runs import FINGERPRINT, HORIZON, SEED, TASK, altered_copy, bad_folders, edited_certificate, make_run

from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.run.deploy import (
    Acceptance,
    CommandLimits,
    Coverage,
    GateRefusal,
    JointLayout,
    NonFiniteState,
    RobotStateError,
    Watchdog,
    check_command_interface,
    load_deployment,
    parse_vector,
    safe_command,
    stored_state,
)
from npp_ros.run.store import RunStore
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.rollout import rollout

ACCEPT = Acceptance(model_fingerprint=FINGERPRINT)


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, tuple[Path, str]]]:
    root = tmp_path_factory.mktemp("deploy-runs")
    good = make_run(root / "good")
    return good, bad_folders(good, root)


def test_a_certified_run_deploys_exactly_the_policy_its_certificate_names(runs) -> None:
    good, _ = runs
    deployment = load_deployment(good, ACCEPT)
    with RunStore.open(good / "run.sqlite") as store:
        certificate, dataset = store.certificate(), store.load_dataset()
    assert certificate is not None and certificate["proven"]
    count = certificate["policy_trajectories"]
    assert count < dataset.num_trajectories  # the run stored more than the certified policy uses
    assert deployment.policy_trajectories == count and deployment.overridden == ()
    prefix = NonparametricPolicy(dataset.prefix(count), certificate["lipschitz"])
    s0 = get_task(TASK).initial_state(SEED, 1000)
    plant = get_task(TASK).make_plant(SEED)
    want = rollout(plant, prefix.act, s0, HORIZON)
    got = rollout(plant, deployment.policy.act, s0, HORIZON)
    np.testing.assert_array_equal(got.actions, want.actions)
    assert "proven" in deployment.describe() and f"greedy over {count} trajectories" in deployment.describe()


@pytest.mark.parametrize(
    "case", ["missing", "uncertified", "not proven", "altered data", "altered certificate", "deleted certificate"]
)
def test_the_gate_refuses_each_bad_folder_with_its_reason(runs, case: str) -> None:
    _, bad = runs
    folder, reason = bad[case]
    with pytest.raises(GateRefusal, match=reason):
        load_deployment(folder, ACCEPT)


def test_an_edit_of_both_the_run_and_its_certificate_does_not_follow_from_the_episode_log(runs, tmp_path) -> None:
    good, _ = runs
    loose = edited_certificate(good, tmp_path / "a", epsilon=0.5)
    both = altered_copy(loose, tmp_path / "b", ("UPDATE meta SET value = '0.5' WHERE key = 'epsilon'", ()))
    with pytest.raises(GateRefusal, match="does not follow from the run's own log"):
        load_deployment(both, ACCEPT)
    more = edited_certificate(good, tmp_path / "c", policy_trajectories=3)
    with pytest.raises(GateRefusal, match="altered"):
        load_deployment(more, ACCEPT)


def test_a_hand_edited_run_file_is_refused_with_a_reason_not_a_traceback(runs, tmp_path) -> None:
    good, _ = runs
    garbled = edited_certificate(good, tmp_path / "a", episodes="many")
    without = altered_copy(good, tmp_path / "b", ("DELETE FROM meta WHERE key = 'epsilon'", ()))
    missing = edited_certificate(good, tmp_path / "c", window=None)
    for folder in (garbled, without, missing):
        with pytest.raises(GateRefusal, match="altered"):
            load_deployment(folder, ACCEPT)


def test_the_gate_refuses_a_weaker_certificate_than_the_operator_accepts(runs) -> None:
    good, _ = runs
    with pytest.raises(GateRefusal, match=r"epsilon 2 is larger than this deployment accepts \(max_epsilon 1\)"):
        load_deployment(good, Acceptance(max_epsilon=1.0, model_fingerprint=FINGERPRINT))
    with pytest.raises(GateRefusal, match=r"p 0.9 is below min_p 0.95"):
        load_deployment(good, Acceptance(min_p=0.95, model_fingerprint=FINGERPRINT))
    with pytest.raises(GateRefusal, match=r"delta 0.1 is larger .* \(max_delta 0.05\)"):
        load_deployment(good, Acceptance(max_delta=0.05, model_fingerprint=FINGERPRINT))
    load_deployment(good, Acceptance(max_epsilon=2.0, min_p=0.9, max_delta=0.1, model_fingerprint=FINGERPRINT))


def test_the_gate_refuses_a_robot_without_the_certified_model(runs) -> None:
    good, _ = runs
    with pytest.raises(GateRefusal, match="no robot model fingerprint was given"):
        load_deployment(good, Acceptance())
    other = get_task(TASK).make_plant(SEED + 1).model_sha256()
    with pytest.raises(GateRefusal, match=f"fingerprint {other[:12]}.*is not the certified one"):
        load_deployment(good, Acceptance(model_fingerprint=other))


def test_an_override_passes_the_certificate_checks_and_keeps_every_reason(runs) -> None:
    good, bad = runs
    folder, _ = bad["uncertified"]
    deployment = load_deployment(folder, Acceptance(override=True))
    assert any("no certificate" in r for r in deployment.overridden)
    assert any("no robot model fingerprint" in r for r in deployment.overridden)
    with RunStore.open(folder / "run.sqlite") as store:
        assert deployment.policy_trajectories == store.num_trajectories()  # no certificate: all the data
    assert "NO certificate" in deployment.describe()
    weak = load_deployment(good, Acceptance(max_epsilon=1.0, model_fingerprint=FINGERPRINT, override=True))
    assert len(weak.overridden) == 1 and weak.policy_trajectories == load_deployment(good, ACCEPT).policy_trajectories


def test_no_override_deploys_data_that_fail_their_checksums(runs) -> None:
    _, bad = runs
    folder, _ = bad["altered data"]
    with pytest.raises(GateRefusal, match="altered or damaged"):
        load_deployment(folder, Acceptance(override=True))


def test_the_acceptance_limits_are_checked() -> None:
    for bad in ({"max_epsilon": 0.0}, {"min_p": 1.0}, {"max_delta": 0.0}, {"max_delta": 1.5}):
        with pytest.raises(ValueError):
            Acceptance(**bad)


# ----------------------------------------------------------------------------- joints and commands
def test_a_joint_state_is_assembled_by_name_whatever_its_order_and_extra_joints() -> None:
    plant = get_task("lqr_6_2").make_plant(0)
    layout = JointLayout.of_plant(plant, ("joint_1", "joint_0"))
    names = ["gripper", *reversed(plant.joint_names)]
    positions = [9.0, *[float(10 + i) for i in reversed(range(6))]]
    velocities = [8.0, *[float(20 + i) for i in reversed(range(6))]]
    state = layout.state(names, positions, velocities)
    np.testing.assert_array_equal(state, [10, 11, 12, 13, 14, 15, 20, 21, 22, 23, 24, 25])
    np.testing.assert_array_equal(layout.command([1.0, 2.0]), [2.0, 1.0])  # the controller's order
    np.testing.assert_array_equal(layout.action(layout.command([1.0, 2.0])), [1.0, 2.0])
    np.testing.assert_array_equal(layout.hold(state), [11.0, 10.0])


def test_bad_joint_states_are_refused_with_the_joints_at_fault() -> None:
    layout = JointLayout.of_plant(get_task("lqr_2_1").make_plant(0))
    with pytest.raises(RobotStateError, match=r"lacks the task's joints joint_1 \(it names: joint_0, elbow\)"):
        layout.state(["joint_0", "elbow"], [0.0, 0.0], [0.0, 0.0])
    with pytest.raises(RobotStateError, match="2 joints but has 1 positions and 2 velocities"):
        layout.state(["joint_0", "joint_1"], [0.0], [0.0, 0.0])
    with pytest.raises(RobotStateError, match="names joint_0 more than once"):
        layout.state(["joint_0", "joint_0", "joint_1"], [0.0] * 3, [0.0] * 3)
    with pytest.raises(NonFiniteState, match="joint_1 velocity = nan"):
        layout.state(["joint_1", "joint_0"], [0.0, 0.0], [float("nan"), 0.0])
    with pytest.raises(RobotStateError, match=r"\(it names: none\)"):
        layout.state([], [], [])
    np.testing.assert_array_equal(layout.state(["joint_1", "joint_0"], [2.0, 1.0], [4.0, 3.0]), [1, 2, 3, 4])


def test_command_joints_must_be_the_actuated_ones() -> None:
    plant = get_task("lqr_6_2").make_plant(0)
    with pytest.raises(ValueError, match="must be the task's actuated joints"):
        JointLayout.of_plant(plant, ("joint_0", "joint_5"))


def test_commands_are_clamped_to_the_model_limits_and_the_effort_limit() -> None:
    pendulum = get_task("pendulum_swingup").make_plant(0)  # ctrlrange [-1, 1]
    limits = CommandLimits.of_plant(pendulum)
    assert limits.clamp(np.array([3.0])) == (pytest.approx([1.0]), 1)
    assert limits.clamp(np.array([0.5]))[1] == 0
    lqr = get_task("lqr_6_2").make_plant(0)  # not limited
    assert CommandLimits.of_plant(lqr).clamp(np.array([1e6, -1e6]))[1] == 0
    assert "not limited" in CommandLimits.of_plant(lqr).describe()
    clamped, count = CommandLimits.of_plant(lqr, effort_limit=2.0).clamp(np.array([5.0, -1.0]))
    np.testing.assert_array_equal(clamped, [2.0, -1.0])
    assert count == 1
    np.testing.assert_array_equal(CommandLimits.of_plant(pendulum, effort_limit=0.5).high, [0.5])


def test_the_safe_command_is_zero_effort_or_the_present_position_held() -> None:
    plant = get_task("lqr_6_2").make_plant(0)
    layout = JointLayout.of_plant(plant, ("joint_1", "joint_0"))
    np.testing.assert_array_equal(safe_command("effort", layout, None), [0.0, 0.0])
    raw = np.arange(12, dtype=np.float64)
    np.testing.assert_array_equal(safe_command("position", layout, raw), [1.0, 0.0])
    with pytest.raises(RobotStateError, match="no position to hold"):
        safe_command("position", layout, None)


def test_the_command_interface_must_fit_the_certified_actions() -> None:
    plant = get_task("lqr_2_1").make_plant(0)
    check_command_interface(plant, "effort")
    with pytest.raises(ValueError, match="certified actions are efforts"):
        check_command_interface(plant, "position")
    with pytest.raises(ValueError, match="must be one of"):
        check_command_interface(plant, "velocity")


def test_the_pendulum_state_is_stored_with_its_angle_wrapped() -> None:
    plant = get_task("pendulum_swingup").make_plant(0)
    np.testing.assert_allclose(stored_state(plant, np.array([2 * np.pi + 0.5, 1.0])), [0.5, 1.0])
    lqr = get_task("lqr_2_1").make_plant(0)
    np.testing.assert_array_equal(stored_state(lqr, np.array([5.0, 1.0, 2.0, 3.0])), [5.0, 1.0, 2.0, 3.0])


def test_coverage_measures_the_distance_to_the_policy_data(runs) -> None:
    good, _ = runs
    deployment = load_deployment(good, ACCEPT)
    coverage = Coverage.of_deployment(deployment)
    starts = deployment.checked_starts
    assert len(starts) > 0 and coverage.radius == pytest.approx(coverage.farthest_start(starts)) and coverage.radius > 0
    data = {tuple(row) for row in deployment.policy.dataset.states}
    assert not any(tuple(s0) in data for s0 in starts)  # the policy's own trajectories start elsewhere
    assert coverage.covers(deployment.policy.dataset.states[5]) == (True, 0.0)
    far = deployment.policy.dataset.states[5] + np.array([0.0, 0.0, 100.0, 0.0])
    inside, distance = coverage.covers(far)
    assert not inside and distance > 50
    assert Coverage.of_deployment(deployment, radius=200.0).covers(far)[0]
    # Near a given data point no search is needed; far from it the search decides.
    near = deployment.policy.dataset.states[5]
    assert coverage.covers(near + 1e-3, near) == (True, pytest.approx(2e-3))
    assert coverage.covers(far, near) == (False, pytest.approx(distance))
    assert coverage.covers(deployment.policy.dataset.states[7], far) == (True, 0.0)


def test_parse_vector_refuses_what_is_not_a_state() -> None:
    np.testing.assert_array_equal(parse_vector("1, 2,3", 3, "s0"), [1, 2, 3])
    for text in ("1,2", "1,2,x", "1,nan,3"):
        with pytest.raises(ValueError, match="s0 must be 3"):
            parse_vector(text, 3, "s0")


# ----------------------------------------------------------------------------- watchdog
def test_the_watchdog_fires_once_after_the_timeout_and_again_after_states_resume() -> None:
    fired: list[float] = []
    event = threading.Event()

    def expire(age: float) -> None:
        fired.append(age)
        event.set()

    watchdog = Watchdog(0.05, expire)
    try:
        time.sleep(0.12)
        assert fired == []  # not armed: not watching
        armed_at = time.monotonic()
        watchdog.arm()
        assert event.wait(10.0)
        assert time.monotonic() - armed_at >= 0.05 and fired[0] >= 0.05
        assert watchdog.expired
        time.sleep(0.12)
        assert len(fired) == 1  # once per expiry
        assert watchdog.feed() is True  # states flow again
        assert not watchdog.expired
        event.clear()
        assert event.wait(10.0) and len(fired) == 2
        watchdog.disarm()
        watchdog.feed()
        time.sleep(0.12)
        assert len(fired) == 2
    finally:
        watchdog.close()


def test_a_fed_watchdog_does_not_fire() -> None:
    fired: list[float] = []
    watchdog = Watchdog(0.5, fired.append)
    try:
        watchdog.arm()
        for _ in range(10):
            watchdog.feed()
            time.sleep(0.01)
        assert fired == []
    finally:
        watchdog.close()


def test_run_files_record_what_the_gate_reads(runs) -> None:
    good, _ = runs
    with RunStore.open(good / "run.sqlite") as store:
        assert store.metadata.plant_fingerprint == FINGERPRINT
        assert json.dumps(store.certificate())  # a plain record


def test_a_mixture_rule_certificate_deploys_its_policy_and_an_edited_one_is_refused(tmp_path) -> None:
    run = make_run(tmp_path / "mixture", rule="mixture", max_episodes=1000)
    with RunStore.open(run / "run.sqlite") as store:
        certificate = store.certificate()
    assert certificate is not None and certificate["rule"] == "mixture" and certificate["proven"]
    assert load_deployment(run, ACCEPT).policy_trajectories == certificate["policy_trajectories"]
    for name, value in (("failures", certificate.get("failures", 0) + 1), ("policy_trajectories", 2)):
        with pytest.raises(GateRefusal, match="altered"):
            load_deployment(edited_certificate(run, tmp_path / name, **{name: value}), ACCEPT)
