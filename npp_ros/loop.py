"""Algorithm 1 (NPP) as one reusable loop.

The loop owns the algorithm's decisions: sample s0, compute the surrogate gap, ask the oracle
when the gap exceeds epsilon, append and persist, certify. What it talks to plugs in: where s0
comes from, the oracle, an optional episode driver (the policy's rollout, in process or through
the ROS graph) and observers. The supervisor node and in-process experiments run this same
class, so the same seed gives the same dataset and gap sequence in both.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Protocol

import numpy as np

from npp_ros.bounds import NonparametricPolicy
from npp_ros.certification import Certificate, CertificationSpec, CertificationStatus, Certifier, Condition
from npp_ros.dataset import Dataset, FloatArray, Trajectory
from npp_ros.lipschitz import LipschitzConstant
from npp_ros.storage import EpisodeRow, RunFileError, RunMetadata, RunStore, state_tuple


class Oracle(Protocol):
    """The TrajectoryOptimizer: an expert trajectory from a given state."""

    def trajectory(self, initial_state: FloatArray) -> Trajectory: ...


class EpisodeDriver(Protocol):
    """Lets the current policy drive one episode from s0; returns its return (or None)."""

    def run_episode(self, episode: int, initial_state: FloatArray, policy: NonparametricPolicy) -> float | None: ...


class Observer:
    """Hooks for progress, logs and topics; override what you need."""

    def on_episode(self, row: EpisodeRow, status: CertificationStatus) -> None:
        """Called after each episode is stored."""

    def on_certificate(self, certificate: Certificate) -> None:
        """Called once, when the run certifies."""

    def on_trajectory(self, index: int, trajectory: Trajectory) -> None:
        """Called when an expert trajectory is stored, before the policy drives the episode."""


@dataclass(frozen=True)
class RunConfig:
    """Everything that defines a run; two runs with equal configs give equal numbers."""

    task: str
    seed: int
    state_dim: int
    action_dim: int
    lipschitz: LipschitzConstant
    epsilon: float
    condition: Condition = "i"
    p: float = 0.9
    delta: float = 0.1
    horizon: int = 1000
    gamma: float = 1.0
    diameter: float | None = None

    def spec(self) -> CertificationSpec:
        return CertificationSpec(self.condition, self.epsilon, self.p, self.delta, self.lipschitz.value, self.diameter)

    def metadata(self) -> RunMetadata:
        return RunMetadata(
            task=self.task, seed=self.seed, state_dim=self.state_dim, action_dim=self.action_dim,
            lipschitz=self.lipschitz.value, lipschitz_source=self.lipschitz.source,
            lipschitz_detail=self.lipschitz.detail, gamma=self.gamma, horizon=self.horizon,
            epsilon=self.epsilon, condition=self.condition, p=self.p, delta=self.delta,
        )  # fmt: skip


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
    """Algorithm 1 over pluggable parts; resumes from a run store if it holds episodes."""

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
    ) -> None:
        self.config = config
        self.spec = config.spec()
        self.oracle = oracle
        self.initial_state = initial_state
        self.store = store
        self.driver = driver
        self.observers = list(observers)
        self.expert_value = expert_value
        self.certifier = Certifier(self.spec)
        self.rows: list[EpisodeRow] = []
        self.certificate: Certificate | None = None
        self.dataset = Dataset(config.state_dim, config.action_dim)
        if store is not None:
            self._resume(store)
        self.policy = NonparametricPolicy(self.dataset, config.lipschitz.value)

    # ------------------------------------------------------------------ state
    @property
    def next_episode(self) -> int:
        return len(self.rows)

    @property
    def oracle_calls(self) -> int:
        return self.dataset.num_trajectories

    def _resume(self, store: RunStore) -> None:
        problems = store.metadata.mismatches(self.config.metadata())
        if problems:
            raise RunFileError(f"{store.path} belongs to another run:\n  " + "\n  ".join(problems))
        self.dataset = store.load_dataset()
        self.rows = store.episodes()
        for expected, row in enumerate(self.rows):
            if row.episode != expected:
                raise RunFileError(f"{store.path} is damaged: episode {expected} is missing from its log")
            self.certifier.observe(row.gap, row.oracle_called)
        called = sum(row.oracle_called for row in self.rows)
        if called != self.dataset.num_trajectories:
            raise RunFileError(
                f"{store.path} is inconsistent: {called} episodes called the oracle, "
                f"{self.dataset.num_trajectories} trajectories are stored"
            )
        if self.rows and self.rows[-1].certified:
            self.certificate = self._make_certificate(self.certifier.status())

    # ------------------------------------------------------------------ one episode
    def run_episode(self) -> EpisodeRow:
        """One iteration of Algorithm 1 (lines 6-17)."""
        started = time.perf_counter()
        episode = self.next_episode
        s0 = np.asarray(self.initial_state(episode), dtype=np.float64)
        bound_lo = self.policy.lower(s0)
        bound_hi = self.policy.upper(s0)
        v_lb, v_ub = float(bound_lo.value[0]), float(bound_hi.value[0])
        gap = v_ub - v_lb if len(self.dataset) else math.inf
        called = gap > self.spec.epsilon
        trajectory: Trajectory | None = None
        index: int | None = None
        if called:
            answer = self.oracle.trajectory(s0)
            trajectory = self.dataset.validate(answer.states, answer.actions, answer.values)
            index = self.dataset.num_trajectories
        status = self._preview_status(gap, called)
        expert_value = self.expert_value(s0) if self.expert_value is not None else None
        if expert_value is None and trajectory is not None:
            expert_value = float(trajectory.values[0])
        row = EpisodeRow(
            episode=episode,
            initial_state=state_tuple(s0),
            v_lb=v_lb,
            v_ub=v_ub,
            gap=gap,
            oracle_called=called,
            trajectory=index,
            dataset_size=len(self.dataset) + (len(trajectory) if trajectory is not None else 0),
            oracle_calls=self.oracle_calls + int(called),
            quiet_episodes=status.quiet_episodes,
            window=status.window,
            required=status.required,
            certified=status.certified,
            expert_value=expert_value,
            wall_time=time.perf_counter() - started,
        )
        # Persist before anything else can fail: expert data is the expensive part.
        if self.store is not None:
            self.store.record_episode(row, trajectory)
        if trajectory is not None and index is not None:
            self.dataset.append(trajectory)
            for observer in self.observers:
                observer.on_trajectory(index, trajectory)
        self.certifier.observe(gap, called)
        self.rows.append(row)
        if self.driver is not None:
            ret = self.driver.run_episode(episode, s0, self.policy)
            if ret is not None:
                row = replace(row, policy_return=float(ret))
                self.rows[-1] = row
                if self.store is not None:
                    self.store.set_policy_return(episode, float(ret))
        for observer in self.observers:
            observer.on_episode(row, status)
        if status.certified and self.certificate is None:
            self.certificate = self._make_certificate(status)
            if self.store is not None:
                self.store.set_certificate(asdict(self.certificate))
            for observer in self.observers:
                observer.on_certificate(self.certificate)
        return row

    def _preview_status(self, gap: float, called: bool) -> CertificationStatus:
        probe = Certifier(self.spec, list(self.certifier.gaps), self.certifier.quiet_episodes)
        return probe.observe(gap, called)

    def _make_certificate(self, status: CertificationStatus) -> Certificate:
        cfg = self.config
        return Certificate(
            task=cfg.task,
            condition=cfg.condition,
            epsilon=cfg.epsilon,
            p=cfg.p,
            delta=cfg.delta,
            lipschitz=cfg.lipschitz.value,
            lipschitz_source=cfg.lipschitz.source,
            episodes=len(self.rows),
            oracle_calls=self.oracle_calls,
            dataset_size=len(self.dataset),
            window=status.window,
            required=status.required,
            statement=self.spec.statement(status.window),
        )

    # ------------------------------------------------------------------ whole run
    def run(self, max_episodes: int) -> RunResult:
        """Run until certified or until ``max_episodes`` episodes exist in total."""
        while self.certificate is None and self.next_episode < max_episodes:
            self.run_episode()
        return RunResult(len(self.rows), self.oracle_calls, len(self.dataset), self.certificate, self.rows)
