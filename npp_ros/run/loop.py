"""Algorithm 1 (NPP) as one reusable loop.

The loop owns the algorithm's decisions: sample s0, check the policy at s0 with the quantity the
run certifies on (npp_ros.certificate), ask the oracle when the check fails, append and persist,
certify. What it talks to plugs in: where s0 comes from, the oracle, an episode driver (the
policy's rollout, in process or through the ROS graph) and observers. The supervisor node and
in-process experiments run this same class, so the same seed gives the same dataset and gap
sequence in both.

Order within an episode, per mode:
- ``surrogate`` (the paper): gap V_ub - V_lb at s0; oracle if it exceeds epsilon; then the
  (updated) policy drives the episode, its return recorded for information.
- ``rollout``: the current policy drives the episode first; the check V_ub + tail - R^pi decides,
  and a failed check sends s0 to the oracle.
- ``success``: the current policy drives the episode first; the check is whether its rollout met the task's
  success criterion (no expert value involved), and a failed check sends s0 to the oracle.
- ``oracle``: the current policy drives the episode and the oracle answers for s0 in every
  episode; the check is V^E(s0) - R^pi(s0). A test must see one frozen policy, so trajectories
  from passed checks are held back (stored at once, never lost) and join the policy's data when
  the streak ends: with a failed check, or after the certificate is issued.

Under the ``mixture`` rule (mixture.py) a verification also holds back its failed checks'
trajectories, in every mode, until it certifies or gives up: the certifier's status says when the
policy is frozen, and the loop only follows it.

Where the task states a success criterion (npp_ros.tasks.success), every episode is also judged on it: the
expert's answer from s0 on its stored states, the policy's rollout on the states of that rollout, which a
:class:`Replay` gives (the in-process driver's own rollout, or in the graph the same rollout re-run on a local
copy of the deterministic plant). Nothing of this decides a check; the certificate states the counts.

A run whose plant is a robot itself (npp_ros.run.on_robot) plugs the robot in as its starts, its driver and its replay,
and its facts into the certificate; a driver there may cut an episode short (EpisodeCut: a robot's fault), which is
then no check, and the episode runs again. A run may start with another run's trajectories (``prior``): its first
data, never its expert calls, and its first check is already the first test of a policy.

Under model uncertainty (npp_ros.tasks.uncertainty) each episode also draws its robot theta from the run's seed and
the episode's index (``robots``), and everything the episode checks runs on it: the policy's rollout (the driver and
the replay), the oracle's answer (a privileged expert, planning on theta) and the explorer's. The row records it.
"""

from __future__ import annotations

import json
import math
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields, replace
from typing import TYPE_CHECKING, Protocol

import numpy as np

from npp_ros.certificate.authoring import MeasuredSuccess, RobotClaim, author_certificate
from npp_ros.certificate.certifier import (
    SUCCESS_CHECK,
    Certificate,
    CertificationSpec,
    CertificationStatus,
    Certifier,
)
from npp_ros.certificate.mixture import MixtureCertifier, certifier_for
from npp_ros.certificate.values import ValueBasis
from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import Dataset, FloatArray, Trajectory
from npp_ros.policy.feedback import ControlSpace
from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.policy.spec import PolicySpec
from npp_ros.run import defaults
from npp_ros.run.nominal_plan import DEFAULT_EXPERT_MODEL, REFERENCE
from npp_ros.run.policy_lipschitz import (
    LipschitzChoice,
    acted_by,
    check_policy_lipschitz,
    choice_point,
    choose_lipschitz,
    recent_starts,
)
from npp_ros.run.records import (
    EpisodeRow,
    RunFileError,
    RunMetadata,
    SuccessCounts,
    UnrecordedSettings,
    state_tuple,
)
from npp_ros.run.store import RunStore
from npp_ros.tasks.success import SuccessCriterion
from npp_ros.tasks.task import DEFAULT_HORIZON
from npp_ros.tasks.uncertainty import Robot, describe_robots

if TYPE_CHECKING:
    from npp_ros.tasks.rollout import Rollout


class Oracle(Protocol):
    """The TrajectoryOptimizer: an expert trajectory from a given state (a run under model uncertainty names the
    episode's robot, and the oracle plans on it; a run without names none, and any expert is an oracle)."""

    def trajectory(self, initial_state: FloatArray) -> Trajectory: ...


class RobotOracle(Protocol):
    """An oracle that plans on a drawn robot (npp_ros.tasks.uncertainty): a privileged expert."""

    def trajectory(self, initial_state: FloatArray, robot: Robot | None = None) -> Trajectory: ...


class Explorer(Protocol):
    """Where to ask the expert besides s0 after a failed check (npp_ros.run.explore), or None."""

    def state_to_ask(
        self, initial_state: FloatArray, policy: NonparametricPolicy, robot: Robot | None = None
    ) -> FloatArray | None: ...


class Replay(Protocol):
    """The policy's own rollout from s0 (npp_ros.run.explore.PolicyReplay): what the success check judges."""

    def rollout(
        self, initial_state: FloatArray, policy: NonparametricPolicy, robot: Robot | None = None
    ) -> Rollout: ...


class EpisodeInterrupted(RuntimeError):
    """The run is stopping while an episode is under way: nothing of the episode is recorded, and a
    resumed run plays it again from the same s0 (a pause or a restart never decides a check)."""


class EpisodeCut(RuntimeError):
    """The plant cut the episode short (a robot's fault: its states stopped, its reset failed): the driver stored
    and marked what it ran, nothing of it is a check, and the loop runs the episode again from a new start."""


class RobotFacts(Protocol):
    """What a run whose plant is a robot (npp_ros.run.on_robot) tells its certificate: the robot and its episodes."""

    def claim(self) -> RobotClaim: ...


class EpisodeDriver(Protocol):
    """Lets the current policy drive one episode from s0; returns its return, or None when the policy
    cannot drive at all (no data). A driver that loses a result asks for it again or runs the episode
    again; it raises EpisodeInterrupted only when the run is stopping. Under model uncertainty the episode's
    ``robot`` is the plant the policy drives."""

    def run_episode(
        self, episode: int, initial_state: FloatArray, policy: NonparametricPolicy, robot: Robot | None = None
    ) -> float | None: ...


class Observer:
    """Hooks for progress, logs and topics; override what you need."""

    def on_episode(self, row: EpisodeRow, status: CertificationStatus) -> None:
        """Called after each episode is stored."""

    def on_certificate(self, certificate: Certificate) -> None:
        """Called once, when the run certifies."""

    def on_trajectory(self, index: int, trajectory: Trajectory) -> None:
        """Called when an expert trajectory joins the policy's data (the policy must learn it)."""


@dataclass(frozen=True)
class RunConfig:
    """Everything that defines a run: the task and its plant, and what the run certifies (``spec``).

    Two runs with equal configs give equal numbers. ``npp_ros.run.setup.build_config`` builds one for a task.
    """

    task: str
    seed: int
    state_dim: int
    action_dim: int
    spec: CertificationSpec
    horizon: int = DEFAULT_HORIZON
    gamma: float = defaults.GAMMA
    plant_fingerprint: str = ""  # the compiled model's SHA-256 (Plant.model_sha256): which plant the data are of
    # > 0: after a failed check, also ask where the policy's rollout leaves the data this far
    explore: float = defaults.EXPLORE
    # The L the policy chooses its data point by: the claim's ("claim") or chosen from the run's data ("select",
    # npp_ros.run.policy_lipschitz).
    policy_lipschitz: str = defaults.POLICY_LIPSCHITZ
    # The set of robots the run draws from (UncertaintySet.record(), its elements named): '' = the exact model.
    uncertainty: str = ""
    # Under uncertainty, the model the expert plans on: each episode's robot, or the nominal one (nominal_plan).
    expert_model: str = DEFAULT_EXPERT_MODEL
    # A run whose plant is a robot (npp_ros.run.on_robot.identity.RobotIdentity.record()): which robot, which model
    # the expert plans on, where its starts come from; '' = a run on the task's model.
    robot_run: str = ""
    # Trajectories the run starts with, from another run (on_robot.setup.prior_record: its folder, seal digest and
    # count); '' = none. They are the file's first trajectories, asked by no episode of this run.
    prior: str = ""
    # The expert's settings that decide its answers (records.EXPERT_SETTINGS), as its expert resolved them (the task's
    # defaults filled in; records.expert_settings); None where an option does not apply to that expert.
    expert_kind: str | None = None
    time_budget: float | None = None
    max_iterations: int | None = None
    expert_stop: str | None = None
    values: str | None = None
    control_weight: float | None = None

    def metadata(self) -> RunMetadata:
        """What the run file records of this config: its own fields, the spec's record, where L came from."""
        own = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "spec"}
        return RunMetadata(**own, **self.spec.record(), lipschitz_detail=self.spec.lipschitz.detail)

    def identity(self) -> dict[str, object]:
        """Every recorded setting that decides the run's answers and checks (its metadata but where L came from): a
        resume must ask for the same, and records kept beside the run (its held-out answers) are of it only."""
        return {k: v for k, v in vars(self.metadata()).items() if k not in RunMetadata.PROVENANCE}


@dataclass
class RunResult:
    episodes: int
    oracle_calls: int
    dataset_size: int
    certificate: Certificate | None
    rows: list[EpisodeRow] = field(default_factory=list)

    @property
    def certified(self) -> bool:
        return self.certificate is not None


def policy_spec(
    spec: CertificationSpec, control: ControlSpace, lipschitz: LipschitzConstant | None = None
) -> PolicySpec:
    """The policy a run's spec names, as one value: its kind from the spec, its L the spec's unless the run chose
    its own (``lipschitz``, npp_ros.run.policy_lipschitz), the task's control space. The one place a run's policy is
    decided; the supervisor sends it whole to the policy node."""
    return PolicySpec(spec.policy, lipschitz or spec.lipschitz, control)


def make_policy(
    data: Dataset, spec: CertificationSpec, control: ControlSpace | None, lipschitz: LipschitzConstant | None = None
) -> NonparametricPolicy:
    """The policy a run's spec names over ``data``: the choice on V_lb with its L (the spec's, or the one the run
    chose for its policy; its distance blind to the task's invariant entries), acting open loop, with the expert's
    feedback, or along the path it chose, in the task's control space. Every place that acts for a run builds it
    here (:func:`policy_spec`)."""
    if control is None:  # a plant that states no control space: no angles, no limits, nothing invariant
        return NonparametricPolicy(data, (lipschitz or spec.lipschitz).value, kind=spec.policy)
    return policy_spec(spec, control, lipschitz).build(data)


class NPPLoop:
    """Algorithm 1 over pluggable parts; resumes from a run store if it holds episodes.

    ``basis`` says which value the certificate is about and bounds its tail (values.py); the
    rollout mode needs its tail, and every mode needs a driver except ``surrogate``.
    """

    def __init__(
        self,
        config: RunConfig,
        oracle: Oracle,
        initial_state: Callable[[int], FloatArray],
        *,
        store: RunStore | None = None,
        driver: EpisodeDriver | None = None,
        observers: Sequence[Observer] = (),
        expert_value: Callable[[FloatArray], float] | None = None,
        basis: ValueBasis | None = None,
        control: ControlSpace | None = None,
        explorer: Explorer | None = None,
        success: SuccessCriterion | None = None,
        replay: Replay | None = None,
        robots: Callable[[int], Robot] | None = None,
        robot_facts: RobotFacts | None = None,
        prior: Dataset | None = None,
    ) -> None:
        self.config = config
        self.spec = config.spec
        certify = self.spec.certify
        if certify != "surrogate" and driver is None:
            raise ValueError(f"certify={certify} checks the policy's own return: it needs the policy's rollouts")
        if config.explore > 0 and explorer is None:
            raise ValueError("explore > 0 needs an explorer (npp_ros.run.explore.RolloutExplorer)")
        if certify == "success" and (success is None or replay is None):
            raise ValueError(
                "certify=success judges the policy's own rollout on the task's success criterion: it needs a task "
                "that states one (a task file's [success]) and the policy's replay"
            )
        if certify == "rollout" and (basis is None or basis.tail is None):
            detail = basis.tail_detail if basis is not None else "the expert states no value basis"
            raise ValueError(f"certify=rollout needs an upper bound on the H-step value at s0 ({detail}); use oracle")
        self.oracle = oracle
        self.initial_state = initial_state
        self.store = store
        self.driver = driver
        self.observers = list(observers)
        self.expert_value = expert_value
        self.basis = basis
        self.control = control
        self.explorer = explorer if config.explore > 0 else None
        self.success = success
        self.replay = replay  # None: the policy's success is not judged (the expert's still is)
        if config.uncertainty and robots is None:
            raise ValueError("a run under model uncertainty needs its robot draw (npp_ros.run.setup.robot_fn)")
        self.robots = robots if config.uncertainty else None
        if bool(config.robot_run) != (robot_facts is not None):
            raise ValueError("a run on a robot needs its robot's facts for its certificate; only such a run has some")
        if config.robot_run and certify != "success":
            raise ValueError(
                f"a run on a robot certifies the success claim only (certify=success), not {certify}: its checks are "
                "the robot's own episodes, which give no expert value to compare with"
            )
        self.robot_facts = robot_facts
        check_policy_lipschitz(config.policy_lipschitz, certify)
        if config.policy_lipschitz == "select" and replay is None:
            raise ValueError(
                "a policy L chosen from the run's data (policy_lipschitz select) needs the policy's replay"
            )
        self.choices: dict[int, LipschitzChoice] = {}  # the policy's L chosen at each choice point (trajectories)
        self._acting_lipschitz: LipschitzConstant | None = None  # the current policy's (set where it is built)
        self.prior_count = int(json.loads(config.prior)["trajectories"]) if config.prior else 0
        self.certifier = certifier_for(self.spec, with_policy=self.prior_count > 0)
        self.rows: list[EpisodeRow] = []
        self.certificate: Certificate | None = None
        self.dataset = Dataset(config.state_dim, config.action_dim)  # every stored trajectory, in order
        self.policy_data = self.dataset  # the prefix the policy acts on (shorter only while checks hold data back)
        if store is not None:
            self._resume(store)
        if self.prior_count and not self.rows and self.dataset.num_trajectories == 0:  # a new run, with its start
            self._start_from(prior, store)
        self.policy = self._new_policy()

    # ------------------------------------------------------------------ state
    @property
    def next_episode(self) -> int:
        return len(self.rows)

    @property
    def oracle_calls(self) -> int:
        """Expert answers this run asked for (the trajectories it started with are not its calls)."""
        return self.dataset.num_trajectories - self.prior_count

    @property
    def held_back(self) -> int:
        """Stored trajectories not yet part of the policy (oracle mode during a streak; a verification)."""
        return self.dataset.num_trajectories - self.policy_data.num_trajectories

    def _passed(self, row: EpisodeRow) -> bool:
        return self.spec.passes(row.checked_gap)

    def held_back_after(self, episodes: int) -> int:
        """Trajectories stored among the first ``episodes`` episodes but not yet part of the policy
        then (held while its test ran); replays the rule's decisions."""
        rows = self.rows[:episodes]
        return self.prior_count + sum(row.trajectories_stored for row in rows) - self._replay(rows)[1]

    def _replay(self, rows: Sequence[EpisodeRow]) -> tuple[Certifier | MixtureCertifier, int]:
        """A fresh certifier fed ``rows``, and how many stored trajectories the policy held after them."""
        certifier = certifier_for(self.spec, with_policy=self.prior_count > 0)
        stored = joined = self.prior_count
        for row in rows:
            stored += row.trajectories_stored
            if not certifier.observe(row.checked_gap, not self._passed(row)).frozen:
                joined = stored
        return certifier, joined

    def _resume(self, store: RunStore) -> None:
        """Take up the stored run: refused (naming each setting, its recorded value and the asked one) unless this run
        asks for what the file records; a file that never recorded some settings says so (UnrecordedSettings)."""
        asked = self.config.metadata()
        problems = store.metadata.mismatches(asked)
        if problems:
            raise RunFileError(f"{store.path} belongs to another run:\n  " + "\n  ".join(problems))
        notice = store.metadata.unrecorded_notice(asked, store.path)
        if notice:
            warnings.warn(notice, UnrecordedSettings, stacklevel=2)
        self.dataset = store.load_dataset()
        self.policy_data = self.dataset
        self.rows = store.episodes()
        for expected, row in enumerate(self.rows):
            if row.episode != expected:
                raise RunFileError(f"{store.path} is damaged: episode {expected} is missing from its log")
        if not self.rows and self.dataset.num_trajectories == 0:
            return  # a new file: nothing to take up
        self.certifier, joined = self._replay(self.rows)
        called = self.prior_count + sum(row.trajectories_stored for row in self.rows)
        if called != self.dataset.num_trajectories:
            raise RunFileError(
                f"{store.path} is inconsistent: its episodes asked the oracle for {called} trajectories, "
                f"{self.dataset.num_trajectories} trajectories are stored"
            )
        stored = store.certificate()
        if stored is not None:
            self.certificate = Certificate.from_record(stored, self.spec)
        else:
            self._set_policy_prefix(joined)

    def _start_from(self, prior: Dataset | None, store: RunStore | None) -> None:
        """A new run that starts with another run's trajectories (config.prior): stored first, asked by no episode."""
        if prior is None or prior.num_trajectories != self.prior_count:
            raise ValueError(f"the run starts with {self.prior_count} trajectories of another run: give them")
        trajectories = [prior.trajectory(index) for index in range(prior.num_trajectories)]
        if store is not None:
            store.record_prior(trajectories)
        for item in trajectories:
            self.dataset.append(item)

    def _new_policy(self) -> NonparametricPolicy:
        """The policy over its data now, by the L its data's choice point gives (chosen here, in the loop's thread)."""
        self._acting_lipschitz = self._lipschitz_for(self.policy_data.num_trajectories)
        return make_policy(self.policy_data, self.spec, self.control, self._acting_lipschitz)

    @property
    def policy_spec(self) -> PolicySpec | None:
        """How this run's policy acts, as one value (None where the task states no control space)."""
        return None if self.control is None else policy_spec(self.spec, self.control, self.policy_lipschitz)

    @property
    def policy_lipschitz(self) -> LipschitzConstant | None:
        """The L the current policy acts by when the run chose its own (policy_lipschitz select); None: the claim's.
        Read only: another thread (the supervisor's dataset service) may ask while the loop runs an episode."""
        return self._acting_lipschitz

    def _lipschitz_for(self, count: int) -> LipschitzConstant | None:
        """The L a policy over ``count`` trajectories acts by: its choice point's, made there if not yet."""
        point = choice_point(count) if self.config.policy_lipschitz == "select" else 0
        if not point:
            return None
        return self._choice_at(point).constant()

    def policy_over(self, count: int) -> NonparametricPolicy:
        """The run's policy over its first ``count`` trajectories (an evaluation of an earlier policy), by the L it
        acted by then."""
        if count == self.policy_data.num_trajectories:
            return self.policy
        stored = self.store.lipschitz_choices() if self.store is not None else {}
        lipschitz = acted_by({**stored, **self.choices}, count) if self.config.policy_lipschitz == "select" else None
        return make_policy(self.dataset.prefix(count), self.spec, self.control, lipschitz)

    def _choice_at(self, point: int) -> LipschitzChoice:
        """The choice at ``point`` trajectories: made once (on the first ``point`` stored trajectories and the starts
        of the episodes up to the one that stored the last of them), then kept, in the run file too."""
        if point in self.choices:
            return self.choices[point]
        stored = self.store.lipschitz_choices() if self.store is not None else {}
        if point in stored:
            self.choices[point] = stored[point]
            return stored[point]
        assert self.replay is not None
        replay, control = self.replay, self.control
        last = max(
            (row.episode for row in self.rows if row.trajectory is not None and row.trajectory < point), default=-1
        )

        def build(data: Dataset, lipschitz: float) -> NonparametricPolicy:
            constant = LipschitzConstant(lipschitz, "selected")
            return make_policy(data, self.spec, control, constant)

        def run(state: FloatArray, policy: NonparametricPolicy, robot: Robot | None) -> tuple[FloatArray, float]:
            found = replay.rollout(state, policy, robot)
            return found.states, found.total_return

        choice = choose_lipschitz(
            self.dataset.prefix(point), recent_starts(self.rows, last), self.spec.lipschitz.value, build, run,
            self.success,
        )  # fmt: skip
        if self.store is not None:
            self.store.record_lipschitz_choice(choice)
        self.choices[point] = choice
        return choice

    def _policy_grew(self, before: int) -> None:
        """The policy's data grew from ``before`` trajectories: a new choice point gives the policy its new L."""
        now = self.policy_data.num_trajectories
        if self.config.policy_lipschitz == "select" and choice_point(now) != choice_point(before):
            self.policy = self._new_policy()

    def _set_policy_prefix(self, count: int) -> None:
        self.policy_data = self.dataset if count == self.dataset.num_trajectories else self.dataset.prefix(count)

    # ------------------------------------------------------------------ one episode
    def _drive(self, episode: int, s0: FloatArray, robot: Robot | None) -> float | None:
        if self.driver is None or len(self.policy_data) == 0:
            return None
        if robot is None:
            ret = self.driver.run_episode(episode, s0, self.policy)
        else:
            ret = self.driver.run_episode(episode, s0, self.policy, robot)
        return None if ret is None else float(ret)

    def _ask_oracle(self, s0: FloatArray, robot: Robot | None) -> Trajectory:
        if robot is None:
            answer = self.oracle.trajectory(s0)
        else:
            answer = self.oracle.trajectory(s0, robot=robot)  # type: ignore[call-arg]  # a RobotOracle
        trajectory = self.dataset.validate(answer.states, answer.actions, answer.values, answer.gains)
        if self.spec.certify == "oracle":
            ret = answer.expert_return
            if ret is None or not math.isfinite(ret):
                raise ValueError("certify=oracle needs the expert's own return at s0, and the expert gave none")
            trajectory = replace(trajectory, expert_return=float(ret))
        return trajectory

    def _check(
        self, s0: FloatArray, v_ub: float, policy_return: float | None, answer: Trajectory | None, robot: Robot | None
    ) -> float:
        """The checked quantity at s0; +inf when it cannot be computed (no policy yet, no return)."""
        if len(self.policy_data) == 0 or (self.spec.certify != "surrogate" and policy_return is None):
            return math.inf
        if self.spec.certify == "success":
            met = self._policy_success(s0, robot)
            return math.inf if met is None else SUCCESS_CHECK[met]
        if self.spec.certify == "rollout":
            assert self.basis is not None and self.basis.tail is not None and policy_return is not None
            return v_ub + self.basis.tail(s0) - policy_return
        assert answer is not None and answer.expert_return is not None and policy_return is not None
        return answer.expert_return - policy_return

    def run_episode(self) -> EpisodeRow:
        """One iteration of Algorithm 1 (lines 6-17), in the order the certification mode needs."""
        started = time.perf_counter()
        episode = self.next_episode
        s0 = np.asarray(self.initial_state(episode), dtype=np.float64)
        robot = None if self.robots is None else self.robots(episode)
        v_lb, v_ub = float(self.policy.lower(s0).value[0]), float(self.policy.upper(s0).value[0])
        gap = v_ub - v_lb if len(self.policy_data) else math.inf
        mode = self.spec.certify
        trajectory: Trajectory | None = None
        policy_return: float | None = None
        if mode == "surrogate":
            checked = gap
            if not self.spec.passes(checked):
                trajectory = self._ask_oracle(s0, robot)
        else:
            policy_return = self._drive(episode, s0, robot)
            if mode == "oracle":
                trajectory = self._ask_oracle(s0, robot)
            checked = self._check(s0, v_ub, policy_return, trajectory, robot)
            if not self.spec.passes(checked) and trajectory is None:
                trajectory = self._ask_oracle(s0, robot)
        failed = not self.spec.passes(checked)
        explored = self._explore(s0, robot) if failed and trajectory is not None and policy_return is not None else []
        index = self.dataset.num_trajectories if trajectory is not None else None
        status = self.certifier.preview(checked, failed)
        new = [] if trajectory is None else [trajectory, *explored]
        joins = 0 if status.frozen else sum(len(t) for t in new)  # this episode's data, joining now
        expert_value = self.expert_value(s0) if self.expert_value is not None else None
        if expert_value is None and trajectory is not None:
            expert_value = float(trajectory.values[0])
        expert_success = self._met(trajectory.states) if trajectory is not None else None
        policy_success = self._policy_success(s0, robot) if policy_return is not None else None
        row = EpisodeRow(
            episode=episode,
            initial_state=state_tuple(s0),
            v_lb=v_lb,
            v_ub=v_ub,
            gap=gap,
            oracle_called=trajectory is not None,
            trajectory=index,
            dataset_size=len(self.policy_data) if status.frozen else len(self.dataset) + joins,
            oracle_calls=self.oracle_calls + len(new),
            quiet_episodes=status.quiet_episodes,
            window=status.window,
            required=status.required,
            certified=status.certified,
            expert_value=expert_value,
            policy_return=policy_return,
            wall_time=time.perf_counter() - started,
            checked_gap=checked,
            test=status.test,
            test_delta=status.test_delta,
            explored=len(explored),
            expert_success=expert_success,
            policy_success=policy_success,
            robot=None if robot is None else robot.record(),
        )
        # Persist before anything else can fail: expert data is the expensive part.
        if self.store is not None:
            self.store.record_episode(row, trajectory, explored)
        self.rows.append(row)  # before the data joins: a choice of the policy's L reads this episode's start
        if new:
            first = self.dataset.num_trajectories
            for item in new:
                self.dataset.append(item)
            if status.frozen:  # the policy under test stays as it is until its test ends
                self._hold_back(len(new))
            elif self.policy_data is self.dataset:
                self._policy_grew(first)
                for joined in range(first, self.dataset.num_trajectories):
                    self._joined(joined)
            else:
                self._release_held()
        elif not status.frozen and self.held_back:  # a verification ended on a check without a trajectory
            self._release_held()
        self.certifier.observe(checked, failed)
        if mode == "surrogate" and self.driver is not None:
            ret = self._drive(episode, s0, robot)
            if ret is not None:
                row = replace(row, policy_return=ret, policy_success=self._policy_success(s0, robot))
                self.rows[-1] = row
                if self.store is not None:
                    self.store.set_policy_return(episode, ret, row.policy_success)
        for observer in self.observers:
            observer.on_episode(row, status)
        if status.certified and self.certificate is None:
            self.certificate = self._make_certificate(status)
            if self.store is not None:
                self.store.set_certificate(self.certificate.record())
            for observer in self.observers:
                observer.on_certificate(self.certificate)
            if self.held_back:
                self._release_held()
        return row

    def _met(self, states: FloatArray) -> bool | None:
        """Whether an episode with these stored states met the task's success criterion (None: the task states none)."""
        return None if self.success is None else self.success.met(states)

    def _policy_success(self, s0: FloatArray, robot: Robot | None) -> bool | None:
        """The success criterion on the current policy's own rollout from s0 (the one the episode measured)."""
        if self.success is None or self.replay is None or len(self.policy_data) == 0:
            return None
        return self.success.met(self.replay.rollout(s0, self.policy, robot).states)

    def success_counts(self) -> SuccessCounts:
        """The expert's and the policy's successes so far; the policy's only where the check measured its rollout."""
        return SuccessCounts.of(self.rows, policy=self.spec.certify != "surrogate")

    def _explore(self, s0: FloatArray, robot: Robot | None) -> list[Trajectory]:
        """After a failed check: the expert's trajectory from where the checked policy's rollout left the data."""
        if self.explorer is None:
            return []
        state = self.explorer.state_to_ask(s0, self.policy, robot)
        return [] if state is None else [self._ask_oracle(state, robot)]

    def _hold_back(self, count: int = 1) -> None:
        """The first held trajectories split the policy's data from the stored data."""
        if self.policy_data is self.dataset:
            self._set_policy_prefix(self.dataset.num_trajectories - count)
            self.policy = self._new_policy()

    def _joined(self, index: int | None) -> None:
        if index is None:
            return
        for observer in self.observers:
            observer.on_trajectory(index, self.dataset.trajectory(index))

    def _release_held(self) -> None:
        """The streak ended: held trajectories join the policy, in stored order."""
        first = self.policy_data.num_trajectories
        self.policy_data = self.dataset
        self.policy = self._new_policy()
        for index in range(first, self.dataset.num_trajectories):
            self._joined(index)

    def _make_certificate(self, status: CertificationStatus) -> Certificate:
        return author_certificate(
            self.spec,
            self.basis,
            status,
            task=self.config.task,
            horizon=self.config.horizon,
            episodes=len(self.rows),
            oracle_calls=self.oracle_calls,
            dataset_size=len(self.policy_data),
            policy_trajectories=self.policy_data.num_trajectories,
            success=self.measured_success(),
            robots=describe_robots(self.config.uncertainty),
            reference=REFERENCE[self.config.expert_model],
            robot=None if self.robot_facts is None else self.robot_facts.claim(),
            policy_lipschitz=None if self.policy_lipschitz is None else self.policy_lipschitz.value,
        )

    def measured_success(self) -> MeasuredSuccess:
        """What the run measured of the task's success, in the words the certificate states."""
        counts = self.success_counts()
        return MeasuredSuccess(
            criterion=None if self.success is None else self.success.describe(),
            expert=(counts.expert_successes, counts.expert_answers),
            policy=None if self.spec.certify == "surrogate" else (counts.policy_successes, counts.policy_checked),
            relative=self.spec.certify != "success",
        )

    # ------------------------------------------------------------------ whole run
    def run(self, max_episodes: int) -> RunResult:
        """Run until certified or until ``max_episodes`` episodes exist in total; an episode the plant cut short
        (EpisodeCut) is run again, and its driver decides when a plant that keeps cutting is gone."""
        while self.certificate is None and self.next_episode < max_episodes:
            try:
                self.run_episode()
            except EpisodeCut:
                continue
        return RunResult(len(self.rows), self.oracle_calls, len(self.policy_data), self.certificate, self.rows)
