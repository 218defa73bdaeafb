"""Which model the expert plans on in a run under model uncertainty, and the nominal plan run on a robot.

A run on a set of robots (npp_ros.tasks.uncertainty) asks its expert about each episode's robot theta. Two
experts are offered, named by ``expert_model``:

- ``robot`` (the default): a privileged expert, which plans on theta itself (the teacher of teacher-student
  training knows the robot; the policy does not). Its answer is its plan's true rollout on theta.
- ``nominal``: the expert plans on the task's nominal model, as an expert that does not know theta would; its
  plan, with the plan's own feedback gains (a = clamp(a_t + K_t (s - s_t)), the feedback policy's law at the
  plan's point t), is then run on theta, and that rollout is the answer: its states, the actions applied and the
  true rewards on theta. Any expert can serve here, including one that cannot model a drawn robot.

In both, the answer is a true rollout on theta's physical parameters without its action delay or state noise, and
its values are true H-step returns there. What differs is the reference a gap claim compares with: a nominal
plan tracked on theta can do worse than a plan made for theta, so a gap to it may be small while the policy is
poor on theta, and a success claim's expert answers fail more often. The certificate names which.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from typing import Any, Literal, get_args

import numpy as np

from npp_ros.certificate.authoring import PRIVILEGED_REFERENCE
from npp_ros.policy.dataset import FloatArray, Trajectory
from npp_ros.policy.feedback import ControlSpace
from npp_ros.tasks.rollout import rollout
from npp_ros.tasks.task import Plant, control_space
from npp_ros.tasks.uncertainty import Robot
from npp_ros.trajopt.expert import DEFAULT_VALUES, return_to_go, window_values

ExpertModel = Literal["robot", "nominal"]
EXPERT_MODELS: tuple[str, ...] = get_args(ExpertModel)
DEFAULT_EXPERT_MODEL: ExpertModel = "robot"
EXPERT_MODEL_HELP = (
    "under --uncertainty, the model the expert plans on: robot (the default: each episode's drawn robot, a "
    "privileged expert) or nominal (the task's own model; its plan, with its feedback gains, then runs on the "
    "episode's robot, and that rollout is the answer)"
)
REFERENCE = {  # what V^E is in a claim under uncertainty (npp_ros.certificate.authoring.over_robots)
    "robot": PRIVILEGED_REFERENCE,
    "nominal": (
        "V^E is the expert planning on the task's nominal model, its plan run on each episode's robot with the "
        "plan's own feedback gains (neither knows the robot)"
    ),
}


def check_expert_model(name: str, uncertainty: float | None = None) -> ExpertModel:
    """A known expert model; with the run's ``uncertainty`` factor, refused where it would change nothing (on the
    exact model the expert plans on the model either way), so that no run records a choice it did not make."""
    if name not in EXPERT_MODELS:
        raise ValueError(f"the expert model must be one of {', '.join(EXPERT_MODELS)}, got {name!r}")
    if uncertainty == 0 and name != DEFAULT_EXPERT_MODEL:
        raise ValueError(
            f"expert model {name} needs a set of robots (uncertainty > 0): on the exact model the expert plans on "
            "the model either way"
        )
    return name  # type: ignore[return-value]


def stores_window_values(expert: Any) -> bool:
    """Whether the expert's stored values are window values (the optimizer experts' default), which a tracked plan's
    answer then stores too; else return-to-go."""
    return getattr(expert, "values", DEFAULT_VALUES) == "window"


def tracked_on_robot(
    plant: Plant, plan: Trajectory, initial_state: FloatArray, robot: Robot, space: ControlSpace, *, window: bool
) -> Trajectory:
    """``plan`` (made on the nominal model from ``initial_state``) run on ``robot`` by its own feedback law.

    Step t applies clamp(a_t + K_t (s_t' - s_t)), s_t' the robot's state and (s_t, a_t, K_t) the plan's row t (K = 0
    where the plan has no gains: open loop). ``window`` values (the optimizer experts' convention): Q_t is the
    return of the T steps from t, the law past the plan's end holding its last row, so the rollout runs 2T - 1
    steps; else Q_t is the return still to come within the plan's T steps. Q_0 is the plan's H-step return on the
    robot either way. The robot's physical parameters apply, not its delay or noise, as for a privileged expert's
    answer. The stored gains are the plan's.
    """
    physical = Robot(robot.scales)  # no delay, no noise: what an expert's answer is run on
    run = rollout(plant, plan_law(plan, space), initial_state, tracked_steps(plan, window), physical)
    return tracked_answer(plan, run.states, run.actions, run.rewards, window=window)


def plan_law(plan: Trajectory, space: ControlSpace) -> Callable[[FloatArray], FloatArray]:
    """The plan's own feedback law, one call per step: step t applies clamp(a_t + K_t (s - s_t)), K = 0 where the
    plan has no gains; past the plan's end it holds its last row."""
    steps = len(plan)
    gains = plan.gains if plan.gains is not None else np.zeros((steps, plan.actions.shape[1], plan.states.shape[1]))
    clock = itertools.count()

    def law(state: FloatArray) -> FloatArray:
        t = min(next(clock), steps - 1)
        correction = gains[t] @ space.difference(state[None, :], plan.states[t][None, :])[0]
        return space.clamp(plan.actions[t] + correction)

    return law


def tracked_steps(plan: Trajectory, window: bool) -> int:
    """How long a tracked plan runs: 2T - 1 steps for window values (each of the T stored points gets its window),
    else the plan's T."""
    return 2 * len(plan) - 1 if window else len(plan)


def tracked_answer(
    plan: Trajectory, states: FloatArray, actions: FloatArray, rewards: FloatArray, *, window: bool
) -> Trajectory:
    """The answer a tracked plan gives: the plan's first T points of what was run, its values from the rewards
    earned there, the plan's gains."""
    steps = len(plan)
    values = window_values(rewards, steps) if window else return_to_go(rewards)
    return Trajectory(states[:steps].copy(), actions[:steps].copy(), values, expert_return=float(values[0]),
                      gains=plan.gains)  # fmt: skip


def nominal_plan_returns(
    expert: Any,
    plant: Plant,
    states: FloatArray,
    horizon: int,
    robots: Sequence[Robot],
    progress: Callable[[int, int], None] | None = None,
) -> FloatArray:
    """The H-step return on robot k of the expert's nominal plan from s0 k, run as a run's answers are: the
    held-out reference of a claim whose expert plans on the nominal model. ``progress(done, total)`` after each."""
    window = stores_window_values(expert)
    space = control_space(plant)
    out = np.empty(len(states))
    for k, s0 in enumerate(states):
        plan = expert.trajectory(s0, horizon)
        out[k] = tracked_on_robot(plant, plan, s0, robots[k], space, window=window).expert_return
        if progress is not None:
            progress(k + 1, len(states))
    return out
