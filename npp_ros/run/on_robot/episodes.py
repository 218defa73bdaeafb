"""The policy's episodes on the robot itself: the run's starts, its episode driver and the rollout its check judges.

Each episode starts from the robot's reset (asked for the run's s0 of that episode, or the robot's own) and the
measured start is the episode's s0; the policy's controller then reads the measured state once per control period
and its command goes to the robot, for H periods. What the robot measured, the commands sent and the task's reward
(the model's reward of the measured state and the command) are stored in the run file the moment the episode ends,
before its check is: a run stopped between the two takes that same episode up again rather than running the robot
anew (a stop must never decide a check). A fault cuts the episode: it is stored with its reason and marked, never
counted as a check, and the episode runs again from a new reset; ``max_faults`` faults in a row mean the robot is
gone (RobotGone), and the run stops with everything kept. An episode a stop (Ctrl-C) cuts is kept and marked the
same way: neither a fault nor a stop ever makes a check, so neither can choose which checks count.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from npp_ros.certificate.authoring import RobotClaim
from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import FloatArray
from npp_ros.run.loop import EpisodeCut, EpisodeInterrupted
from npp_ros.run.on_robot.identity import RobotIdentity
from npp_ros.run.on_robot.link import Reading, RobotFault, RobotGone, RobotLink
from npp_ros.run.records import RobotEpisode, state_tuple
from npp_ros.run.store import RunStore
from npp_ros.tasks.rollout import Rollout, episode_return
from npp_ros.tasks.success import SuccessCriterion
from npp_ros.tasks.task import Plant
from npp_ros.tasks.uncertainty import Robot

DEFAULT_MAX_FAULTS = 5


@dataclass
class _Started:
    """The episode under way: its index and the start the robot measured."""

    episode: int
    requested: FloatArray | None
    start: Reading


class RobotEpisodes:
    """The robot as a run's plant: ``initial_state`` (the loop's starts), ``run_episode`` (its driver) and
    ``rollout`` (what its check judges: the episode the robot just ran). ``model`` is a plant of the task's model,
    used only to compute the reward of each measured state and command; ``requested(episode)`` is the start asked of
    the reset (None: the robot's own)."""

    def __init__(
        self,
        link: RobotLink,
        model: Plant,
        horizon: int,
        identity: RobotIdentity,
        *,
        requested: Callable[[int], FloatArray | None],
        success: SuccessCriterion | None,
        store: RunStore | None = None,
        max_faults: int = DEFAULT_MAX_FAULTS,
        log: Callable[[str], None] = lambda text: None,
        prior: str = "",
    ) -> None:
        self.link, self.model, self.horizon, self.identity = link, model, int(horizon), identity
        self.requested, self.success, self.store = requested, success, store
        self.max_faults, self.log = int(max_faults), log
        self.kept: list[RobotEpisode] = [] if store is None else store.robot_episodes()
        self._started: _Started | None = None
        self._faults_in_a_row = 0
        self._last: Rollout | None = None  # the episode the robot ran last, which the loop's check judges
        self.answering = 0  # the episode whose check ran last: an expert's plan run after it is stored under it
        self.prior = prior  # the trajectories the run started with from another run, in words

    # ------------------------------------------------------------------ records
    def _pending(self, episode: int) -> RobotEpisode | None:
        """A check the robot ran to its end for ``episode`` whose row the run has not stored (it stopped between)."""
        done = [kept for kept in self.kept if kept.episode == episode and kept.role == "check" and kept.fault is None]
        return done[-1] if done else None

    def _keep(self, item: RobotEpisode) -> None:
        if self.store is not None:
            self.store.record_robot_episode(item)
        self.kept.append(item)

    def _record(
        self,
        episode: int,
        role: str,
        requested: FloatArray | None,
        start: Reading | None,
        states: list[FloatArray],
        actions: list[FloatArray],
        rewards: list[float],
        end_time: float,
        late: int,
        fault: str | None,
    ) -> RobotEpisode:
        n, m = self.model.state_dim, self.model.action_dim
        s = np.array(states, dtype=np.float64).reshape(-1, n)
        a = np.array(actions, dtype=np.float64).reshape(-1, m)
        r = np.array(rewards, dtype=np.float64)
        steps = len(r)
        success = None
        if fault is None and role == "check" and self.success is not None:
            success = bool(self.success.met(s))
        item = RobotEpisode(
            id=len(self.kept),
            episode=episode,
            role=role,
            requested=None if requested is None else state_tuple(requested),
            start=() if start is None else state_tuple(start.state),
            steps=steps,
            started_at=0.0 if start is None else start.time,
            robot_time=0.0 if start is None else max(end_time - start.time, 0.0),
            late_commands=late,
            fault=fault,
            success=success,
            policy_return=None if fault is not None else episode_return(r),
            rollout=RobotEpisode.pack(s[:steps], a[:steps], r),
        )
        self._keep(item)
        return item

    def _fault(self, episode: int, role: str, text: str) -> None:
        """Count a fault in a row; past max_faults the robot is gone."""
        self._faults_in_a_row += 1
        self.log(f"episode {episode}: the robot cut the {role} short: {text} ({self._faults_in_a_row} in a row)")
        if self._faults_in_a_row >= self.max_faults:
            raise RobotGone(
                f"the robot faulted {self._faults_in_a_row} times in a row (last: {text}); everything it ran is "
                "stored, and the run resumes where it stopped"
            )

    # ------------------------------------------------------------------ the loop's parts
    def reset(self, episode: int, requested: FloatArray | None, role: str) -> Reading:
        """The robot brought to a start; a failed reset is stored as a fault and tried again."""
        while True:
            try:
                reading = self.link.reset(requested)
            except RobotFault as exc:
                self._record(episode, role, requested, None, [], [], [], 0.0, 0, f"reset: {exc}")
                self._fault(episode, role, f"reset: {exc}")
                continue
            return reading

    def initial_state(self, episode: int) -> FloatArray:
        """The episode's s0: the start the robot measured after its reset (or a kept check's, taken up again)."""
        pending = self._pending(episode)
        if pending is not None:
            self._started = None
            return np.array(pending.start, dtype=np.float64)
        requested = self.requested(episode)
        start = self.reset(episode, requested, "check")
        self._started = _Started(episode, requested, start)
        return np.array(start.state, dtype=np.float64)

    def run_episode(
        self, episode: int, initial_state: FloatArray, policy: NonparametricPolicy, robot: Robot | None = None
    ) -> float:
        """The policy on the robot from its measured start for H periods; its return on the measured states."""
        self.answering = episode
        pending = self._pending(episode)
        if pending is not None:
            states, actions, rewards = pending.arrays(self.model.state_dim, self.model.action_dim)
            self._last = Rollout(states, actions, rewards)
            self.log(f"episode {episode}: the robot's episode kept before the stop is taken up again")
            assert pending.policy_return is not None
            return float(pending.policy_return)
        started = self._started
        if started is None or started.episode != episode:
            raise RuntimeError(f"episode {episode} was not started from a reset (initial_state first)")
        controller = policy.controller()
        item = self.run_law(episode, "check", started.requested, started.start, controller, self.horizon)
        self._started = None
        if item.fault is not None:
            raise EpisodeCut(f"episode {episode}: {item.fault}")
        states, actions, rewards = item.arrays(self.model.state_dim, self.model.action_dim)
        self._last = Rollout(states, actions, rewards)
        assert item.policy_return is not None
        return float(item.policy_return)

    def run_law(
        self,
        episode: int,
        role: str,
        requested: FloatArray | None,
        start: Reading,
        law: Callable[[FloatArray], FloatArray],
        steps: int,
    ) -> RobotEpisode:
        """``law`` on the robot from ``start`` for ``steps`` periods, stored as it ended (cut short by a fault, or
        not); the safe command follows either way."""
        states: list[FloatArray] = []
        actions: list[FloatArray] = []
        late_before = self.link.late_commands
        reading = start
        fault = None
        stopped: EpisodeInterrupted | None = None
        try:
            for _ in range(steps):
                x = np.asarray(reading.state, dtype=np.float64)
                u = np.asarray(law(x), dtype=np.float64)
                reading = self.link.step(u)
                states.append(x)
                actions.append(u)
        except RobotFault as exc:
            fault = str(exc)
        except EpisodeInterrupted as exc:  # the run stops: what the robot ran is kept and marked, then the stop goes on
            stopped, fault = exc, f"stopped: {exc}"
        finally:
            self.link.hold()  # the safe command first, before anything is computed or stored
        item = self._store_run(episode, role, requested, start, states, actions, reading, late_before, fault)
        if stopped is not None:
            raise stopped
        if fault is not None:
            self._fault(episode, role, fault)
        else:
            self._faults_in_a_row = 0
        return item

    def _store_run(
        self,
        episode: int,
        role: str,
        requested: FloatArray | None,
        start: Reading,
        states: list[FloatArray],
        actions: list[FloatArray],
        last: Reading,
        late_before: int,
        fault: str | None,
    ) -> RobotEpisode:
        rewards = [self.reward(x, u) for x, u in zip(states, actions, strict=True)]  # after the robot has stopped
        late = self.link.late_commands - late_before
        return self._record(episode, role, requested, start, states, actions, rewards, last.time, late, fault)

    def reward(self, state: FloatArray, command: FloatArray) -> float:
        """The task's reward of a measured state and the command sent, as the model gives it."""
        self.model.reset(state)
        return float(self.model.step(command))

    def close_start(self) -> None:
        """Before an answer: a start the policy did not drive from (no data yet) is kept as such, steps 0."""
        started = self._started
        if started is None:
            return
        self._started = None
        self.answering = started.episode
        self._record(started.episode, "start", started.requested, started.start, [], [], [], started.start.time, 0,
                     None)  # fmt: skip

    def rollout(self, initial_state: FloatArray, policy: NonparametricPolicy, robot: Robot | None = None) -> Rollout:
        """The episode the robot just ran: what the loop's success check judges (never a re-run on a model)."""
        if self._last is None:
            raise RuntimeError("no robot episode has run yet")
        return self._last

    # ------------------------------------------------------------------ the certificate's words
    def claim(self) -> RobotClaim:
        counted = {kept.episode for kept in self.kept if kept.role == "check" and kept.fault is None}
        return RobotClaim(
            robot=self.identity.describe(),
            starts=self.identity.starts_words(),
            checks=len(counted),
            answers=sum(kept.role == "answer" and kept.fault is None for kept in self.kept),
            faults=sum(kept.fault is not None for kept in self.kept),
            robot_time=sum(kept.robot_time for kept in self.kept),
            late_commands=sum(kept.late_commands for kept in self.kept),
            prior=self.prior,
        )
