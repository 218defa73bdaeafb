"""The iLQR expert on mujoco.batch answers what its one-at-a-time reference answers, bit for bit.

Derivatives (centred differences of the RK4 step), the line search's closed-loop rollouts, the
line search's cost values and whole expert requests, on cartpole, acrobot and pendulum.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from npp_ros.tasks.expert_pool import ExpertPool
from npp_ros.tasks.registry import ExpertOptions, get_task
from npp_ros.trajopt import batch_steps
from npp_ros.trajopt.dynamics import MujocoDynamics
from npp_ros.trajopt.expert import OptimizingExpert
from npp_ros.trajopt.ilqr import LINE_SEARCH_STEPS

TASKS = ("cartpole_swingup", "acrobot_swingup", "pendulum_swingup")
SHORT = 150  # steps per request: a few seconds for every task and both paths


def trajectory_like(dyn: MujocoDynamics, horizon: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """States a swing-up visits (angles all round, fast rates) and controls, some beyond their bounds."""
    rng = np.random.default_rng(seed)
    nq = dyn.nq
    states = np.concatenate([rng.uniform(-3.5, 3.5, (horizon + 1, nq)), rng.normal(0.0, 4.0, (horizon + 1, nq))], 1)
    actions = rng.uniform(-1.3, 1.3, (horizon, dyn.action_dim))
    actions[::7] = dyn.upper if np.isfinite(dyn.upper).all() else actions[::7]  # exactly at a bound
    return states, actions


@pytest.mark.parametrize("task", TASKS)
@pytest.mark.parametrize("threads", [1, 2])
def test_batch_jacobians_equal_the_rollout_ones_bit_for_bit(task: str, threads: int) -> None:
    dyn = MujocoDynamics(get_task(task).make_plant(0), threads=threads)
    for seed, horizon in ((0, 40), (1, 25)):  # a second size: the batch is rebuilt for it
        states, actions = trajectory_like(dyn, horizon, seed)
        a_ref, b_ref = dyn._rollout_jacobians(states, actions)
        a, b = dyn._differences.jacobians(states, actions, dyn.fd_eps, dyn.lower, dyn.upper)
        np.testing.assert_array_equal(a, a_ref)
        np.testing.assert_array_equal(b, b_ref)
        assert np.abs(a).max() > 0 and np.abs(b).max() > 0


@pytest.mark.parametrize("task", ["cartpole_swingup", "acrobot_swingup"])
def test_rk4_jacobians_take_the_batch_unless_asked_for_the_reference(task: str) -> None:
    dyn = MujocoDynamics(get_task(task).make_plant(0), threads=2)
    states, actions = trajectory_like(dyn, 30, 2)
    new = dyn.jacobians(states, actions)
    dyn.reference = True
    old = dyn.jacobians(states, actions)
    for x, y in zip(new, old, strict=True):
        np.testing.assert_array_equal(x, y)
    assert "mujoco.rollout" in dyn.derivatives_by
    dyn.reference = False
    assert dyn.derivatives_by == "one-step simulations on mujoco.batch, 2 threads (RK4)"


def test_the_pendulum_keeps_mjd_transition_fd() -> None:
    """Euler models keep MuJoCo's own transition derivatives, on both paths."""
    dyn = MujocoDynamics(get_task("pendulum_swingup").make_plant(0))
    assert not dyn.batched_fd and dyn.derivatives_by == "mujoco.mjd_transitionFD"


@pytest.mark.parametrize("task", TASKS)
def test_closed_loops_equal_one_closed_loop_each_bit_for_bit(task: str) -> None:
    dyn = MujocoDynamics(get_task(task).make_plant(0))
    horizon = 120
    ref_states, ref_actions = dyn.rollout(get_task(task).initial_state(0, 0), horizon, actions=np.zeros((horizon, 1)))
    rng = np.random.default_rng(3)
    k = rng.normal(0.0, 0.5, ref_actions.shape)
    gains = rng.normal(0.0, 0.3, (horizon, dyn.action_dim, dyn.state_dim))
    alphas = LINE_SEARCH_STEPS[:5]
    states, actions = dyn.closed_loops(ref_states, ref_actions, k, gains, alphas)
    assert states.shape == (len(alphas), horizon + 1, dyn.state_dim)
    for i, alpha in enumerate(alphas):
        one_states, one_actions = dyn.closed_loop(ref_states, ref_actions, k, gains, alpha)
        np.testing.assert_array_equal(states[i], one_states)
        np.testing.assert_array_equal(actions[i], one_actions)
    assert not np.array_equal(states[0], states[1])  # the step sizes do lead to different rollouts


@pytest.mark.parametrize("controls", [1, 2, 3])
def test_a_stacked_feedback_is_each_single_feedback_bit_for_bit(controls: int) -> None:
    """What the batched closed loop relies on, for any number of controls: K @ dx[i] for every row i
    is one stacked matmul's row i, to the last bit (the same BLAS call per row)."""
    rng = np.random.default_rng(controls)
    for n in (2, 4, 6, 12):
        gains = rng.normal(0.0, 1.0, (controls, n))
        dx = rng.normal(0.0, 1.0, (11, n)) * 10.0 ** rng.integers(-8, 3, (11, n))
        stacked = np.matmul(gains, dx[:, :, None])[:, :, 0]
        for i in range(len(dx)):
            np.testing.assert_array_equal(stacked[i], gains @ dx[i])


def test_term_cost_values_alone_equal_state_terms_values() -> None:
    """A task file's cost (the two-link arm example's reward terms) gives the same values without derivatives."""
    expert = get_task(str(TWO_LINK_ARM)).make_expert(0, SHORT)
    assert hasattr(expert.optimizer.cost, "state_values")
    dyn = expert.optimizer.dynamics
    states, _ = trajectory_like(dyn, 300, 4)
    values, _, _ = expert.optimizer.cost.state_terms(states)
    np.testing.assert_array_equal(expert.optimizer.cost.state_values(states), values)


TWO_LINK_ARM = Path(__file__).resolve().parents[1] / "examples" / "two_link_arm" / "task.toml"


def short_expert(task: str, reference: bool) -> OptimizingExpert:
    """The task's expert at a short horizon, stopped by its iteration cap or convergence (never the budget)."""
    expert = get_task(task).make_expert(0, SHORT, ExpertOptions(time_budget=600.0, max_iterations=6, threads=2))
    assert isinstance(expert, OptimizingExpert)
    expert.optimizer.dynamics.reference = reference
    return expert


@pytest.mark.parametrize("task", TASKS)
def test_a_request_gets_the_reference_answer_bit_for_bit(task: str) -> None:
    """Same request, both paths: equal states, actions, values, W_x and cost history. The batch path's
    multi-step-size searches are counted, so the comparison covers them."""
    new, old = short_expert(task, reference=False), short_expert(task, reference=True)
    searched_at_once = []
    closed_loops = new.optimizer.dynamics.closed_loops

    def counted(*args: object) -> tuple[np.ndarray, np.ndarray]:
        states, actions = closed_loops(*args)  # type: ignore[arg-type]
        searched_at_once.append(len(states))
        return states, actions

    new.optimizer.dynamics.closed_loops = counted  # type: ignore[method-assign]
    spec = get_task(task)
    for episode in range(2):
        s0 = spec.initial_state(0, episode)
        mine, reference = new.solve(s0), old.solve(s0)
        assert mine.optimization.stop_reason in ("converged", "max iterations")
        assert reference.optimization.stop_reason == mine.optimization.stop_reason
        np.testing.assert_array_equal(mine.trajectory.states, reference.trajectory.states)
        np.testing.assert_array_equal(mine.trajectory.actions, reference.trajectory.actions)
        np.testing.assert_array_equal(mine.trajectory.values, reference.trajectory.values)
        np.testing.assert_array_equal(mine.raw_states, reference.raw_states)
        np.testing.assert_array_equal(mine.optimization.value_gradient, reference.optimization.value_gradient)
        assert mine.optimization.cost_history == reference.optimization.cost_history
        assert mine.kept_warm_start == reference.kept_warm_start
    if task == "acrobot_swingup":  # its searches often need several step sizes
        assert searched_at_once and max(searched_at_once) > 1


def test_threads_are_checked_and_reach_the_expert() -> None:
    with pytest.raises(ValueError, match=r"^threads must be an integer >= 1, got 0$"):
        MujocoDynamics(get_task("cartpole_swingup").make_plant(0), threads=0)
    expert = get_task("cartpole_swingup").make_expert(0, SHORT, ExpertOptions(threads=2))
    assert isinstance(expert, OptimizingExpert) and expert.optimizer.dynamics.threads == 2
    assert get_task("cartpole_swingup").make_expert(0, SHORT).optimizer.dynamics.threads == 1  # type: ignore[attr-defined]


def test_a_pool_shares_the_cores_among_its_workers() -> None:
    cores = batch_steps.usable_cores()
    assert batch_steps.default_threads() == cores
    assert batch_steps.default_threads(2 * cores) == 1
    with ExpertPool("pendulum_swingup", 0, SHORT, ExpertOptions(), workers=2) as pool:
        assert pool.threads == max(1, cores // 2)
        assert pool.threads * pool.workers <= max(cores, pool.workers)
    with ExpertPool("pendulum_swingup", 0, SHORT, ExpertOptions(threads=3), workers=2) as pool:
        assert pool.threads == 3  # an explicit count is the caller's choice


def test_an_expert_that_planned_on_another_robot_answers_as_a_fresh_one() -> None:
    """A batch copies its model when made: after a request on one drawn robot, a request on another plans on that
    other robot's model (derivatives and gains too), as an expert that never saw the first one does."""
    from npp_ros.tasks.uncertainty import SWINGUP_UNCERTAINTY, as_robot

    task = get_task("cartpole_swingup")
    options = ExpertOptions(time_budget=120.0, max_iterations=5, threads=1)
    robots = SWINGUP_UNCERTAINTY.resolved(task.make_plant(2).physics.model)
    first, second = robots.draw(2, 1), robots.draw(2, 0)
    s0 = np.array([0.1, 3.0, 0.0, 0.0])
    used = task.make_expert(2, 80, options)
    with as_robot(used.plant, first):
        used.trajectory(s0)
    with as_robot(used.plant, second):
        after = used.trajectory(s0)
    fresh = task.make_expert(2, 80, options)
    with as_robot(fresh.plant, second):
        want = fresh.trajectory(s0)
    assert after.gains is not None and want.gains is not None
    for name in ("states", "actions", "values", "gains"):
        np.testing.assert_array_equal(getattr(after, name), getattr(want, name))
