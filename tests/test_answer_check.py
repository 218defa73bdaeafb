"""The supervisor's check of an expert answer: every built-in expert's answers pass, wrong ones are refused."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from npp_ros.policy.dataset import Trajectory
from npp_ros.tasks.registry import ExpertOptions, get_task
from npp_ros_graph.nodes.supervisor.answer_check import AnswerCheck, AnswerError

CASES = [
    ("lqr_2_1", 1000, ExpertOptions()),
    ("lqr_6_2", 300, ExpertOptions()),
    ("pendulum_swingup", 100, ExpertOptions(max_iterations=3)),
    ("cartpole_swingup", 100, ExpertOptions(max_iterations=3)),
    ("examples/two_link_arm/task.toml", 100, ExpertOptions()),
]


def answer_and_check(name: str, horizon: int, options: ExpertOptions) -> tuple[Trajectory, np.ndarray, AnswerCheck]:
    task = get_task(name)
    expert = task.make_expert(0, horizon, options)
    check = AnswerCheck(task.make_plant(0), horizon, expert.value_basis().tail, task.reward_range)
    s0 = task.initial_state(0, 1)
    return expert.trajectory(s0, horizon), s0, check


@pytest.mark.parametrize(("name", "horizon", "options"), CASES, ids=[c[0].split("/")[-1] for c in CASES])
def test_every_built_in_expert_passes(name: str, horizon: int, options: ExpertOptions) -> None:
    answer, s0, check = answer_and_check(name, horizon, options)
    check(answer, s0)


def test_wrong_answers_are_refused_with_the_check_they_fail() -> None:
    answer, s0, check = answer_and_check("lqr_2_1", 1000, ExpertOptions())
    states, values = answer.states, answer.values
    wrong = {
        "wrong dimensions": replace(answer, states=states[:, :3]),
        "wrong length": replace(answer, states=states[:-1], actions=answer.actions[:-1], values=values[:-1]),
        "it does not start at the requested state": replace(answer, states=states + 0.01),
        "states[1] = ": replace(answer, states=np.vstack([states[:1], states[1:] * 1.001])),
        "is not its trajectory's return": replace(answer, expert_return=answer.expert_return + 1.0),
        "expert_return is inf": replace(answer, expert_return=np.inf),
        "values[0] = ": replace(answer, values=values + 5.0),
        "values[9] - values[10]": replace(answer, values=np.concatenate([values[:10], values[10:] + 0.5])),
    }
    for reason, bad in wrong.items():
        with pytest.raises(AnswerError, match=reason.replace("[", r"\[").replace("]", r"\]")):
            check(bad, s0)
    check(answer, s0)  # the check keeps no state between answers
