"""Algorithm 1 (NPP) as one reusable loop.

The loop owns the algorithm's decisions: sample s0, check the policy at s0 with the quantity the
run certifies on (certification.py), ask the oracle when the check fails, append and persist,
certify. What it talks to plugs in: where s0 comes from, the oracle, an episode driver (the
policy's rollout, in process or through the ROS graph) and observers. The supervisor node and
in-process experiments run this same class, so the same seed gives the same dataset and gap
sequence in both.

Order within an episode, per mode:
- ``surrogate`` (the paper): gap V_ub - V_lb at s0; oracle if it exceeds epsilon; then the
  (updated) policy drives the episode, its return recorded for information.
- ``rollout``: the current policy drives the episode first; the check V_ub + tail - R^pi decides,
  and a failed check sends s0 to the oracle.
- ``oracle``: the current policy drives the episode and the oracle answers for s0 in every
  episode; the check is V^E(s0) - R^pi(s0). A test must see one frozen policy, so trajectories
  from passed checks are held back (stored at once, never lost) and join the policy's data when
  the streak ends: with a failed check, or after the certificate is issued.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Protocol

import numpy as np

from npp_ros.bounds import NonparametricPolicy
from npp_ros.certification import Certificate, CertificationSpec, CertificationStatus, Certifier, assumption_list
from npp_ros.dataset import Dataset, FloatArray, Trajectory
from npp_ros.storage import EpisodeRow, RunFileError, RunMetadata, RunStore, state_tuple
from npp_ros.values import ValueBasis


class Oracle(Protocol):
    """The TrajectoryOptimizer: an expert trajectory from a given state."""

    def trajectory(self, initial_state: FloatArray) -> Trajectory: ...


class EpisodeInterrupted(RuntimeError):
    """The run is stopping while an episode is under way: nothing of the episode is recorded, and a
    resumed run plays it again from the same s0 (a pause or a restart never decides a check)."""


class EpisodeDriver(Protocol):
    """Lets the current policy drive one episode from s0; returns its return, or None when the policy
    cannot drive at all (no data). A driver that loses a result asks for it again or runs the episode
    again; it raises EpisodeInterrupted only when the run is stopping."""

    def run_episode(self, episode: int, initial_state: FloatArray, policy: NonparametricPolicy) -> float | None: ...


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

    Two runs with equal configs give equal numbers. ``run_setup.build_config`` builds one for a task.
    """

    task: str
    seed: int
    state_dim: int
    action_dim: int
    spec: CertificationSpec
    horizon: int = 1000
    gamma: float = 1.0
    plant_fingerprint: str = ""  # the compiled model's SHA-256 (Plant.model_sha256): which plant the data are of

    def metadata(self) -> RunMetadata:
        """What the run file records of this config: its own fields, the spec's record, where L came from."""
        own = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "spec"}
        return RunMetadata(**own, **self.spec.record(), lipschitz_detail=self.spec.lipschitz.detail)


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
    ) -> None:
        self.config = config
        self.spec = config.spec
        certify = self.spec.certify
        if certify != "surrogate" and driver is None:
            raise ValueError(f"certify={certify} checks the policy's own return: it needs the policy's rollouts")
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
        self.certifier = Certifier(self.spec)
        self.rows: list[EpisodeRow] = []
        self.certificate: Certificate | None = None
        self.dataset = Dataset(config.state_dim, config.action_dim)  # every stored trajectory, in order
        self.policy_data = self.dataset  # the prefix the policy acts on (shorter only while checks hold data back)
        if store is not None:
            self._resume(store)
        self.policy = NonparametricPolicy(self.policy_data, self.spec.lipschitz.value)

    # ------------------------------------------------------------------ state
    @property
    def next_episode(self) -> int:
        return len(self.rows)

    @property
    def oracle_calls(self) -> int:
        return self.dataset.num_trajectories

    @property
    def held_back(self) -> int:
        """Stored trajectories not yet part of the policy (oracle mode, during a streak)."""
        return self.dataset.num_trajectories - self.policy_data.num_trajectories

    def _passed(self, row: EpisodeRow) -> bool:
        return row.checked_gap is not None and row.checked_gap <= self.spec.epsilon

    def held_back_after(self, episodes: int) -> int:
        """Oracle mode: trajectories of the passed checks since the last failed one, among the first
        ``episodes`` episodes; they were stored but not yet part of the policy."""
        if self.spec.certify != "oracle":
            return 0
        held = 0
        for row in reversed(self.rows[:episodes]):
            if not self._passed(row):
                break
            held += int(row.oracle_called)
        return held

    def _resume(self, store: RunStore) -> None:
        problems = store.metadata.mismatches(self.config.metadata())
        if problems:
            raise RunFileError(f"{store.path} belongs to another run:\n  " + "\n  ".join(problems))
        self.dataset = store.load_dataset()
        self.policy_data = self.dataset
        self.rows = store.episodes()
        for expected, row in enumerate(self.rows):
            if row.episode != expected:
                raise RunFileError(f"{store.path} is damaged: episode {expected} is missing from its log")
            self.certifier.observe(row.checked_gap, not self._passed(row))
        called = sum(row.oracle_called for row in self.rows)
        if called != self.dataset.num_trajectories:
            raise RunFileError(
                f"{store.path} is inconsistent: {called} episodes called the oracle, "
                f"{self.dataset.num_trajectories} trajectories are stored"
            )
        stored = store.certificate()
        if stored is not None:
            self.certificate = Certificate.from_record(stored, self.spec)
        elif self.spec.certify == "oracle":
            self._set_policy_prefix(self.dataset.num_trajectories - self.held_back_after(len(self.rows)))

    def _set_policy_prefix(self, count: int) -> None:
        self.policy_data = self.dataset if count == self.dataset.num_trajectories else self.dataset.prefix(count)

    # ------------------------------------------------------------------ one episode
    def _drive(self, episode: int, s0: FloatArray) -> float | None:
        if self.driver is None or len(self.policy_data) == 0:
            return None
        ret = self.driver.run_episode(episode, s0, self.policy)
        return None if ret is None else float(ret)

    def _ask_oracle(self, s0: FloatArray) -> Trajectory:
        answer = self.oracle.trajectory(s0)
        trajectory = self.dataset.validate(answer.states, answer.actions, answer.values)
        if self.spec.certify == "oracle":
            ret = answer.expert_return
            if ret is None or not math.isfinite(ret):
                raise ValueError("certify=oracle needs the expert's own return at s0, and the expert gave none")
            trajectory = replace(trajectory, expert_return=float(ret))
        return trajectory

    def _check(self, s0: FloatArray, v_ub: float, policy_return: float | None, answer: Trajectory | None) -> float:
        """The checked quantity at s0; +inf when it cannot be computed (no policy yet, no return)."""
        if len(self.policy_data) == 0 or (self.spec.certify != "surrogate" and policy_return is None):
            return math.inf
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
        v_lb, v_ub = float(self.policy.lower(s0).value[0]), float(self.policy.upper(s0).value[0])
        gap = v_ub - v_lb if len(self.policy_data) else math.inf
        mode, epsilon = self.spec.certify, self.spec.epsilon
        trajectory: Trajectory | None = None
        policy_return: float | None = None
        if mode == "surrogate":
            checked = gap
            if checked > epsilon:
                trajectory = self._ask_oracle(s0)
        else:
            policy_return = self._drive(episode, s0)
            if mode == "oracle":
                trajectory = self._ask_oracle(s0)
            checked = self._check(s0, v_ub, policy_return, trajectory)
            if checked > epsilon and trajectory is None:
                trajectory = self._ask_oracle(s0)
        failed = not checked <= epsilon
        index = self.dataset.num_trajectories if trajectory is not None else None
        status = self.certifier.preview(checked, failed)
        expert_value = self.expert_value(s0) if self.expert_value is not None else None
        if expert_value is None and trajectory is not None:
            expert_value = float(trajectory.values[0])
        row = EpisodeRow(
            episode=episode,
            initial_state=state_tuple(s0),
            v_lb=v_lb,
            v_ub=v_ub,
            gap=gap,
            oracle_called=trajectory is not None,
            trajectory=index,
            dataset_size=len(self.dataset) + len(trajectory) if failed and trajectory else len(self.policy_data),
            oracle_calls=self.oracle_calls + int(trajectory is not None),
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
        )
        # Persist before anything else can fail: expert data is the expensive part.
        if self.store is not None:
            self.store.record_episode(row, trajectory)
        if trajectory is not None:
            self.dataset.append(trajectory)
            if not failed:  # oracle mode: the policy under test stays frozen until its streak ends
                self._hold_back()
            elif self.policy_data is self.dataset:
                self._joined(index)
            else:
                self._release_held()
        self.certifier.observe(checked, failed)
        self.rows.append(row)
        if mode == "surrogate" and self.driver is not None:
            ret = self._drive(episode, s0)
            if ret is not None:
                row = replace(row, policy_return=ret)
                self.rows[-1] = row
                if self.store is not None:
                    self.store.set_policy_return(episode, ret)
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

    def _hold_back(self) -> None:
        """The first held trajectory splits the policy's data from the stored data."""
        if self.policy_data is self.dataset:
            self._set_policy_prefix(self.dataset.num_trajectories - 1)
            self.policy = NonparametricPolicy(self.policy_data, self.spec.lipschitz.value)

    def _joined(self, index: int | None) -> None:
        if index is None:
            return
        for observer in self.observers:
            observer.on_trajectory(index, self.dataset.trajectory(index))

    def _release_held(self) -> None:
        """The streak ended: held trajectories join the policy, in stored order."""
        first = self.policy_data.num_trajectories
        self.policy_data = self.dataset
        self.policy = NonparametricPolicy(self.policy_data, self.spec.lipschitz.value)
        for index in range(first, self.dataset.num_trajectories):
            self._joined(index)

    def _assumptions(self) -> tuple[str, ...]:
        spec, basis = self.spec, self.basis
        lipschitz = (
            f"L = {spec.lipschitz.value:.6g} ({spec.lipschitz.source}) bounds the slope of the stored value function "
            f"on every segment between an initial state and a data point"
        )
        if no_bound := self._no_lipschitz_bound():
            lipschitz += f": it does NOT hold here, {no_bound}"
        common = [
            "initial states are independent draws from rho, independent of the run so far",
            "the plant is deterministic, so one rollout's return is the policy's value at s0",
        ]
        if spec.certify == "rollout":
            assert basis is not None
            items = [lipschitz, "the expert's stored values equal its value function at the data points",
                     basis.tail_detail, *common]  # fmt: skip
        elif spec.certify == "oracle":
            items = ["the expert's reported return at s0 is the return of the trajectory it gives", *common,
                     "no Lipschitz constant is needed; the claim is relative to the expert's own return"]  # fmt: skip
        else:
            items = [lipschitz, "Theorem 3.4 (V_lb <= V^pi), so that the surrogate gap bounds the true gap",
                     basis.theorem_34 if basis is not None and basis.theorem_34 else
                     "Theorem 3.4's condition was not checked for this plant",
                     "initial states are independent draws from rho"]  # fmt: skip
        if spec.rule == "paper":
            items.append("the paper's one-shot test, though it is checked after every episode (not sequentially valid)")
        return assumption_list(items)

    def _no_lipschitz_bound(self) -> str:
        """Why no L bounds the stored values, where the expert knows it ("" otherwise)."""
        return self.basis.no_lipschitz_bound if self.basis is not None else ""

    def _proven(self) -> bool:
        if self.spec.rule == "paper":
            return False
        if self.spec.certify != "oracle" and self._no_lipschitz_bound():
            return False  # the claim rests on an L that cannot exist for these values
        if self.spec.certify == "surrogate":
            return bool(self.basis is not None and self.basis.theorem_34_holds)
        return True

    def _make_certificate(self, status: CertificationStatus) -> Certificate:
        certify = self.spec.certify
        if certify == "oracle":
            value = f"the expert's own H-step return V^E_H (H = {self.config.horizon}), as the oracle reports it"
        elif certify == "rollout" and self.basis is not None:
            value = self.basis.value
        else:
            value = "V*, the value function the expert's stored values describe"
        policy_trajectories = self.policy_data.num_trajectories
        return Certificate(
            task=self.config.task,
            spec=self.spec,
            episodes=len(self.rows),
            oracle_calls=self.oracle_calls,
            dataset_size=len(self.policy_data),
            policy_trajectories=policy_trajectories,
            window=status.window,
            required=status.required,
            test=status.test,
            delta_spent=status.test_delta,
            value=value,
            statement=self.spec.statement(status.window, value, policy_trajectories, status.test),
            proven=self._proven(),
            assumptions=self._assumptions(),
        )

    # ------------------------------------------------------------------ whole run
    def run(self, max_episodes: int) -> RunResult:
        """Run until certified or until ``max_episodes`` episodes exist in total."""
        while self.certificate is None and self.next_episode < max_episodes:
            self.run_episode()
        return RunResult(len(self.rows), self.oracle_calls, len(self.policy_data), self.certificate, self.rows)
