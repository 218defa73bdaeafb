"""A run on a robot played back from its own file: the robot's stored episodes as the link, its stored answers as the
oracle. What a gate re-derives of such a run (npp_ros.run.rederive).

No model can replay a robot, but a run on one is still a function of what the robot measured: each check's commands
are the policy as it then was, acting on the states the robot measured; its success follows from those states; each
answer is what the robot did under a plan, its values from the rewards of the measured states; the certificate
follows from the checks. Playing the stored episodes back through the run's own loop recomputes every command and
compares it with the one stored, and the loop's rows and certificate are compared as any run's are. What is not
re-derived: the robot's physics (what it measured), and which plan the expert made (a plan's commands depend on
the expert's model, which the gate does not run): that the file holds what the robot did is what a signature says.
"""

from __future__ import annotations

import numpy as np

from npp_ros.policy.dataset import Dataset, FloatArray, Trajectory
from npp_ros.run.nominal_plan import tracked_answer
from npp_ros.run.on_robot.episodes import RobotEpisodes
from npp_ros.run.on_robot.link import Reading, RobotFault
from npp_ros.run.records import RobotEpisode


class RecordMismatch(Exception):
    """Playing the robot's stored episodes back, the run's loop did something else than the file says it did."""


class RecordedRobot:
    """The robot's stored episodes, in order, as a RobotLink: a reset gives the next stored start, a step checks the
    command against the stored one and gives the next stored state; a stored fault is raised where it happened."""

    def __init__(self, kept: list[RobotEpisode], state_dim: int, action_dim: int, dt: float) -> None:
        self.kept, self.state_dim, self.action_dim, self.dt = kept, state_dim, action_dim, dt
        self.late_commands = 0
        self.cursor = 0  # the next stored episode
        self._current: RobotEpisode | None = None
        self._arrays: tuple[FloatArray, FloatArray, FloatArray] | None = None
        self._step = 0

    def describe(self) -> str:
        return "the robot's stored episodes"

    def next_record(self, *roles: str) -> RobotEpisode:
        if self.cursor >= len(self.kept):
            raise RecordMismatch(f"the run asks the robot for a {self.cursor + 1}th episode; the file stores "
                                 f"{len(self.kept)}")  # fmt: skip
        item = self.kept[self.cursor]
        if item.role not in roles:
            raise RecordMismatch(f"robot episode {item.id} is stored as a {item.role}, the run asks for a {roles[0]}")
        self.cursor += 1
        return item

    def begin(self, item: RobotEpisode) -> Reading:
        """Start playing back ``item`` (its reset was asked for)."""
        if item.fault is not None and item.fault.startswith("reset: "):
            self._current = None
            raise RobotFault(item.fault[len("reset: ") :])
        self._current, self._step = item, 0
        self._arrays = item.arrays(self.state_dim, self.action_dim)
        return Reading(np.array(item.start, dtype=np.float64), item.started_at)

    def reset(self, requested: FloatArray | None) -> Reading:
        item = self.next_record("check", "start")
        if (item.requested is None) != (requested is None) or (
            requested is not None and not np.allclose(item.requested, requested, rtol=1e-12, atol=1e-12)
        ):
            raise RecordMismatch(f"robot episode {item.id}: the run asks its reset for another start than stored")
        return self.begin(item)

    def step(self, command: FloatArray) -> Reading:
        item, arrays = self._current, self._arrays
        if item is None or arrays is None:
            raise RecordMismatch("the run commands the robot outside any stored episode")
        states, actions, _ = arrays
        t = self._step
        if t >= item.steps:
            if item.fault is not None:
                raise RobotFault(item.fault)
            raise RecordMismatch(f"robot episode {item.id}: the run commands a step {t + 1}; {item.steps} are stored")
        if not np.allclose(command, actions[t], rtol=1e-9, atol=1e-9):
            raise RecordMismatch(
                f"robot episode {item.id} (episode {item.episode}), step {t}: the policy commands "
                f"{np.round(command, 6).tolist()} at the stored state; the file stores "
                f"{np.round(actions[t], 6).tolist()}"
            )
        self._step += 1
        last = self._step == item.steps
        if last:
            self.late_commands += item.late_commands
        after = states[t + 1] if t + 1 < item.steps else states[t]  # the last state read is not stored: never acted on
        when = item.started_at + (item.robot_time if last else self._step * self.dt)
        return Reading(np.array(after, dtype=np.float64), when)

    def hold(self) -> None:
        """Nothing to send: the robot is not here."""


class StoredRobotAnswers:
    """The oracle of a run on a robot played back: the stored answers in order, each checked to be what its stored
    robot episode gives (its states and commands, its values from the rewards of the measured states)."""

    def __init__(
        self, robot: RecordedRobot, episodes: RobotEpisodes, dataset: Dataset, *, window: bool, first: int = 0
    ) -> None:
        self.robot, self.episodes, self.dataset, self.window = robot, episodes, dataset, window
        self.given = first  # the run's first trajectories came from another run, not from the robot

    def trajectory(self, initial_state: FloatArray) -> Trajectory:
        self.episodes.close_start()
        while True:
            item = self.robot.next_record("answer")
            self.episodes.kept.append(item)  # the derived run's record of what the robot ran, as the stored one's
            if item.fault is None:
                break
        index = self.given
        if index >= self.dataset.num_trajectories:
            raise RecordMismatch(f"the run asks for a {index + 1}th answer; the file stores "
                                 f"{self.dataset.num_trajectories}")  # fmt: skip
        stored = self.dataset.trajectory(index)
        states, actions, rewards = item.arrays(self.robot.state_dim, self.robot.action_dim)
        recomputed = [self.episodes.reward(x, u) for x, u in zip(states, actions, strict=True)]
        if not np.allclose(recomputed, rewards, rtol=1e-9, atol=1e-9):
            raise RecordMismatch(f"robot episode {item.id}: its rewards are not the task's on its measured states")
        plan = Trajectory(stored.states, stored.actions, stored.values, gains=stored.gains)
        answer = tracked_answer(plan, states, actions, rewards, window=self.window)
        for name in ("states", "actions", "values"):
            if not np.allclose(getattr(answer, name), getattr(stored, name), rtol=1e-9, atol=1e-9):
                raise RecordMismatch(f"trajectory {index} is not what robot episode {item.id} ran: its {name} differ")
        if item.requested is None or not np.allclose(item.requested, initial_state, rtol=1e-12, atol=1e-12):
            raise RecordMismatch(f"robot episode {item.id}: the run asks for an answer from another start than stored")
        self.given += 1
        return stored
