"""npp-deploy's core (npp_ros/deployment/), without ROS: the gate on real run folders, the robot's joints, the
command limits, coverage, the watchdog, and the robot's model from its MJCF (robot_model.py)."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from deploy_runs import FINGERPRINT, HORIZON, SEED, TASK, altered_copy, bad_folders, edited_certificate, make_run

from npp_ros.certificate.certifier import Certificate
from npp_ros.deployment.commands import CommandLimits, check_command_interface, safe_command
from npp_ros.deployment.coverage import Coverage
from npp_ros.deployment.gate import Acceptance, GateRefusal, load_deployment
from npp_ros.deployment.joints import JointLayout, NonFiniteState, RobotStateError, parse_vector, stored_state
from npp_ros.deployment.robot_model import DescriptionError, described_fingerprint, mjcf_fingerprint, model_mjcf
from npp_ros.deployment.timing import Watchdog
from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.vectors import MAX_MAGNITUDE
from npp_ros.run.store import RunStore
from npp_ros.tasks.registry import TASK_NAMES, get_task
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


def test_a_feedback_run_deploys_its_feedback_policy_and_the_gate_refuses_another(tmp_path) -> None:
    run = make_run(tmp_path / "feedback", policy="feedback")
    deployment = load_deployment(run, ACCEPT)
    with RunStore.open(run / "run.sqlite") as store:
        certificate, dataset = store.certificate(), store.load_dataset()
    assert certificate is not None and certificate["policy"] == "feedback"
    assert deployment.policy.kind == "feedback" and "acting feedback" in deployment.describe()
    open_loop = NonparametricPolicy(dataset.prefix(certificate["policy_trajectories"]), certificate["lipschitz"])
    plant = get_task(TASK).make_plant(SEED)
    s0 = get_task(TASK).initial_state(SEED, 1000)
    expert = get_task(TASK).make_expert(SEED, HORIZON)
    got = rollout(plant, deployment.policy.act, s0, HORIZON)
    np.testing.assert_allclose(got.actions, rollout(plant, expert.action, s0, HORIZON).actions, rtol=1e-9, atol=1e-12)
    assert not np.array_equal(got.actions, rollout(plant, open_loop.act, s0, HORIZON).actions)
    with pytest.raises(GateRefusal, match="policy 'open-loop' against the run's 'feedback'"):
        load_deployment(edited_certificate(run, tmp_path / "edited", resealed=True, policy="open-loop"), ACCEPT)


@pytest.mark.parametrize(
    "case",
    [
        "missing",
        "uncertified",
        "not proven",
        "altered data",
        "altered certificate",
        "another policy",
        "deleted certificate",
    ],
)
def test_the_gate_refuses_each_bad_folder_with_its_reason(runs, case: str) -> None:
    _, bad = runs
    folder, reason = bad[case]
    with pytest.raises(GateRefusal, match=reason):
        load_deployment(folder, ACCEPT)


def test_a_run_file_without_a_certificate_is_not_said_to_be_never_certified(runs, tmp_path) -> None:
    """Resealed, the file cannot tell a run that never certified from a certificate removed afterwards: both are
    named (without resealing, the seal names the removal)."""
    good, bad = runs
    removed = altered_copy(
        good, tmp_path / "removed", ("DELETE FROM meta WHERE key = 'certificate'", ()), resealed=True
    )
    for folder in (removed, bad["uncertified"][0]):
        with pytest.raises(GateRefusal) as refusal:
            load_deployment(folder, ACCEPT)
        assert "the run file holds no certificate" in str(refusal.value)
        assert "never certified, or its certificate was removed" in str(refusal.value)


def test_an_edit_of_both_the_run_and_its_certificate_does_not_follow_from_the_episode_log(runs, tmp_path) -> None:
    """Even resealed by its editor (test_run_seal.py: the seal names any edit that is not), an edit the log
    contradicts is refused."""
    good, _ = runs
    loose = edited_certificate(good, tmp_path / "a", resealed=True, epsilon=0.5)
    edit = ("UPDATE meta SET value = '0.5' WHERE key = 'epsilon'", ())
    both = altered_copy(loose, tmp_path / "b", edit, resealed=True)
    with pytest.raises(GateRefusal, match="does not follow from the run's own log"):
        load_deployment(both, ACCEPT)
    more = edited_certificate(good, tmp_path / "c", resealed=True, policy_trajectories=3)
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


def test_only_what_the_run_file_cannot_give_is_reported_as_damage(runs, tmp_path, monkeypatch) -> None:
    """A file the store refuses (a dropped table, bytes that are no SQLite file) is damage; an error in the gate's
    own reading is a bug, raised as itself, and never told to the operator as a damaged file."""
    good, _ = runs
    dropped = altered_copy(good, tmp_path / "dropped", ("DROP TABLE episodes", ()))
    garbage = tmp_path / "garbage"
    garbage.mkdir()
    (garbage / "run.sqlite").write_bytes(b"not a run file" * 100)
    for folder in (dropped, garbage):
        with pytest.raises(GateRefusal, match="altered or damaged"):
            load_deployment(folder, ACCEPT)

    def broken_reader(record: object, spec: object) -> Certificate:
        raise TypeError("a bug in the certificate's reader")

    monkeypatch.setattr(Certificate, "from_record", broken_reader)
    with pytest.raises(TypeError, match="a bug in the certificate's reader"):
        load_deployment(good, ACCEPT)


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


@pytest.mark.parametrize("task", ["pendulum_swingup", "lqr_2_1"])
def test_a_first_joint_state_naming_no_joint_is_refused_like_any_other(task: str) -> None:
    """The layout caches where the task's joints are in the last message's names; before any message that cache
    is empty, and a first message naming no joints must not match it (it was taken as a valid, empty state)."""
    plant = get_task(task).make_plant(0)
    layout = JointLayout.of_plant(plant)
    for _ in range(2):  # the first one and the same again
        with pytest.raises(RobotStateError, match=r"lacks the task's joints .*\(it names: none\)"):
            layout.state([], [], [])
    partial = plant.joint_names[:-1]
    if partial:
        with pytest.raises(RobotStateError, match=f"lacks the task's joints {plant.joint_names[-1]}"):
            layout.state(partial, [0.0] * len(partial), [0.0] * len(partial))
    count = len(plant.joint_names)
    np.testing.assert_array_equal(layout.state(plant.joint_names, [0.5] * count, [0.25] * count),
                                  [0.5] * count + [0.25] * count)  # fmt: skip
    with pytest.raises(RobotStateError, match=r"\(it names: none\)"):
        layout.state([], [], [])


def test_a_joint_state_too_large_to_compare_with_the_data_is_refused_naming_the_joint() -> None:
    layout = JointLayout.of_plant(get_task("lqr_2_1").make_plant(0))
    with pytest.raises(RobotStateError, match=r"too large .*: joint_0 position = 1e\+200 \(entries must be within"):
        layout.state(["joint_0", "joint_1"], [1e200, 0.0], [0.0, 0.0])
    layout.state(["joint_0", "joint_1"], [MAX_MAGNITUDE, 0.0], [0.0, 0.0])  # the largest the policy compares


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


def test_no_safe_command_follows_a_fresh_one_that_came_while_the_watchdog_was_sending_it() -> None:
    """The expiry decision and the safe command are one step against fresh commands: a fresh command sent while
    the watchdog is deciding and sending waits for it, and goes out after the safe one, never before it."""
    sent: list[str] = []
    deciding, go_on = threading.Event(), threading.Event()
    outcome: list[str] = []

    def send_safe(age: float) -> None:
        deciding.set()
        go_on.wait(10.0)  # the safe command leaves late, as on a busy machine
        sent.append("safe")

    watchdog = Watchdog(0.05, send_safe)
    try:
        watchdog.arm()
        assert deciding.wait(10.0)
        fresh = threading.Thread(target=lambda: outcome.append(watchdog.send_fresh(lambda: sent.append("fresh"))))
        fresh.start()
        fresh.join(0.2)  # had the watchdog decided outside its lock, the fresh command would have gone out now
        go_on.set()
        fresh.join(10.0)
        assert sent == ["safe", "fresh"] and outcome == ["resumed"]
        assert not watchdog.expired
    finally:
        go_on.set()
        watchdog.close()


def test_no_fresh_command_follows_the_safe_one_sent_when_the_watchdog_is_disarmed() -> None:
    sent: list[str] = []
    after: list[float] = []
    watchdog = Watchdog(60.0, lambda age: sent.append("expired"), after.append)
    try:
        assert watchdog.send_fresh(lambda: sent.append("before arming")) == "disarmed"
        watchdog.arm()
        assert watchdog.send_fresh(lambda: sent.append("fresh")) == "sent"
        assert watchdog.disarm(lambda: sent.append("safe") or "safe sent") == "safe sent"
        assert watchdog.send_fresh(lambda: sent.append("late")) == "disarmed"
        assert sent == ["fresh", "safe"] and not watchdog.armed and after == []
    finally:
        watchdog.close()


def test_the_watchdog_reports_after_its_safe_command_outside_its_step() -> None:
    order: list[str] = []
    reported = threading.Event()
    watchdog = Watchdog(0.05, lambda age: order.append("safe"), lambda age: (order.append("report"), reported.set()))
    try:
        watchdog.arm()
        assert reported.wait(10.0)
        assert order == ["safe", "report"] and watchdog.fired == 1
    finally:
        watchdog.close()


# ----------------------------------------------------------------------------- the robot's model as MJCF
@pytest.mark.parametrize("task", [*TASK_NAMES, "examples/two_link_arm/task.toml"])
def test_a_plants_mjcf_compiles_alone_to_its_own_fingerprint(task: str) -> None:
    """What npp-robot publishes on /robot_description gives, compiled by npp-deploy, the plant's fingerprint."""
    path = Path(__file__).resolve().parents[1] / task
    plant = get_task(str(path) if path.is_file() else task).make_plant(0)
    mjcf = model_mjcf(plant)
    assert mjcf is not None and "<include" not in mjcf
    assert mjcf_fingerprint(plant, mjcf) == plant.model_sha256()


def test_another_models_mjcf_gives_another_fingerprint_and_garbage_does_not_compile(runs) -> None:
    good, _ = runs
    plant = get_task(TASK).make_plant(SEED)
    other = model_mjcf(get_task(TASK).make_plant(SEED + 1))  # lqr's stiffness is drawn from the seed
    assert other is not None
    assert mjcf_fingerprint(plant, other) == get_task(TASK).make_plant(SEED + 1).model_sha256() != FINGERPRINT
    own = model_mjcf(plant)
    assert own is not None and described_fingerprint(good, own) == FINGERPRINT  # the run's task, by its plant
    assert described_fingerprint(good / "run.sqlite", other) != FINGERPRINT
    assert described_fingerprint(good.parent / "nothing-here", own) is None  # the gate says why, not this
    for text in ("<robot name='arm'><link name='base'/>", "not xml at all", ""):
        with pytest.raises(DescriptionError, match="does not compile as a MuJoCo model"):
            mjcf_fingerprint(plant, text)


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
