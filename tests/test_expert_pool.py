"""The expert pool answers exactly as one expert answering one request at a time."""

from __future__ import annotations

import numpy as np
import pytest

from npp_ros.tasks.expert_pool import ExpertPool, default_workers
from npp_ros.tasks.registry import ExpertOptions, episode_rng, get_task

TASK, HORIZON = "pendulum_swingup", 60
OPTIONS = ExpertOptions(time_budget=120.0, max_iterations=5)  # the iteration cap decides, not the clock


def test_pool_answers_are_the_one_at_a_time_answers_bit_for_bit() -> None:
    task = get_task(TASK)
    states = np.array([task.sample_initial_state(episode_rng(3, k)) for k in range(5)])
    alone = task.make_expert(0, HORIZON, OPTIONS)
    want = [alone.trajectory(s0, HORIZON) for s0 in states]
    with ExpertPool(TASK, 0, HORIZON, OPTIONS, workers=2) as pool:
        got = [f.result(timeout=600) for f in [pool.submit(s0) for s0 in states]]  # all asked at once
    for answer, expected in zip(got, want, strict=True):
        assert not answer.budget_stopped and answer.stop_reason in {"converged", "max iterations"}
        np.testing.assert_array_equal(answer.trajectory.states, expected.states)
        np.testing.assert_array_equal(answer.trajectory.actions, expected.actions)
        np.testing.assert_array_equal(answer.trajectory.values, expected.values)
        assert answer.trajectory.expert_return == expected.expert_return


def test_an_answer_cut_by_the_time_budget_is_named() -> None:
    with ExpertPool(TASK, 0, HORIZON, ExpertOptions(time_budget=1e-6, max_iterations=5), workers=1) as pool:
        answer = pool.submit(np.array([3.0, 0.0])).result(timeout=600)
    assert answer.budget_stopped and len(answer.trajectory) == HORIZON


def test_a_pool_needs_a_worker() -> None:
    assert default_workers() >= 1
    with pytest.raises(ValueError, match="at least one worker"):
        ExpertPool(TASK, 0, HORIZON, OPTIONS, workers=0)
