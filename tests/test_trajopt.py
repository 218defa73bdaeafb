"""iLQR on MuJoCo's own derivatives against the closed forms of the lqr tasks, and its request checks."""

from __future__ import annotations

import numpy as np
import pytest

from npp_ros.lqr import LQRExpert, LQRPlant, episode_rng, rollout, sample_initial_state
from npp_ros.trajopt import ILQR, MujocoDynamics, lqr_task_cost, replay_return_to_go, time_trajectories

TASK, SEED, HORIZON = "lqr_2_1", 0, 1000


@pytest.fixture(scope="module")
def expert() -> LQRExpert:
    return LQRExpert(TASK, SEED)


@pytest.fixture(scope="module")
def plant() -> LQRPlant:
    return LQRPlant(TASK, SEED)


@pytest.fixture(scope="module")
def optimizer(plant: LQRPlant) -> ILQR:
    return ILQR(plant, lqr_task_cost(plant))


def finite_horizon_lqr(expert: LQRExpert, horizon: int) -> tuple[np.ndarray, np.ndarray]:
    """Exact time-varying optimum of sum_t 0.5 u'Ru + 0.5 x_{t+1}'Qc x_{t+1}: gains K_t and P_t."""
    a, b = expert.A, expert.B
    qc, r = expert.plant.state_cost, expert.plant.control_cost
    n, m = b.shape
    gains = np.empty((horizon, m, n))
    costs = np.empty((horizon, n, n))
    p = np.zeros((n, n))
    for t in range(horizon - 1, -1, -1):
        s = qc + p
        k = np.linalg.solve(r + b.T @ s @ b, b.T @ s @ a)
        p = a.T @ s @ a - a.T @ s @ b @ k
        p = 0.5 * (p + p.T)
        gains[t], costs[t] = k, p
    return gains, costs


@pytest.mark.parametrize("episode", [0, 1, 2])
def test_ilqr_recovers_the_lqr_expert_on_lqr_2_1(
    expert: LQRExpert, plant: LQRPlant, optimizer: ILQR, episode: int
) -> None:
    """H = 1000 from s0 on the initial sphere.

    Against the exact finite-horizon optimum (time-varying Riccati on the same A, B): actions
    within 1e-6 and W_x = P_t x_t within 1e-5 relative. Against the stationary LQR expert: the
    H-step return within 0.5% and never below it (the finite-horizon optimum is >= any policy's
    H-step return); actions within 8% of the largest |u|, as the stationary gain differs from the
    time-varying one (the closed loop's slowest mode has |lambda| = 0.997, so the horizon's end
    is felt early; measured up to 6.5% on these s0, mostly in the last 200 steps).
    """
    s0 = sample_initial_state(TASK, episode_rng(SEED, episode))
    result = optimizer.solve(s0, HORIZON, time_budget=60.0)
    assert result.converged, result.stop_reason

    gains, costs = finite_horizon_lqr(expert, HORIZON)
    x = s0.copy()
    exact = np.empty((HORIZON, 1))
    for t in range(HORIZON):
        exact[t] = -gains[t] @ x
        np.testing.assert_allclose(
            result.value_gradient[t], costs[t] @ x, rtol=0, atol=1e-5 * np.linalg.norm(costs[0] @ s0)
        )
        x = expert.A @ x + expert.B @ exact[t]
    np.testing.assert_allclose(result.actions, exact, rtol=0, atol=1e-6)

    _, values = replay_return_to_go(plant, s0, result.actions)
    stationary = rollout(expert.plant, expert.action, s0, HORIZON)
    assert values[0] >= stationary.total_return - 1e-9
    assert values[0] == pytest.approx(stationary.total_return, rel=5e-3)
    assert values[0] == pytest.approx(HORIZON - result.cost, abs=1e-8)
    np.testing.assert_allclose(result.actions, stationary.actions, rtol=0, atol=0.08 * np.abs(stationary.actions).max())
    assert result.max_value_slope <= 1.01 * float(np.max(expert.slope(stationary.states)))


def test_return_to_go_is_the_replayed_tail_sum(plant: LQRPlant, optimizer: ILQR) -> None:
    s0 = sample_initial_state(TASK, episode_rng(SEED, 7))
    result = optimizer.solve(s0, 200, time_budget=60.0)
    states, values = replay_return_to_go(plant, s0, result.actions)
    np.testing.assert_array_equal(states, result.states)  # the optimizer's model step is the plant's step
    rewards = []
    plant.reset(s0)
    for u in result.actions:
        rewards.append(plant.step(u))
    expected = np.array([sum(rewards[t:]) for t in range(len(rewards))])
    np.testing.assert_allclose(values, expected, rtol=0, atol=1e-9)
    assert values[0] == pytest.approx(sum(rewards), abs=1e-9)


def test_identical_requests_give_identical_arrays(plant: LQRPlant, optimizer: ILQR) -> None:
    s0 = sample_initial_state(TASK, episode_rng(SEED, 3))
    warm = np.full((300, 1), 0.1)
    first = optimizer.solve(s0, 300, time_budget=60.0, initial_actions=warm)
    second = ILQR(plant, lqr_task_cost(plant)).solve(s0, 300, time_budget=60.0, initial_actions=warm)
    for name in ("states", "actions", "value_gradient", "final_state"):
        np.testing.assert_array_equal(getattr(first, name), getattr(second, name))
    assert first.cost_history == second.cost_history


def test_warm_start_from_a_feedback_controller(expert: LQRExpert, optimizer: ILQR) -> None:
    """Started at the optimum's own feedback controller, iLQR has almost nothing left to do."""
    s0 = sample_initial_state(TASK, episode_rng(SEED, 4))
    result = optimizer.solve(s0, 300, time_budget=60.0, initial_policy=expert.action)
    assert result.converged
    assert result.cost <= result.cost_history[0]
    assert result.iterations <= 3


def test_a_spent_budget_returns_the_best_so_far_and_says_so(optimizer: ILQR) -> None:
    s0 = sample_initial_state(TASK, episode_rng(SEED, 5))
    result = optimizer.solve(s0, 1000, time_budget=1e-6)
    assert result.stop_reason == "time budget" and result.timed_out and not result.converged
    assert result.iterations == 0
    assert result.cost == result.cost_history[-1] == min(result.cost_history)
    assert result.value_gradient.shape == (1000, 4)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"x0": np.zeros(3)}, r"initial state must have 4 entries \(qpos then qvel\), got shape \(3,\)"),
        ({"x0": np.array([0.0, np.nan, 0.0, 0.0])}, r"initial state\[1\] is nan; it must be finite"),
        ({"time_budget": 0.0}, r"time_budget must be finite and > 0 seconds, got 0.0"),
        ({"time_budget": -1.0}, r"time_budget must be finite and > 0 seconds, got -1.0"),
        ({"time_budget": float("inf")}, r"time_budget must be finite and > 0 seconds, got inf"),
        ({"time_budget": "5"}, r"time_budget must be a number of seconds, got '5'"),
        ({"horizon": 0}, r"horizon must be an integer >= 1, got 0"),
        ({"horizon": 2.5}, r"horizon must be an integer >= 1, got 2.5"),
        ({"initial_actions": np.zeros((9, 1))}, r"warm-start actions must have shape \(10, 1\), got \(9, 1\)"),
        ({"initial_actions": np.zeros((10, 2))}, r"warm-start actions must have shape \(10, 1\), got \(10, 2\)"),
        ({"initial_actions": np.r_[np.zeros(9), np.inf][:, None]}, r"warm-start actions\[9, 0\] is not finite"),
        ({"max_iterations": -1}, r"max_iterations must be an integer >= 0, got -1"),
        (
            {"initial_actions": np.zeros((10, 1)), "initial_policy": lambda x: np.zeros(1)},
            r"give initial_actions or initial_policy, not both",
        ),
    ],
)
def test_bad_requests_are_refused_precisely(optimizer: ILQR, kwargs: dict, message: str) -> None:
    request = {"x0": np.zeros(4), "horizon": 10, "time_budget": 5.0} | kwargs
    x0, horizon = request.pop("x0"), request.pop("horizon")
    with pytest.raises(ValueError, match=f"^{message}$"):
        optimizer.solve(x0, horizon, **request)


def test_dynamics_checks_its_plant_and_fd_step(plant: LQRPlant) -> None:
    with pytest.raises(ValueError, match=r"^fd_eps must be finite and > 0, got 0.0$"):
        MujocoDynamics(plant, fd_eps=0.0)
    dyn = MujocoDynamics(plant)
    assert (dyn.state_dim, dyn.action_dim) == (4, 1)
    assert np.all(np.isinf(dyn.lower)) and np.all(np.isinf(dyn.upper))  # lqr actuators are unlimited


def test_time_trajectories_reports_seconds_per_request(optimizer: ILQR) -> None:
    starts = [sample_initial_state(TASK, episode_rng(SEED, e)) for e in range(2)]
    seconds = time_trajectories(lambda s0: optimizer.solve(s0, 50, time_budget=30.0), starts)
    assert seconds.shape == (2,) and np.all(seconds > 0)


def test_batched_fd_equals_mjd_transition_fd() -> None:
    """The RK4 path (one-step rollouts in C) takes the same centred differences as mjd_transitionFD."""
    from npp_ros.pendulum import PendulumPlant

    dyn = MujocoDynamics(PendulumPlant())
    rng = np.random.default_rng(0)
    states, actions = rng.uniform(-3, 3, (60, 2)), rng.uniform(-1.5, 1.5, (60, 1))  # some beyond the bounds
    a, b = dyn.jacobians(states, actions)
    a2, b2 = dyn._batched_jacobians(states, actions)
    np.testing.assert_allclose(a2, a, rtol=0, atol=1e-9)
    np.testing.assert_allclose(b2, b, rtol=0, atol=1e-9)
