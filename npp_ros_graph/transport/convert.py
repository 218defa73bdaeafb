"""Where a message becomes a core type and back: the only module that knows both.

Pure functions, no node and no DDS: a message class is an ordinary Python object here, so every
conversion is tested on its own (tests/ros/test_convert.py). Incoming data is checked on the way in;
anything malformed raises a :class:`ValueError` subclass (MessageError, VectorError, DatasetError)
whose message says what is wrong, which the nodes log or answer with.
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import replace
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PointStamped
from npp_interfaces.msg import Certificate as CertificateMsg
from npp_interfaces.msg import EpisodeResult, GapReport, PlantDescription
from npp_interfaces.msg import PolicySpec as PolicySpecMsg
from npp_interfaces.msg import Trajectory as TrajectoryMsg
from npp_interfaces.srv import ExpertTrajectory
from numpy.typing import ArrayLike
from sensor_msgs.msg import JointState

from npp_ros.certificate.certifier import Certificate, CertificationSpec
from npp_ros.policy.dataset import DatasetError, FloatArray, Trajectory
from npp_ros.policy.feedback import ControlSpace, check_policy_kind
from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.policy.spec import PolicySpec
from npp_ros.policy.vectors import finite_vector
from npp_ros.run.loop import RunConfig
from npp_ros.run.records import EpisodeOutcome, EpisodeRow, GapRecord, PlantRecord
from npp_ros.tasks.registry import Plant, control_space, get_task
from npp_ros.tasks.uncertainty import Robot

NS_PER_S = 1_000_000_000


class MessageError(ValueError):
    """A message whose structure does not fit the plant (joint names or counts)."""


def float64_array(values: ArrayLike) -> array[float]:
    """A float64 array.array: the fast path of rosidl's sequence setters (a list is checked item by item)."""
    out = array("d")
    out.frombytes(np.ascontiguousarray(values, dtype=np.float64).tobytes())
    return out


# ----------------------------------------------------------------------------- time
def stamp(nanoseconds: int) -> Time:
    return Time(sec=nanoseconds // NS_PER_S, nanosec=nanoseconds % NS_PER_S)


def stamp_ns(time: Time) -> int:
    return time.sec * NS_PER_S + time.nanosec


# ----------------------------------------------------------------------------- trajectories
def _trajectory(states: Sequence[float], actions: Sequence[float], values: Sequence[float],
                state_dim: int, action_dim: int, gains: Sequence[float] = ()) -> Trajectory:  # fmt: skip
    """Row-major message arrays -> a validated core Trajectory (raises DatasetError); empty gains: none."""
    steps = len(values)
    s = np.asarray(states, dtype=np.float64)
    a = np.asarray(actions, dtype=np.float64)
    if state_dim <= 0 or action_dim <= 0 or s.size != steps * state_dim or a.size != steps * action_dim:
        raise DatasetError(
            f"trajectory arrays do not fit: {steps} values, {s.size} state entries (state_dim {state_dim}), "
            f"{a.size} action entries (action_dim {action_dim})"
        )
    k = np.asarray(gains, dtype=np.float64) if len(gains) else None
    return Trajectory.validated(s.reshape(steps, state_dim), a.reshape(steps, action_dim), values, gains=k)


def _gains(trajectory: Trajectory) -> array[float]:
    return float64_array(() if trajectory.gains is None else trajectory.gains.ravel())


def trajectory_to_msg(
    index: int, trajectory: Trajectory, run: str = "", policy_lipschitz: float = 0.0
) -> TrajectoryMsg:
    """Trajectory `index` of the dataset of run `run` (its identity: see seal.py), with the L the run's policy acts
    by as it is sent (0: the policy spec's)."""
    return TrajectoryMsg(
        policy_lipschitz=float(policy_lipschitz),
        run=run,
        index=index,
        state_dim=trajectory.states.shape[1],
        action_dim=trajectory.actions.shape[1],
        states=float64_array(trajectory.states.ravel()),
        actions=float64_array(trajectory.actions.ravel()),
        values=float64_array(trajectory.values),
        gains=_gains(trajectory),
    )


def trajectory_from_msg(msg: TrajectoryMsg) -> tuple[int, Trajectory]:
    """(index, trajectory); raises DatasetError when the arrays do not fit the dimensions or are not finite."""
    return int(msg.index), _trajectory(msg.states, msg.actions, msg.values, msg.state_dim, msg.action_dim, msg.gains)


def trajectory_to_response(trajectory: Trajectory, response: ExpertTrajectory.Response) -> ExpertTrajectory.Response:
    """Fill an expert answer's arrays and return (success and message are the server's); NaN: return unknown."""
    response.expert_return = math.nan if trajectory.expert_return is None else trajectory.expert_return
    response.state_dim = trajectory.states.shape[1]
    response.action_dim = trajectory.actions.shape[1]
    response.states = float64_array(trajectory.states.ravel())
    response.actions = float64_array(trajectory.actions.ravel())
    response.values = float64_array(trajectory.values)
    response.gains = _gains(trajectory)
    return response


def trajectory_from_response(response: ExpertTrajectory.Response) -> Trajectory:
    traj = _trajectory(
        response.states, response.actions, response.values, response.state_dim, response.action_dim, response.gains
    )
    known = math.isfinite(response.expert_return)
    return replace(traj, expert_return=float(response.expert_return) if known else None)


# ----------------------------------------------------------------------------- states and actions
def _check_names(names: Sequence[str], expected: Sequence[str]) -> None:
    """Names are optional (empty), but when given they must be exactly the expected joints, in order."""
    if len(names) and list(names) != list(expected):
        raise MessageError(f"wrong joint names: {list(names)}, expected {list(expected)} (or none)")


def state_to_joint_state(state: ArrayLike, joint_names: Sequence[str], time: Time) -> JointState:
    """position = qpos, velocity = qvel (one entry per joint), stamp = the state's time."""
    bodies = len(joint_names)
    x = finite_vector(state, 2 * bodies, "state", f"qpos then qvel of {bodies} joints")
    msg = JointState(name=list(joint_names), position=float64_array(x[:bodies]), velocity=float64_array(x[bodies:]))
    msg.header.stamp = time
    return msg


def state_from_joint_state(msg: JointState, joint_names: Sequence[str]) -> FloatArray:
    """The state (qpos then qvel) a JointState carries, checked against the plant's joints."""
    _check_names(msg.name, joint_names)
    bodies = len(joint_names)
    if len(msg.position) != bodies or len(msg.velocity) != bodies:
        raise MessageError(
            f"wrong joint count: {len(msg.position)} positions and {len(msg.velocity)} velocities, "
            f"expected {bodies} each"
        )
    values = np.concatenate([np.asarray(msg.position, dtype=np.float64), np.asarray(msg.velocity, dtype=np.float64)])
    return finite_vector(values, 2 * bodies, "state")


def action_to_joint_state(action: ArrayLike, actuated_joint_names: Sequence[str], time: Time) -> JointState:
    """effort = the action, name = the actuated joints, stamp = the stamp of the state it answers."""
    return refill_action(JointState(name=list(actuated_joint_names)), action, time)


def refill_action(msg: JointState, action: ArrayLike, time: Time) -> JointState:
    """action_to_joint_state into a message built once: a publisher that answers every control step
    saves the JointState construction, which costs several times these two assignments."""
    msg.effort = float64_array(np.asarray(action, dtype=np.float64))
    msg.header.stamp = time
    return msg


def action_from_joint_state(msg: JointState, actuated_joint_names: Sequence[str]) -> FloatArray:
    """The action (effort) a JointState carries, checked against the plant's actuated joints."""
    _check_names(msg.name, actuated_joint_names)
    joints = list(actuated_joint_names)
    return finite_vector(msg.effort, len(joints), "effort", f"one per actuated joint {joints}")


def point_from_msg(msg: PointStamped, frame: str) -> FloatArray:
    """The point a PointStamped carries, given in ``frame``; a MessageError naming both frames for a point in
    another (or in none): no transform is looked up, a point is the model's world coordinates or refused."""
    point = np.array([msg.point.x, msg.point.y, msg.point.z], dtype=np.float64)
    given = msg.header.frame_id
    if given != frame:
        named = f"in frame {given!r}" if given else "in no frame (header.frame_id empty)"
        raise MessageError(f"target {tuple(point.tolist())} is {named}, not {frame!r}: give it in {frame!r}")
    return point


# ----------------------------------------------------------------------------- plant
def plant_description(plant: Plant, seed: int, horizon: int) -> PlantDescription:
    space = control_space(plant)
    return PlantDescription(
        task=plant.task,
        seed=seed,
        horizon=horizon,
        timestep=plant.dt,
        state_dim=plant.state_dim,
        action_dim=plant.action_dim,
        joint_names=list(plant.joint_names),
        actuated_joint_names=list(plant.actuated_joint_names),
        model_sha256=plant.model_sha256(),
        angle_entries=list(space.angles),
        action_low=float64_array(space.action_low),
        action_high=float64_array(space.action_high),
    )


def policy_spec_to_msg(spec: PolicySpec) -> PolicySpecMsg:
    """A run's policy as the dataset service sends it with its data (:func:`policy_spec_from_msg` reads it back)."""
    control = spec.control
    return PolicySpecMsg(
        kind=spec.kind, lipschitz=spec.lipschitz.value, lipschitz_source=spec.lipschitz.source,
        lipschitz_margin=spec.lipschitz.margin, state_dim=control.state_dim, angle_entries=list(control.angles),
        action_low=float64_array(control.action_low), action_high=float64_array(control.action_high),
        invariant_entries=list(control.invariant), distance_weights=float64_array(control.weights),
    )  # fmt: skip


def policy_spec_from_msg(msg: PolicySpecMsg) -> PolicySpec:
    """The policy a dataset answer names; ValueError naming what is wrong with one that names none."""
    if not msg.kind:
        raise ValueError("the dataset answer names no policy (an npp_ros from before the policy was sent whole?)")
    kind = check_policy_kind(msg.kind)
    control = ControlSpace.of(msg.state_dim, list(msg.angle_entries), list(msg.action_low), list(msg.action_high))
    control = replace(
        control,
        invariant=tuple(int(i) for i in msg.invariant_entries),
        weights=tuple(float(w) for w in msg.distance_weights),
    )
    lipschitz = LipschitzConstant(float(msg.lipschitz), msg.lipschitz_source, margin=float(msg.lipschitz_margin))
    return PolicySpec(kind, lipschitz, control)


def plant_from_msg(msg: PlantDescription) -> PlantRecord:
    """The plant a sim's description names, as the core record a viewer of the run reads (GraphClient)."""
    return PlantRecord(
        task=msg.task, seed=int(msg.seed), horizon=int(msg.horizon), timestep=float(msg.timestep),
        state_dim=int(msg.state_dim), action_dim=int(msg.action_dim), joint_names=tuple(msg.joint_names),
        actuated_joint_names=tuple(msg.actuated_joint_names), model_sha256=msg.model_sha256,
        angle_entries=tuple(int(i) for i in msg.angle_entries), action_low=tuple(float(x) for x in msg.action_low),
        action_high=tuple(float(x) for x in msg.action_high),
    )  # fmt: skip


def control_space_from(msg: PlantDescription) -> ControlSpace:
    """The plant's control space as its sim describes it (raises ValueError on a description that is no range)."""
    return ControlSpace.of(msg.state_dim, list(msg.angle_entries), list(msg.action_low), list(msg.action_high))


def state_layout(plant: PlantDescription) -> str:
    """What a state's entries are, for messages that tell a caller what to send."""
    return f"qpos then qvel of {len(plant.joint_names)} joints of {plant.task}"


# ----------------------------------------------------------------------------- robots
def robot_to_field(robot: Robot | None) -> str:
    """A drawn robot as the ``robot`` field of a reset, an expert request or a rollout report ('' = nominal)."""
    return "" if robot is None else robot.record()


def robot_from_field(text: str) -> Robot | None:
    """The robot a ``robot`` field names (None: the nominal model); MessageError naming what is wrong."""
    if not text:
        return None
    try:
        return Robot.from_record(text)
    except ValueError as exc:
        raise MessageError(f"robot: {exc}") from None


# ----------------------------------------------------------------------------- episodes
def gap_report(row: EpisodeRow, config: RunConfig, time: Time) -> GapReport:
    """One episode's decision as /npp/gap reports it: its GapRecord (the row against the run's spec), as a message."""
    spec = config.spec
    gap = GapRecord.of(row, epsilon=spec.epsilon, condition=spec.condition, certify=spec.certify)
    msg = GapReport(
        episode=gap.episode,
        initial_state=float64_array(gap.initial_state),
        v_lb=gap.v_lb,
        v_ub=gap.v_ub,
        gap=gap.gap,
        epsilon=gap.epsilon,
        oracle_called=gap.oracle_called,
        dataset_size=gap.dataset_size,
        oracle_calls=gap.oracle_calls,
        quiet_episodes=gap.quiet_episodes,
        quiet_required=gap.required,
        condition=gap.condition,
        certify=gap.certify,
        checked_gap=gap.checked_gap,
        test=gap.test,
        test_delta=gap.test_delta,
    )
    msg.header.stamp = time
    return msg


def episode_result(row: EpisodeRow, steps: int, time: Time) -> EpisodeResult:
    """One episode's outcome as /npp/episode reports it: NaN return and 0 steps when the policy did not drive;
    the robot it ran on under model uncertainty ('' for the exact model)."""
    driven = row.policy_return is not None
    msg = EpisodeResult(
        episode=row.episode,
        policy_return=row.policy_return if driven else float("nan"),
        steps=steps if driven else 0,
        initial_state=float64_array(row.initial_state),
        expert_value_known=row.expert_value is not None,
        expert_value=row.expert_value if row.expert_value is not None else 0.0,
        v_lb=row.v_lb,
        robot=row.robot or "",
    )
    msg.header.stamp = time
    return msg


def gap_from_msg(msg: GapReport) -> GapRecord:
    """A gap report as the core record a viewer of the run reads (GraphClient)."""
    return GapRecord(
        episode=int(msg.episode), initial_state=tuple(float(x) for x in msg.initial_state), v_lb=msg.v_lb,
        v_ub=msg.v_ub, gap=msg.gap, checked_gap=msg.checked_gap, epsilon=msg.epsilon,
        oracle_called=bool(msg.oracle_called), dataset_size=int(msg.dataset_size), oracle_calls=int(msg.oracle_calls),
        quiet_episodes=int(msg.quiet_episodes), required=int(msg.quiet_required), test=int(msg.test),
        test_delta=msg.test_delta, condition=msg.condition, certify=msg.certify,
    )  # fmt: skip


def episode_from_msg(msg: EpisodeResult) -> EpisodeOutcome:
    """An episode result as the core record a viewer of the run reads: None for what the report does not know."""
    driven = msg.steps > 0 and not math.isnan(msg.policy_return)
    return EpisodeOutcome(
        episode=int(msg.episode), policy_return=msg.policy_return if driven else None, steps=int(msg.steps),
        initial_state=tuple(float(x) for x in msg.initial_state),
        expert_value=msg.expert_value if msg.expert_value_known else None, v_lb=msg.v_lb, robot=msg.robot,
    )  # fmt: skip


def rollout_result(
    episode: int, policy_return: float, steps: int, initial_state: ArrayLike, time: Time, robot: Robot | None = None
) -> EpisodeResult:
    """The sim's report of an episode the policy drove (it knows neither V* nor the bounds), naming the robot
    it ran on."""
    msg = EpisodeResult(
        episode=episode,
        policy_return=policy_return,
        steps=steps,
        initial_state=float64_array(initial_state),
        expert_value_known=False,
        robot=robot_to_field(robot),
    )
    msg.header.stamp = time
    return msg


# ----------------------------------------------------------------------------- certificate
CERTIFICATE_RENAMED = {"window": "quiet_episodes", "required": "episodes_required"}  # record name -> message field


def certificate_to_msg(certificate: Certificate, time: Time) -> CertificateMsg:
    """The certificate's record (``Certificate.record``) under the message's names, so the two never drift.

    Not carried: ``task`` (the plant description names it) and ``rule`` (the statement says it).
    """
    named = {CERTIFICATE_RENAMED.get(name, name): value for name, value in certificate.record().items()}
    if named.get("mixture") is None:
        named["mixture"] = math.nan  # not the mixture rule: no statistic
    if named.get("policy_lipschitz") is None:
        named["policy_lipschitz"] = math.nan  # the policy chooses by the claim's L
    carried = CertificateMsg.get_fields_and_field_types()
    msg = CertificateMsg(**{name: value for name, value in named.items() if name in carried})
    msg.header.stamp = time
    return msg


def certificate_from_msg(msg: CertificateMsg, task: str, diameter: float | None = None) -> Certificate:
    """The certificate a message carries, for the run of ``task`` (the plant description names it) whose
    initial states span ``diameter`` (condition (ii) states it); the inverse of :func:`certificate_to_msg`.

    The stopping rule is not carried: a mixture statistic means the mixture rule, and the statement names the
    paper's one-shot rule where it was that one; else the rule was the sequential one.
    """
    mixture = None if math.isnan(msg.mixture) else float(msg.mixture)
    if mixture is not None:
        rule = "mixture"
    else:
        rule = "paper" if "the paper's one-shot rule" in msg.statement else "sequential"
    spec = CertificationSpec(
        msg.condition, msg.epsilon, msg.p, msg.delta,  # type: ignore[arg-type]
        LipschitzConstant(msg.lipschitz, msg.lipschitz_source, margin=msg.lipschitz_margin), diameter,
        certify=msg.certify, rule=rule, policy=msg.policy,  # type: ignore[arg-type]
    )  # fmt: skip
    fields = CertificateMsg.get_fields_and_field_types()
    renamed = {carried: name for name, carried in CERTIFICATE_RENAMED.items()}
    record = {renamed.get(name, name): getattr(msg, name) for name in fields if name != "header"}
    own = None if math.isnan(msg.policy_lipschitz) else float(msg.policy_lipschitz)
    record.update(task=task, mixture=mixture, assumptions=list(msg.assumptions), policy_lipschitz=own)
    return Certificate.from_record(record, spec)


def certificate_of_run(msg: CertificateMsg, plant: PlantRecord | None) -> Certificate:
    """The certificate a message carries, for the run whose sim describes ``plant`` (its task, and under condition
    (ii) the diameter of the task's initial states); None: no plant described yet, so no task."""
    task = plant.task if plant is not None else ""
    diameter = get_task(task).initial_state_diameter if task and msg.condition == "ii" else None
    return certificate_from_msg(msg, task, diameter)


# ----------------------------------------------------------------------------- recordings
Record = GapRecord | EpisodeOutcome | Certificate | PlantRecord  # what a viewer of the run reads


def recorded_records(messages: Iterable[tuple[str, Any]]) -> Iterator[Record]:
    """A recording's reports and plant descriptions, as (message type, message) in recorded order (a bag's, each
    decoded by the definitions the bag carries), as the records GraphClient gives live: each certificate for the
    plant described last before it. Messages of other types are passed over."""
    plant: PlantRecord | None = None
    for msgtype, msg in messages:
        kind = msgtype.rpartition("/")[2]
        if kind == "PlantDescription":
            plant = plant_from_msg(msg)
            yield plant
        elif kind == "GapReport":
            yield gap_from_msg(msg)
        elif kind == "EpisodeResult":
            yield episode_from_msg(msg)
        elif kind == "Certificate":
            yield certificate_of_run(msg, plant)
