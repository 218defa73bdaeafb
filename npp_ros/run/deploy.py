"""Deploying one certified run on a robot: the gate, the robot's joints, command limits, coverage, the watchdog.

No ROS here: npp-deploy (``npp_ros_graph/nodes/deploy.py``) converts the robot's messages and calls these.

The gate (:func:`load_deployment`) decides whether a run folder may command a robot. It refuses:

- a folder without a readable run file, or one whose data fail their SHA-256 checks (altered or
  damaged), or whose certificate does not follow from its own episode log (an edited certificate);
- a run without a certificate, or with one that is not proven;
- a certificate weaker than the operator accepts (epsilon, p, delta);
- a robot whose model fingerprint is not the certified plant's.

An operator may override the certificate and fingerprint checks (``Acceptance.override``), and every
overridden reason is kept for the log and /diagnostics. Nothing overrides a file whose data fail
their checksums: those data are no run's, so there is no policy to deploy.
What the checksums detect is an edit of the data after the run; they are not a signature, and a
writer who recomputes them is not detected.
"""

from __future__ import annotations

import math
import sqlite3
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, TypeVar

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from npp_ros.certificate.mixture import certifier_for
from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import Dataset, FloatArray
from npp_ros.policy.vectors import MAX_MAGNITUDE
from npp_ros.run.records import EpisodeRow, RunFileError, RunMetadata
from npp_ros.run.setup import policy_for, spec_of
from npp_ros.run.store import RunStore
from npp_ros.tasks.registry import Plant, Task, UnknownTaskError, get_task

RUN_FILE = "run.sqlite"
CommandInterface = Literal["effort", "position"]
COMMAND_INTERFACES: tuple[str, ...] = ("effort", "position")
_SPEC_FIELDS = ("condition", "epsilon", "p", "delta", "certify", "rule", "policy", "lipschitz", "lipschitz_source")
_MJ_JOINT_SLIDE, _MJ_JOINT_HINGE = 2, 3  # MuJoCo joint types with one position and one velocity
_MJ_BIAS_NONE = 0  # a motor: the control is a force or torque
T = TypeVar("T")


class GateRefusal(ValueError):
    """The gate refuses to deploy a run folder; the message says every reason."""


class RobotStateError(ValueError):
    """A joint state the policy cannot act on; the message names the joints or values at fault."""


class NonFiniteState(RobotStateError):
    """A joint state with a NaN or infinite value on one of the task's joints."""


@dataclass(frozen=True)
class Acceptance:
    """What the operator accepts: the weakest certificate, the robot's model, and whether to override."""

    max_epsilon: float = math.inf
    min_p: float = 0.0
    max_delta: float = 1.0
    model_fingerprint: str = ""  # the robot's; must equal the run's plant fingerprint
    override: bool = False

    def __post_init__(self) -> None:
        if not self.max_epsilon > 0:
            raise ValueError(f"max_epsilon must be > 0, got {self.max_epsilon!r}")
        if not 0 <= self.min_p < 1:
            raise ValueError(f"min_p must lie in [0, 1), got {self.min_p!r}")
        if not 0 < self.max_delta <= 1:
            raise ValueError(f"max_delta must lie in (0, 1], got {self.max_delta!r}")


@dataclass(frozen=True)
class Deployment:
    """A run folder that passed the gate (or was let through by an override): the policy it names and its plant."""

    run_file: Path
    metadata: RunMetadata
    certificate: Mapping[str, Any] | None
    policy: NonparametricPolicy
    task: Task
    plant: Plant
    checked_starts: FloatArray  # the s0 ~ rho the run checked whose trajectory is not in the policy's data
    overridden: tuple[str, ...] = ()  # the reasons the gate gave and the operator overrode

    @property
    def policy_trajectories(self) -> int:
        return self.policy.dataset.num_trajectories

    def describe(self) -> str:
        """One line: which run, which policy, what its certificate claims."""
        meta, cert = self.metadata, self.certificate
        policy = f"greedy over {self.policy_trajectories} trajectories ({len(self.policy.dataset)} points)"
        policy += f", acting {self.policy.kind}"
        head = f"{meta.task} seed {meta.seed}, {policy}, L {self.policy.lipschitz:g}"
        if cert is None:
            return f"{head}; NO certificate"
        claim = f"condition ({cert['condition']}), epsilon {cert['epsilon']:g}, p {cert['p']:g}"
        claim += f", delta {cert['delta']:g}"
        proven = "proven" if cert["proven"] else "NOT proven"
        return f"{head}; certificate {claim}, certify={cert['certify']}, H {meta.horizon}, {proven}"


def load_deployment(run_dir: str | Path, acceptance: Acceptance) -> Deployment:
    """The gate: the policy a run folder's certificate names, or a GateRefusal with every reason."""
    run_file = _run_file(Path(run_dir))
    try:
        return _pass_gate(run_file, acceptance)
    except GateRefusal:
        raise
    except (RunFileError, KeyError, TypeError, ValueError, sqlite3.Error) as exc:  # a hand-edited or damaged file
        what = f"no {exc}" if isinstance(exc, KeyError) else str(exc)
        raise GateRefusal(f"{run_file} cannot be read as a run ({what}): the run file was altered or damaged") from None


def _pass_gate(run_file: Path, acceptance: Acceptance) -> Deployment:
    try:
        store = RunStore.open(run_file)
    except RunFileError as exc:
        raise GateRefusal(f"cannot read the run: {exc}") from None
    try:
        with store.snapshot():
            metadata = store.metadata
            task = _task_of(metadata, run_file)
            try:
                dataset = store.load_dataset()
            except RunFileError as exc:
                raise GateRefusal(f"the run file was altered or damaged: {exc}") from None
            certificate = store.certificate()
            rows = store.episodes()
    finally:
        store.close()
    if dataset.num_trajectories == 0:
        raise GateRefusal(f"{run_file} holds no expert trajectories: there is no policy to deploy")
    inconsistent = [] if certificate is None else _inconsistencies(certificate, metadata, rows, dataset, task)
    if inconsistent:
        what = "; ".join(inconsistent)
        reasons = [f"the certificate does not follow from the run's own log ({what}): it was altered"]
    else:
        reasons = _certificate_reasons(certificate, len(rows), dataset.num_trajectories, acceptance)
    reasons += _fingerprint_reasons(metadata, acceptance)
    if reasons and not acceptance.override:
        raise GateRefusal("; ".join(reasons))
    # Overridden: the certificate's policy where the certificate agrees with its run, else all the data.
    named = certificate is not None and not inconsistent
    count = int(certificate["policy_trajectories"]) if named else dataset.num_trajectories
    data = dataset if count == dataset.num_trajectories else dataset.prefix(count)
    policy = policy_for(data, spec_of(metadata, task.initial_state_diameter), task.name, int(metadata.seed))
    policy.act(data.states[0])  # builds the search index now: the first state on the robot must not wait for it
    outside = [row.initial_state for row in rows if row.trajectory is None or row.trajectory >= count]
    checked_starts = np.array(outside, dtype=np.float64).reshape(len(outside), metadata.state_dim)
    return Deployment(
        run_file, metadata, certificate, policy, task, task.make_plant(int(metadata.seed)), checked_starts,
        tuple(reasons),
    )  # fmt: skip


def _run_file(run_dir: Path) -> Path:
    if run_dir.is_file():
        return run_dir
    path = run_dir / RUN_FILE
    if not path.is_file():
        where = "does not exist" if not run_dir.exists() else f"holds no {RUN_FILE}"
        raise GateRefusal(f"the run folder {run_dir} {where}: there is no certified run to deploy")
    return path


def _task_of(metadata: RunMetadata, run_file: Path) -> Task:
    try:
        task = get_task(str(getattr(metadata, "task", "")))
    except UnknownTaskError as exc:
        raise GateRefusal(f"{run_file}: {exc}") from None
    if (metadata.state_dim, metadata.action_dim) != (task.state_dim, task.action_dim):
        raise GateRefusal(
            f"{run_file} stores {metadata.state_dim}-D states and {metadata.action_dim}-D actions, but {task.name} "
            f"has {task.state_dim} and {task.action_dim}: the run file was altered"
        )
    return task


def _certificate_reasons(
    certificate: Mapping[str, Any] | None, episodes: int, stored: int, acceptance: Acceptance
) -> list[str]:
    """Why a certificate (consistent with its run) may not be deployed: absent, not proven, too weak."""
    if certificate is None:
        return [
            f"the run file holds no certificate ({episodes} episodes, {stored} trajectories): the run was never "
            "certified, or its certificate was removed"
        ]
    reasons = []
    if not certificate["proven"]:
        failing = [text for text in certificate.get("assumptions", ()) if "NOT" in text or "not sequentially" in text]
        why = failing[0] if failing else "it rests on a step that does not hold for this plant"
        mode = f"certify={certificate['certify']}, rule={certificate['rule']}"
        reasons.append(f"the certificate is not proven ({mode}: {why})")
    if certificate["epsilon"] > acceptance.max_epsilon:
        reasons.append(
            f"the certificate's epsilon {certificate['epsilon']:g} is larger than this deployment accepts "
            f"(max_epsilon {acceptance.max_epsilon:g})"
        )
    if certificate["condition"] == "ii" and acceptance.min_p > 0:
        reasons.append(
            "the certificate bounds the mean gap (condition ii) and states no share p of initial states; "
            f"this deployment asks for p >= {acceptance.min_p:g}"
        )
    elif certificate["p"] < acceptance.min_p:
        reasons.append(f"the certificate's p {certificate['p']:g} is below min_p {acceptance.min_p:g}")
    if certificate["delta"] > acceptance.max_delta:
        reasons.append(
            f"the certificate's delta {certificate['delta']:g} is larger than this deployment accepts "
            f"(max_delta {acceptance.max_delta:g})"
        )
    return reasons


def _inconsistencies(
    certificate: Mapping[str, Any], metadata: RunMetadata, rows: Sequence[EpisodeRow], dataset: Dataset, task: Task
) -> list[str]:
    """Where the certificate disagrees with the run's metadata and episode log (replayed through the Certifier)."""
    problems = [
        f"{name} {certificate.get(name)!r} against the run's {getattr(metadata, name, None)!r}"
        for name in _SPEC_FIELDS
        if certificate.get(name, RunMetadata.BEFORE_RECORDED.get(name)) != getattr(metadata, name, None)
    ]
    if certificate.get("task") != metadata.task:
        problems.append(f"task {certificate.get('task')!r} against the run's {metadata.task!r}")
    if problems:
        return problems
    episodes, trajectories = int(certificate["episodes"]), int(certificate["policy_trajectories"])
    stored = dataset.num_trajectories
    if not 1 <= trajectories <= stored:
        return [f"it names {trajectories} trajectories, the run stores {stored}"]
    if not 1 <= episodes <= len(rows):
        return [f"it was issued at episode {episodes}, the log holds {len(rows)}"]
    try:
        spec = spec_of(metadata, task.initial_state_diameter)
    except (ValueError, TypeError) as exc:
        return [f"its specification is invalid: {exc}"]
    # Replay the run's checks through its rule, as a resumed run does: the certificate must be issued at its
    # episode, and its policy holds every trajectory asked for except those a frozen test held back.
    certifier = certifier_for(spec)
    stored = joined = 0
    status = None
    for row in rows[:episodes]:
        passed = spec.passes(row.checked_gap)
        stored += row.trajectories_stored
        status = certifier.observe(math.inf if row.checked_gap is None else row.checked_gap, not passed)
        if not status.frozen:
            joined = stored
    assert status is not None
    found = {"window": status.window, "required": status.required, "test": status.test, "failures": status.failures}
    if not status.certified or any(int(certificate.get(name, 0)) != value for name, value in found.items()):
        said = ", ".join(f"{name} {certificate.get(name, 0)}" for name in found)
        got = ", ".join(f"{name} {value}" for name, value in found.items())
        return [f"replaying its {episodes} episodes gives certified={status.certified}, {got}; it says {said}"]
    if trajectories != joined:
        return [f"it names {trajectories} trajectories; the first {episodes} episodes gave the policy {joined}"]
    points = int(dataset.trajectory_offsets[trajectories])
    if int(certificate["dataset_size"]) != points:
        return [f"it names {certificate['dataset_size']} points; the first {trajectories} trajectories hold {points}"]
    return []


def _fingerprint_reasons(metadata: RunMetadata, acceptance: Acceptance) -> list[str]:
    certified = str(getattr(metadata, "plant_fingerprint", "") or "")
    robot = acceptance.model_fingerprint.strip()
    if not certified:
        return ["the run records no model fingerprint: which plant its data came from is unknown"]
    if not robot:
        return ["no robot model fingerprint was given: the gate cannot check that the robot runs the certified model"]
    if robot != certified:
        return [f"the robot's model (fingerprint {robot[:12]}...) is not the certified one ({certified[:12]}...)"]
    return []


# ----------------------------------------------------------------------------- the robot's joints
@dataclass
class JointLayout:
    """The task's joints as a robot names them: its state assembled by joint name, its command in the
    controller's joint order.

    ``state_joints``: the task's joints in the state's order (qpos then qvel, one each);
    ``actuated``: the task's actuated joints in the action's order; ``command_joints``: the
    controller's joints, in the order its command array lists them (a permutation of ``actuated``).
    """

    state_joints: tuple[str, ...]
    actuated: tuple[str, ...]
    command_joints: tuple[str, ...]
    # The last message's names and where the task's joints are in them; None until the first message, so
    # that a first message naming no joints is checked like any other (an empty cache would match it).
    _names: tuple[str, ...] | None = field(default=None, init=False, repr=False)
    _where: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.intp), init=False, repr=False)

    def __post_init__(self) -> None:
        if not self.state_joints:
            raise ValueError("a joint layout needs the task's joints; this one names none")
        if sorted(self.command_joints) != sorted(self.actuated):
            raise ValueError(
                f"the command joints {list(self.command_joints)} must be the task's actuated joints "
                f"{list(self.actuated)}, each once, in any order"
            )
        self._command_order = np.array([self.actuated.index(name) for name in self.command_joints], dtype=np.intp)
        self._command_in_state = np.array([self.state_joints.index(n) for n in self.command_joints], dtype=np.intp)

    @classmethod
    def of_plant(cls, plant: Plant, command_joints: Sequence[str] = ()) -> JointLayout:
        """The plant's joints; ``command_joints`` empty: the plant's actuated joints, in its order."""
        model = getattr(getattr(plant, "physics", None), "model", None)
        if model is not None and any(int(t) not in (_MJ_JOINT_SLIDE, _MJ_JOINT_HINGE) for t in model.jnt_type):
            raise ValueError(f"{plant.task} has joints with more than one position (free or ball): not supported")
        actuated = tuple(plant.actuated_joint_names)
        return cls(tuple(plant.joint_names), actuated, tuple(command_joints) or actuated)

    def state(self, names: Sequence[str], positions: Sequence[float], velocities: Sequence[float]) -> FloatArray:
        """[positions, velocities] of the task's joints, whatever order and extra joints the message has; a
        RobotStateError naming what is wrong for a state the policy cannot act on."""
        names = tuple(names)
        if names != self._names:
            self._where = self._index(names)
            self._names = names
        if len(positions) != len(names) or len(velocities) != len(names):
            raise RobotStateError(
                f"joint state names {len(names)} joints but has {len(positions)} positions and "
                f"{len(velocities)} velocities (one each per named joint needed)"
            )
        where = self._where
        position, velocity = np.asarray(positions, dtype=np.float64), np.asarray(velocities, dtype=np.float64)
        raw = np.concatenate([position[where], velocity[where]])
        finite = np.isfinite(raw)
        if not finite.all():
            raise NonFiniteState(f"joint state has non-finite values: {self._entries(~finite, raw)}")
        huge = np.abs(raw) > MAX_MAGNITUDE
        if huge.any():
            raise RobotStateError(
                f"joint state has values too large to compare with the certified data: {self._entries(huge, raw)} "
                f"(entries must be within +-{MAX_MAGNITUDE:g})"
            )
        return raw

    def _entries(self, which: np.ndarray, raw: FloatArray) -> str:
        """The flagged entries of a state, by joint: "joint_1 velocity = nan"."""
        count = len(self.state_joints)
        return ", ".join(
            f"{self.state_joints[i % count]} {'position' if i < count else 'velocity'} = {raw[i]:g}"
            for i in np.flatnonzero(which)
        )

    def _index(self, names: tuple[str, ...]) -> np.ndarray:
        if len(set(names)) != len(names):
            twice = sorted({n for n in names if names.count(n) > 1})
            raise RobotStateError(f"joint state names {', '.join(twice)} more than once")
        where = {name: i for i, name in enumerate(names)}
        missing = [name for name in self.state_joints if name not in where]
        if missing:
            shown = ", ".join(names[:10]) + (", ..." if len(names) > 10 else "") if names else "none"
            raise RobotStateError(f"joint state lacks the task's joints {', '.join(missing)} (it names: {shown})")
        return np.array([where[name] for name in self.state_joints], dtype=np.intp)

    def command(self, action: ArrayLike) -> FloatArray:
        """An action (the task's actuator order) in the controller's joint order."""
        return np.asarray(action, dtype=np.float64)[self._command_order]

    def action(self, command: ArrayLike) -> FloatArray:
        """A command (the controller's joint order) as an action in the task's actuator order."""
        action = np.empty(len(self.actuated))
        action[self._command_order] = np.asarray(command, dtype=np.float64)
        return action

    def hold(self, raw_state: FloatArray) -> FloatArray:
        """The command joints' measured positions (a position interface's safe command)."""
        return raw_state[self._command_in_state].copy()


def check_command_interface(plant: Plant, interface: str) -> None:
    """Refuse an interface the certified actions do not fit: an effort command needs motors, a position one
    position actuators (MuJoCo: a motor has no bias; a position servo an affine one)."""
    if interface not in COMMAND_INTERFACES:
        raise ValueError(f"command_interface must be one of {', '.join(COMMAND_INTERFACES)}, got {interface!r}")
    model = getattr(getattr(plant, "physics", None), "model", None)
    if model is None:
        return
    motors = [int(b) == _MJ_BIAS_NONE for b in model.actuator_biastype]
    if interface == "effort" and not all(motors):
        raise ValueError(f"{plant.task}'s actuators are position servos, not motors: use command_interface position")
    if interface == "position" and any(motors):
        raise ValueError(
            f"{plant.task}'s certified actions are efforts (its actuators on {', '.join(plant.actuated_joint_names)} "
            "are motors): use command_interface effort"
        )


def safe_command(interface: str, layout: JointLayout, raw_state: FloatArray | None) -> FloatArray:
    """What a robot gets when the policy stops: zero effort, or its present position held."""
    if interface == "position":
        if raw_state is None:
            raise RobotStateError("no joint state received yet: there is no position to hold")
        return layout.hold(raw_state)
    return np.zeros(len(layout.command_joints))


@dataclass(frozen=True)
class CommandLimits:
    """The actions a robot may receive: the model's actuator control range, tightened by ``effort_limit``."""

    low: FloatArray
    high: FloatArray

    @classmethod
    def of_plant(cls, plant: Plant, effort_limit: float = 0.0) -> CommandLimits:
        low, high = np.full(plant.action_dim, -np.inf), np.full(plant.action_dim, np.inf)
        model = getattr(getattr(plant, "physics", None), "model", None)
        if model is not None:
            limited = np.asarray(model.actuator_ctrllimited, dtype=bool)
            low[limited] = model.actuator_ctrlrange[limited, 0]
            high[limited] = model.actuator_ctrlrange[limited, 1]
        if effort_limit > 0:
            low, high = np.maximum(low, -effort_limit), np.minimum(high, effort_limit)
        return cls(low, high)

    def clamp(self, action: FloatArray) -> tuple[FloatArray, int]:
        """The action within the limits, and how many of its entries had to be clamped."""
        clamped = np.clip(action, self.low, self.high)
        return clamped, int(np.count_nonzero(clamped != action))

    def describe(self) -> str:
        if not np.isfinite(np.concatenate([self.low, self.high])).any():
            return "none (the model's actuators are not limited and no effort_limit was given)"
        return ", ".join(f"[{lo:g}, {hi:g}]" for lo, hi in zip(self.low, self.high, strict=True))


# ----------------------------------------------------------------------------- coverage
class Coverage:
    """How far a state lies from the certified policy's data (Euclidean, in the stored state space)."""

    def __init__(self, data_states: FloatArray, radius: float) -> None:
        self._tree = cKDTree(np.asarray(data_states, dtype=np.float64))
        self.radius = float(radius)

    @classmethod
    def of_deployment(cls, deployment: Deployment, radius: float = 0.0) -> Coverage:
        """``radius`` 0: the farthest a checked s0 lay from the policy's data (see :meth:`farthest_start`)."""
        coverage = cls(deployment.policy.dataset.states, math.inf)
        coverage.radius = radius if radius > 0 else coverage.farthest_start(deployment.checked_starts)
        return coverage

    def farthest_start(self, starts: FloatArray) -> float:
        """The largest distance from the data to an s0 ~ rho that the run checked and did not add to the policy's
        data (a certified run's streak is made of them): fresh draws from rho came that far from the data.
        Infinite when there is none (a run that never certified): then nothing calibrates a radius."""
        if len(starts) == 0:
            return math.inf
        return float(self._tree.query(starts)[0].max())

    def distance(self, state: FloatArray) -> float:
        return float(self._tree.query(state)[0])

    def covers(self, state: FloatArray, near: FloatArray | None = None) -> tuple[bool, float]:
        """Whether the state lies within the radius of the data, and a distance that decides it.

        ``near``: a data point (the one the policy picked). Within the radius of it the state is covered
        and no search is needed (the distance then is to ``near``, an upper bound on the nearest);
        only a state farther than that pays for the nearest-neighbour search, which can take
        milliseconds at 10^6 points in 12-D.
        """
        if near is not None:
            distance = float(np.sqrt(np.sum((state - near) ** 2)))
            if distance <= self.radius:
                return True, distance
        distance = self.distance(state)
        return distance <= self.radius, distance


def stored_state(plant: Plant, raw: FloatArray) -> FloatArray:
    """The robot's [qpos, qvel] as the task stores states (angles wrapped where the task wraps them)."""
    represent = getattr(plant, "represent", None)
    return raw if represent is None else represent(raw)


# ----------------------------------------------------------------------------- watchdog
Fresh = Literal["sent", "resumed", "disarmed"]


class Watchdog:
    """Sends the safe command once when no fresh command went out for ``timeout`` seconds while armed.

    Its own thread waits until the deadline, so the safe command goes out on time whatever the executor
    is doing. Deciding that the deadline passed and sending the safe command (``on_expire(age_s)``) are
    one step under the lock that :meth:`send_fresh` holds while it sends a fresh command and restarts
    the clock: a safe command never goes out after a fresh one that beat its deadline, and no fresh
    command goes out after :meth:`disarm` sent the safe one. ``after_expire(age_s)`` (logging, reporting)
    runs after the lock is released, so it never delays a fresh command.
    """

    def __init__(
        self,
        timeout: float,
        on_expire: Callable[[float], None],
        after_expire: Callable[[float], None] | None = None,
    ) -> None:
        if not timeout > 0:
            raise ValueError(f"the watchdog timeout must be > 0, got {timeout!r}")
        self.timeout = float(timeout)
        self._on_expire = on_expire
        self._after_expire = after_expire
        self._last = time.monotonic()
        self._armed = False
        self.expired = False
        self.fired = 0
        self._wake = threading.Condition()  # its lock is re-entrant: on_expire may read the watchdog
        self._closed = False
        self._thread = threading.Thread(target=self._watch, name="npp-watchdog", daemon=True)
        self._thread.start()

    @property
    def armed(self) -> bool:
        return self._armed

    def send_fresh(self, send: Callable[[], None]) -> Fresh:
        """Send a fresh command and restart the clock, as one step against the watchdog's own decision.

        "sent"; "resumed" when it ends an expiry (states flow again); "disarmed" when the watchdog is
        not armed, and then nothing is sent (commanding has stopped)."""
        with self._wake:
            if not self._armed:
                return "disarmed"
            send()
            self._last = time.monotonic()
            if not self.expired:
                return "sent"
            self.expired = False
            self._wake.notify()  # it sleeps without a deadline while expired
            return "resumed"

    def feed(self) -> bool:
        """Restart the clock without sending anything; True when it ends an expiry."""
        with self._wake:
            self._last = time.monotonic()
            if not self.expired:
                return False
            self.expired = False
            self._wake.notify()
            return True

    def arm(self) -> None:
        """Start watching now, as if a state had just arrived."""
        with self._wake:
            self._last = time.monotonic()
            self._armed, self.expired = True, False
            self._wake.notify()

    def disarm(self, send: Callable[[], T] | None = None) -> T | None:
        """Stop watching; ``send`` (the safe command) runs in the same step, so no fresh command follows it."""
        with self._wake:
            self._armed = False
            self._wake.notify()
            return None if send is None else send()

    def close(self) -> None:
        with self._wake:
            self._closed = True
            self._wake.notify()
        self._thread.join(timeout=2.0)

    def _watch(self) -> None:
        with self._wake:
            while not self._closed:
                if not self._armed or self.expired:
                    self._wake.wait()
                    continue
                left = self._last + self.timeout - time.monotonic()
                if left > 0:
                    self._wake.wait(left)
                    continue
                self.expired = True
                self.fired += 1
                age = time.monotonic() - self._last
                self._on_expire(age)  # under the lock: the decision and the safe command are one step
                if self._after_expire is not None:
                    self._wake.release()
                    try:
                        self._after_expire(age)
                    finally:
                        self._wake.acquire()


def percentiles(samples: Sequence[float], quantiles: Sequence[float] = (50, 99)) -> list[float]:
    """The given percentiles of the samples (NaN when there are none)."""
    if len(samples) == 0:
        return [math.nan for _ in quantiles]
    return [float(v) for v in np.percentile(np.asarray(samples, dtype=np.float64), quantiles)]


def parse_names(text: str) -> tuple[str, ...]:
    """A comma-separated list of joint names (a ROS parameter holds it as one string)."""
    return tuple(name.strip() for name in text.split(",") if name.strip())


def parse_vector(text: str, size: int, what: str) -> FloatArray:
    """A comma-separated vector of ``size`` finite numbers."""
    try:
        values = [float(x) for x in text.split(",") if x.strip()]
    except ValueError as exc:
        raise ValueError(f"{what} must be {size} comma-separated numbers: {exc}") from None
    arr = np.asarray(values, dtype=np.float64)
    if arr.size != size or not np.isfinite(arr).all():
        raise ValueError(f"{what} must be {size} finite comma-separated numbers, got {text!r}")
    return arr
