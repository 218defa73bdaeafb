"""Message <-> core conversions on their own, without DDS: round trips, and bad input refused with the reason."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from geometry_msgs.msg import Point, PointStamped
from npp_interfaces.msg import Certificate as CertificateMsg
from npp_interfaces.srv import ExpertTrajectory, ResetEpisode
from sensor_msgs.msg import JointState

from npp_ros.certificate.certifier import Certificate, CertificationSpec, CertificationStatus
from npp_ros.policy.dataset import DatasetError, Trajectory
from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.run.loop import Observer
from npp_ros.run.progress import progress_text, status_text
from npp_ros.run.records import EpisodeOutcome, EpisodeRow, GapRecord, PlantRecord
from npp_ros.run.setup import build_config, build_loop, resolve_lipschitz
from npp_ros.tasks.builtin.lqr import LQRExpert
from npp_ros.tasks.uncertainty import Robot
from npp_ros_graph.tools.dashboard import Hub, episode_entry, load_run
from npp_ros_graph.transport.convert import (
    CERTIFICATE_RENAMED,
    MessageError,
    action_from_joint_state,
    action_to_joint_state,
    certificate_from_msg,
    certificate_to_msg,
    episode_from_msg,
    episode_result,
    gap_from_msg,
    gap_report,
    plant_description,
    plant_from_msg,
    point_from_msg,
    recorded_records,
    robot_from_field,
    robot_to_field,
    rollout_result,
    stamp,
    stamp_ns,
    state_from_joint_state,
    state_to_joint_state,
    trajectory_from_msg,
    trajectory_from_response,
    trajectory_to_msg,
    trajectory_to_response,
)

JOINTS = ["joint_0", "joint_1"]
ACTUATED = ["joint_0"]


@pytest.fixture(scope="module")
def trajectory() -> Trajectory:
    return LQRExpert("lqr_2_1", 0, horizon=20).trajectory(np.array([0.3, -0.2, 0.1, 0.0]))


def assert_same(a: Trajectory, b: Trajectory) -> None:
    for name in ("states", "actions", "values"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_trajectory_round_trips_through_the_topic_message(trajectory: Trajectory) -> None:
    index, back = trajectory_from_msg(trajectory_to_msg(7, trajectory))
    assert index == 7
    assert_same(back, trajectory)


def test_trajectory_round_trips_through_the_expert_response(trajectory: Trajectory) -> None:
    response = trajectory_to_response(trajectory, ExpertTrajectory.Response())
    back = trajectory_from_response(response)
    assert_same(back, trajectory)
    assert trajectory.expert_return is not None and back.expert_return == trajectory.expert_return
    assert response.state_dim == 4 and response.action_dim == 1


def test_an_unknown_expert_return_travels_as_nan(trajectory: Trajectory) -> None:
    unknown = Trajectory(trajectory.states, trajectory.actions, trajectory.values)
    response = trajectory_to_response(unknown, ExpertTrajectory.Response())
    assert math.isnan(response.expert_return)
    assert trajectory_from_response(response).expert_return is None


@pytest.mark.parametrize(
    ("change", "fragment"),
    [
        ({"state_dim": 3}, "do not fit"),
        ({"action_dim": 0}, "do not fit"),
        ({"values": [1.0]}, "do not fit"),
        ({"states": [math.nan] + [0.0] * 79}, "must be finite"),
    ],
)
def test_a_trajectory_message_that_does_not_fit_is_refused(
    trajectory: Trajectory, change: dict[str, object], fragment: str
) -> None:
    msg = trajectory_to_msg(0, trajectory)
    for name, value in change.items():
        setattr(msg, name, value)
    with pytest.raises(DatasetError, match=fragment):
        trajectory_from_msg(msg)


def test_state_round_trips_through_joint_state() -> None:
    x = np.array([0.1, -0.2, 0.3, -0.4])
    msg = state_to_joint_state(x, JOINTS, stamp(1_500_000_000))
    assert list(msg.position) == [0.1, -0.2] and list(msg.velocity) == [0.3, -0.4] and list(msg.name) == JOINTS
    assert stamp_ns(msg.header.stamp) == 1_500_000_000
    np.testing.assert_array_equal(state_from_joint_state(msg, JOINTS), x)
    msg.name = []  # names are optional
    np.testing.assert_array_equal(state_from_joint_state(msg, JOINTS), x)


@pytest.mark.parametrize(
    ("msg", "error", "fragment"),
    [
        (JointState(name=["a", "b"], position=[0.0, 0.0], velocity=[0.0, 0.0]), MessageError, "wrong joint names"),
        (JointState(position=[0.0], velocity=[0.0, 0.0]), MessageError, "wrong joint count"),
        (JointState(position=[0.0, math.nan], velocity=[0.0, 0.0]), ValueError, r"state\[1\] = nan"),
        (JointState(position=[0.0, 0.0], velocity=[math.inf, 0.0]), ValueError, r"state\[2\] = inf"),
    ],
)
def test_a_bad_state_message_is_refused_with_the_reason(msg: JointState, error: type, fragment: str) -> None:
    with pytest.raises(error, match=fragment):
        state_from_joint_state(msg, JOINTS)


def test_action_round_trips_through_joint_state() -> None:
    msg = action_to_joint_state(np.array([0.25]), ACTUATED, stamp(30_000_000))
    assert list(msg.effort) == [0.25] and list(msg.name) == ACTUATED and msg.header.stamp.nanosec == 30_000_000
    np.testing.assert_array_equal(action_from_joint_state(msg, ACTUATED), [0.25])


@pytest.mark.parametrize(
    ("msg", "fragment"),
    [
        (JointState(name=["joint_1"], effort=[0.1]), "wrong joint names"),
        (JointState(effort=[0.1, 0.2]), "effort has 2 entries, expected 1"),
        (JointState(effort=[]), "effort is empty"),
        (JointState(effort=[-math.inf]), r"effort must be finite: effort\[0\] = -inf"),
    ],
)
def test_a_bad_action_message_is_refused_with_the_reason(msg: JointState, fragment: str) -> None:
    with pytest.raises(ValueError, match=fragment):
        action_from_joint_state(msg, ACTUATED)


def test_a_target_point_is_read_in_its_frame_and_one_in_another_frame_is_refused() -> None:
    msg = PointStamped(point=Point(x=0.25, y=-0.5, z=math.nan))  # finiteness is the target box's to judge
    msg.header.frame_id = "world"
    np.testing.assert_array_equal(point_from_msg(msg, "world"), [0.25, -0.5, math.nan])
    with pytest.raises(MessageError, match=r"target \(0.25, -0.5, nan\) is in frame 'world', not 'map': give it in"):
        point_from_msg(msg, "map")
    msg.header.frame_id = ""
    with pytest.raises(MessageError, match=r"in no frame \(header.frame_id empty\), not 'world'"):
        point_from_msg(msg, "world")


def test_plant_description_names_the_plant() -> None:
    plant = LQRExpert("lqr_2_1", 3).plant
    desc = plant_description(plant, 3, 200)
    assert (desc.task, desc.seed, desc.horizon, desc.state_dim, desc.action_dim) == ("lqr_2_1", 3, 200, 4, 1)
    assert list(desc.joint_names) == plant.joint_names and desc.model_sha256 == plant.model_sha256()


def row(**changes: object) -> EpisodeRow:
    base = dict(
        episode=4, initial_state=(0.1, 0.2, 0.3, 0.4), v_lb=900.0, v_ub=950.0, gap=50.0, oracle_called=True,
        trajectory=2, dataset_size=3000, oracle_calls=3, quiet_episodes=0, window=0, required=22, certified=False,
    )  # fmt: skip
    return EpisodeRow(**{**base, **changes})  # type: ignore[arg-type]


def test_gap_report_and_episode_result_carry_the_row() -> None:
    r = row(expert_value=970.0, policy_return=960.5, checked_gap=12.5, test=2, test_delta=0.1 / 6)
    config = build_config("lqr_2_1", 0, LipschitzConstant(263.3, "user"), 50.0, certify="oracle")
    gap = gap_report(r, config, stamp(0))
    assert (gap.episode, gap.v_lb, gap.v_ub, gap.gap, gap.epsilon) == (4, 900.0, 950.0, 50.0, 50.0)
    assert (gap.oracle_called, gap.dataset_size, gap.oracle_calls, gap.quiet_required, gap.condition) == (
        True, 3000, 3, 22, "i",
    )  # fmt: skip
    assert (gap.certify, gap.checked_gap, gap.test, gap.test_delta) == ("oracle", 12.5, 2, 0.1 / 6)
    assert list(gap.initial_state) == [0.1, 0.2, 0.3, 0.4]
    result = episode_result(r, 1000, stamp(0))
    assert (result.policy_return, result.steps, result.expert_value_known, result.expert_value) == (
        960.5, 1000, True, 970.0,
    )  # fmt: skip


def test_an_episode_the_policy_did_not_drive_reports_nan_and_no_steps() -> None:
    result = episode_result(row(), 1000, stamp(0))
    assert math.isnan(result.policy_return) and result.steps == 0 and not result.expert_value_known


ROBOT = Robot((("mass", "pole", 1.1), ("gear", "torque", 0.85)), action_delay=1, state_noise=0.02, noise_seed=42)


def test_a_robot_round_trips_through_the_reset_the_expert_request_and_the_rollout_report() -> None:
    """The one text form (Robot.record) in every message that names an episode's robot; '' is the nominal model."""
    reset = ResetEpisode.Request(state=[0.1, 0.2], episode=3, run="r", robot=robot_to_field(ROBOT))
    request = ExpertTrajectory.Request(state=[0.1, 0.2], run="r", robot=robot_to_field(ROBOT))
    report = rollout_result(3, 12.5, 80, [0.1, 0.2], stamp(0), ROBOT)
    for field in (reset.robot, request.robot, report.robot):
        assert robot_from_field(field) == ROBOT
    assert robot_to_field(None) == "" and robot_from_field("") is None
    assert rollout_result(3, 12.5, 80, [0.1, 0.2], stamp(0)).robot == ""
    assert episode_result(row(robot=ROBOT.record()), 80, stamp(0)).robot == ROBOT.record()
    assert episode_result(row(), 80, stamp(0)).robot == ""


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("{not json", "not a robot record"),
        ('{"scales": []}', "KeyError"),
        (ROBOT.record().replace("1.1", "-1.1"), "mass"),
    ],
)
def test_a_damaged_robot_field_is_refused_with_the_reason(text: str, fragment: str) -> None:
    with pytest.raises(MessageError, match=r"^robot: ") as err:
        robot_from_field(text)
    assert fragment in str(err.value)


def test_every_certificate_field_reaches_the_message() -> None:
    """Every entry of the certificate's record is carried (or named here as not carried)."""
    not_carried = {"task", "rule"}  # the message is per run and names no task; the rule shows in the statement
    lipschitz = LipschitzConstant(263.3, "lqr-analytic", margin=0.01)
    cert = Certificate(
        task="lqr_2_1", spec=CertificationSpec("i", 50.0, 0.9, 0.1, lipschitz, certify="oracle"), episodes=178,
        oracle_calls=52, dataset_size=52000, policy_trajectories=40, window=22, required=22, test=3,
        delta_spent=0.1 / 12, value="the return", statement="claim", proven=True, assumptions=("one", "two"),
    )  # fmt: skip
    msg = certificate_to_msg(cert, stamp(0))
    message_fields = set(CertificateMsg.get_fields_and_field_types())
    for name, expected in cert.record().items():
        if name in not_carried:
            continue
        target = CERTIFICATE_RENAMED.get(name, name)
        assert target in message_fields, f"the certificate's {name} has no message field"
        sent = getattr(msg, target)
        if expected is None:  # no value (the mixture statistic under another rule): NaN on the wire
            assert math.isnan(sent), name
            continue
        assert (list(sent) if isinstance(expected, list) else sent) == expected, name
    assert (msg.quiet_episodes, msg.lipschitz_margin, msg.quantity) == (22, 0.01, "V^E(s0) - R^pi(s0)")


def test_the_dashboard_reads_a_run_file_as_the_gap_reports_it_published(tmp_path: Path) -> None:
    """One episode entry for the page, whether it comes from /npp/gap or from run.sqlite: the same fields and values."""
    expert = LQRExpert("lqr_2_1", 0, horizon=50)
    lipschitz = resolve_lipschitz("lqr_2_1", "analytic", expert)
    config = build_config("lqr_2_1", 0, lipschitz, 50.0, horizon=50, certify="surrogate", rule="paper")
    loop = build_loop(config, expert, store_path=tmp_path / "run.sqlite")
    rows = loop.run(max_episodes=6).rows
    loop.store.close()
    hub = Hub("run", "file")
    load_run(tmp_path, hub)
    assert len(rows) == 6
    assert hub.state["episodes"] == [episode_entry(gap_from_msg(gap_report(row, config, stamp(0)))) for row in rows]


class Said(Observer):
    """npp-learn's progress line of each episode, as its StatusLine makes it from the loop's row and status."""

    def __init__(self, spec: CertificationSpec) -> None:
        self.spec, self.lines, self.rows = spec, [], []

    def on_episode(self, row: EpisodeRow, status: CertificationStatus) -> None:
        self.rows.append(row)
        self.lines.append(status_text(row, self.spec.epsilon, status, self.spec.condition, self.spec.certify))


def test_npp_runs_progress_line_of_a_gap_report_is_npp_learns_line_of_its_episode() -> None:
    """One formatter at both doors: the line npp-run prints of the record a gap report reads back as is the line
    npp-learn prints of the episode, counted from 1."""
    expert = LQRExpert("lqr_2_1", 0, horizon=20)
    config = build_config("lqr_2_1", 0, resolve_lipschitz("lqr_2_1", "analytic", expert), 50.0, horizon=20)
    said = Said(config.spec)
    build_loop(config, expert, observers=[said]).run(max_episodes=4)
    lines = [progress_text(gap_from_msg(gap_report(row, config, stamp(0)))) for row in said.rows]
    assert lines == said.lines and lines[0].startswith("episode     1 | ")
    assert lines[0].endswith(f"test {said.rows[0].test} streak 0/{said.rows[0].required}")


def test_a_plant_description_reads_back_as_the_plant_record() -> None:
    plant = LQRExpert("lqr_2_1", 3).plant
    record = plant_from_msg(plant_description(plant, 3, 200))
    assert isinstance(record, PlantRecord)
    assert (record.task, record.seed, record.horizon, record.state_dim, record.action_dim) == ("lqr_2_1", 3, 200, 4, 1)
    assert record.joint_names == tuple(plant.joint_names) and record.model_sha256 == plant.model_sha256()
    assert record.timestep == plant.dt and len(record.action_low) == len(record.action_high) == 1


def test_a_recording_reads_as_the_records_a_live_client_gets() -> None:
    """A bag's messages (type, message) become the records GraphClient gives: the certificate for the task of the
    plant described before it; a type that is no report is passed over."""
    expert = LQRExpert("lqr_2_1", 0, horizon=20)
    config = build_config("lqr_2_1", 0, resolve_lipschitz("lqr_2_1", "analytic", expert), 50.0, horizon=20)
    row = build_loop(config, expert).run(max_episodes=1).rows[0]
    lipschitz = LipschitzConstant(263.3, "lqr-analytic", margin=0.01)
    cert = Certificate(
        task="lqr_2_1", spec=CertificationSpec("i", 50.0, 0.9, 0.1, lipschitz), episodes=178, oracle_calls=52,
        dataset_size=52000, policy_trajectories=40, window=22, required=22, test=3, delta_spent=0.1 / 12,
        value="the return", statement="claim", proven=True, assumptions=("one",),
    )  # fmt: skip
    package = "npp_interfaces/msg/"
    recorded = [
        (package + "PlantDescription", plant_description(expert.plant, 0, 20)),
        (package + "GapReport", gap_report(row, config, stamp(0))),
        (package + "EpisodeResult", episode_result(row, 20, stamp(0))),
        ("std_msgs/msg/UInt32", object()),
        (package + "Certificate", certificate_to_msg(cert, stamp(0))),
    ]
    plant, gap, outcome, certificate = recorded_records(recorded)
    assert plant == plant_from_msg(recorded[0][1]) and gap == gap_from_msg(recorded[1][1])
    assert outcome == episode_from_msg(recorded[2][1]) and certificate == cert


@pytest.mark.parametrize("rule", ["sequential", "paper", "mixture"])
def test_a_certificate_message_reads_back_as_the_certificate_it_carries(rule: str) -> None:
    """GraphClient's certificate is the core type: the message's fields, the run's task, and the rule its statement
    or mixture statistic names."""
    lipschitz = LipschitzConstant(263.3, "lqr-analytic", margin=0.01)
    spec = CertificationSpec("i", 50.0, 0.9, 0.1, lipschitz, certify="rollout", rule=rule)  # type: ignore[arg-type]
    cert = Certificate(
        task="lqr_2_1", spec=spec, episodes=178, oracle_calls=52, dataset_size=52000, policy_trajectories=40,
        window=22, required=22, test=3, delta_spent=0.1 / 12, value="the return",
        statement=spec.statement(22, "the return", 40, 3, log_mixture=3.0), proven=True, assumptions=("one", "two"),
        mixture=20.1 if rule == "mixture" else None,
    )  # fmt: skip
    assert certificate_from_msg(certificate_to_msg(cert, stamp(0)), "lqr_2_1") == cert


def test_gap_and_episode_reports_read_back_as_core_records() -> None:
    expert = LQRExpert("lqr_2_1", 0, horizon=20)
    config = build_config("lqr_2_1", 0, resolve_lipschitz("lqr_2_1", "analytic", expert), 50.0, horizon=20)
    row = build_loop(config, expert).run(max_episodes=1).rows[0]
    gap = gap_from_msg(gap_report(row, config, stamp(0)))
    assert isinstance(gap, GapRecord)
    assert gap == GapRecord.of(row, epsilon=50.0, condition="i", certify=config.spec.certify)  # the row's record
    assert (gap.episode, gap.initial_state, gap.gap, gap.oracle_called, gap.epsilon) == (
        row.episode,
        tuple(row.initial_state),
        row.gap,
        row.oracle_called,
        50.0,
    )
    outcome = episode_from_msg(episode_result(row, 20, stamp(0)))
    assert isinstance(outcome, EpisodeOutcome) and outcome.policy_return == row.policy_return
    undriven = episode_from_msg(rollout_result(3, float("nan"), 0, [0.0] * 4, stamp(0)))
    assert (undriven.policy_return, undriven.expert_value, undriven.robot) == (None, None, "")


def test_a_runs_policy_round_trips_whole_through_the_dataset_answer() -> None:
    from npp_interfaces.msg import PolicySpec as PolicySpecMsg

    from npp_ros.policy.feedback import ControlSpace
    from npp_ros.policy.lipschitz import LipschitzConstant
    from npp_ros.policy.spec import PolicySpec
    from npp_ros_graph.transport.convert import policy_spec_from_msg, policy_spec_to_msg

    control = ControlSpace.of(4, (1,), [-1.0], [math.inf])
    control = ControlSpace(control.state_dim, control.angles, control.action_low, control.action_high, invariant=(0,))
    spec = PolicySpec("path", LipschitzConstant(263.3, "lqr-analytic", margin=1e-6), control)
    assert policy_spec_from_msg(policy_spec_to_msg(spec)) == spec
    weighted = PolicySpec("feedback", spec.lipschitz, ControlSpace.of(4, (1,), [-1.0], [1.0], weights=(1, 10, 1, 0.5)))
    assert policy_spec_from_msg(policy_spec_to_msg(weighted)) == weighted
    with pytest.raises(ValueError, match="names no policy"):
        policy_spec_from_msg(PolicySpecMsg())
    with pytest.raises(ValueError, match="the policy must be one of"):
        policy_spec_from_msg(PolicySpecMsg(kind="greedy", lipschitz=1.0, state_dim=4))
