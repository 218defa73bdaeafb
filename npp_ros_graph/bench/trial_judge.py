"""npp-trial's judgement of one episode on the robot (judge, into a TrialEpisode): the robot's episode against the
model (the drawn robot's) and against the certified policy in process from the same s0.

The robot's return is its reported efforts replayed on that robot's model from s0, and the replay must reproduce
every joint state the robot published, bit for bit (the robot is the model); the in-process return is ``rollout``
of the policy on the plant, which meets the robot's delay and noise itself. judge also counts the steps whose
command was the policy's fresh answer to the state just before, and, where the task has them, whether the pole
ended upright and whether the task's success criterion was met, on the robot and in process.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from npp_ros.bench.measure import POLE_ANGLE, UPRIGHT_DEGREES, worst_angle_degrees
from npp_ros.deployment.gate import Deployment
from npp_ros.deployment.joints import JointLayout, stored_state
from npp_ros.tasks.rollout import rollout
from npp_ros.tasks.uncertainty import Robot, as_robot


@dataclass(frozen=True)
class TrialEpisode:
    """One episode on the robot and the same s0 in process."""

    episode: int
    robot_return: float
    in_process_return: float
    fresh_command_share: float  # steps whose command answered the state just before
    first_command_answers_s0: bool  # the robot waited at s0 for the policy's answer to it
    replay_mismatches: int  # published states the model's replay of the robot's efforts does not reproduce
    robot_upright: bool | None  # swing-up tasks: the pole within 8 degrees over the last half; else None
    in_process_upright: bool | None
    robot: str = ""  # the robot of a run certified on a set (Robot.record()); "" = the task's model
    robot_success: bool | None = None  # the task's success criterion on the robot's states (None: it states none)
    in_process_success: bool | None = None

    @property
    def gap(self) -> float:
        return self.in_process_return - self.robot_return


def judge(deployment: Deployment, episode: int, s0: np.ndarray, raws: np.ndarray, efforts: np.ndarray,
          horizon: int, drawn: Robot | None = None) -> TrialEpisode:  # fmt: skip
    """The robot's episode against the model (the drawn robot's) and against the policy in process on it.

    The efforts are the commands the actuator applied (after the robot's delay), so they are replayed on the
    robot's model without a delay; the in-process reference meets the delay and the noise itself."""
    plant, policy = deployment.plant, deployment.policy
    layout = JointLayout.of_plant(plant)
    actions = np.array([layout.action(effort) for effort in efforts[:horizon]])
    model_only = None if drawn is None else Robot(drawn.scales)
    with as_robot(plant, model_only):
        replayed = _raw_states(plant, s0, actions)
    mismatches = int(np.sum(np.any(replayed[1:] != raws[1 : horizon + 1], axis=1)))
    robot = rollout(plant, _replayer(actions), s0, horizon, model_only)
    stored = np.array([stored_state(plant, raw) for raw in raws[:horizon]])
    answer = policy.controller()  # the robot's episode answered state by state, as npp-deploy's activation did
    fresh = float(
        np.mean([np.array_equal(answer(state), action) for state, action in zip(stored, actions, strict=True)])
    )
    reference = rollout(plant, policy.controller(), s0, horizon, drawn)
    first = bool(np.array_equal(actions[0], reference.actions[0]))
    criterion = deployment.task.success
    success = (None, None) if criterion is None else (criterion.met(stored), criterion.met(reference.states))
    angle = POLE_ANGLE.get(deployment.task.name)
    upright: tuple[bool | None, bool | None] = (None, None)
    if angle is not None:
        hold, acrobot = max(1, horizon // 2), deployment.task.name == "acrobot_swingup"
        upright = tuple(  # type: ignore[assignment]
            worst_angle_degrees(states, angle, hold, acrobot) <= UPRIGHT_DEGREES
            for states in (stored, reference.states)
        )
    record = "" if drawn is None else drawn.record()
    return TrialEpisode(
        episode, robot.total_return, reference.total_return, fresh, first, mismatches, *upright, robot=record,
        robot_success=success[0], in_process_success=success[1],
    )  # fmt: skip


def _replayer(actions: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    steps: Iterator[np.ndarray] = iter(actions)
    return lambda _state: next(steps)


def _raw_states(plant: Any, s0: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """[qpos, qvel] after each of ``actions`` from s0, as the robot publishes them (angles unwrapped)."""
    plant.reset(s0)
    data = plant.physics.data
    out = [np.concatenate([data.qpos, data.qvel])]
    for action in actions:
        plant.step(action)
        out.append(np.concatenate([data.qpos, data.qvel]))
    return np.array(out)
