"""iLQR on MuJoCo's own derivatives against the closed forms of the lqr tasks, and its request checks."""

from __future__ import annotations

import numpy as np
import pytest

from npp_ros.tasks.builtin.lqr import LQRExpert, LQRPlant, episode_rng, sample_initial_state
from npp_ros.tasks.registry import ExpertOptions, get_task
from npp_ros.tasks.rollout import rollout
from npp_ros.trajopt.dynamics import MujocoDynamics
from npp_ros.trajopt.expert import (
    DEFAULT_GUARD_S,
    DEFAULT_STOP,
    DEFAULT_TIME_BUDGET_S,
    OptimizingExpert,
    replay_return_to_go,
    replay_rewards,
    return_to_go,
    time_trajectories,
    window_values,
)
from npp_ros.trajopt.ilqr import ILQR, TrajOptResult, lqr_task_cost

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


def test_min_iterations_are_not_cut_by_the_budget(optimizer: ILQR) -> None:
    """The budget is spent before the first pass ends; the iterations asked for still run, then it stops."""
    s0 = sample_initial_state(TASK, episode_rng(SEED, 5))
    result = optimizer.solve(s0, 1000, time_budget=1e-6, min_iterations=1)
    assert result.stop_reason == "time budget" and result.iterations == 1
    assert result.cost < result.cost_history[0]


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
        ({"min_iterations": -1}, r"min_iterations must be an integer >= 0, got -1"),
        ({"min_iterations": True}, r"min_iterations must be an integer >= 0, got True"),
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
    from npp_ros.tasks.builtin.pendulum import PendulumPlant

    dyn = MujocoDynamics(PendulumPlant())
    rng = np.random.default_rng(0)
    states, actions = rng.uniform(-3, 3, (60, 2)), rng.uniform(-1.5, 1.5, (60, 1))  # some beyond the bounds
    a, b = dyn.jacobians(states, actions)
    a2, b2 = dyn._rollout_jacobians(states, actions)
    np.testing.assert_allclose(a2, a, rtol=0, atol=1e-9)
    np.testing.assert_allclose(b2, b, rtol=0, atol=1e-9)


# ----------------------------------------------------------------------------- the swing-up experts' requests
SHORT = 200  # steps: enough for the pole to come up from some s0, cheap enough for many requests


def swingup_expert(task: str, values: str, **kwargs: object) -> OptimizingExpert:
    """A swing-up expert whose requests stop by their iteration cap (a budget never reached)."""
    from npp_ros.tasks.builtin.cartpole import CartpoleExpert
    from npp_ros.tasks.builtin.pendulum import PendulumExpert

    make = PendulumExpert if task == "pendulum" else CartpoleExpert
    options = {"horizon": SHORT, "time_budget": 600.0, "max_iterations": 5, "values": values} | kwargs
    return make(**options)


def start_of(task: str, k: int) -> np.ndarray:
    pendulum = [np.array([0.3, 0.0]), np.array([2.0, 0.0]), np.array([0.5, 0.5])]
    return pendulum[k] if task == "pendulum" else np.array([0.0, np.pi, 0.0, 0.0])


def separate_replays(expert: OptimizingExpert, s0: np.ndarray) -> tuple[np.ndarray, np.ndarray, TrajOptResult, bool]:
    """The request with one replay per purpose: the optimised actions' H rewards, the warm start's,
    and the optimised (or kept) actions again for the values, window mode continuing them."""
    x0, steps = np.asarray(s0, dtype=np.float64), expert.horizon
    _, warm = expert.optimizer.dynamics.rollout(x0, steps, policy=expert.warm_start)
    result = expert.optimizer.solve(
        x0, steps, time_budget=600.0, initial_actions=warm, max_iterations=expert.max_iterations
    )
    _, rewards = replay_rewards(expert.plant, x0, result.actions)
    _, warm_rewards = replay_rewards(expert.plant, x0, warm)
    kept = float(warm_rewards.sum()) > float(rewards.sum())
    if kept:
        result = expert.optimizer.solve(x0, steps, time_budget=60.0, initial_actions=warm, max_iterations=0)
    if expert.values == "window":
        raw, rewards = replay_rewards(expert.plant, x0, result.actions, expert.warm_start, steps - 1)
        return raw, window_values(rewards, steps), result, kept
    raw, rewards = replay_rewards(expert.plant, x0, result.actions)
    return raw, return_to_go(rewards), result, kept


@pytest.mark.parametrize("task", ["pendulum", "cartpole"])
def test_a_continued_replay_begins_with_the_plain_one(task: str) -> None:
    """A replay starts from a reset plant, so its first H steps are the same whatever follows them or
    whichever replay ran before: bit for bit, on optimised, warm-start and random actions."""
    expert = swingup_expert(task, "window")
    x0 = start_of(task, 0)
    _, warm = expert.optimizer.dynamics.rollout(x0, SHORT, policy=expert.warm_start)
    low, high = expert.optimizer.dynamics.lower, expert.optimizer.dynamics.upper
    noise = np.random.default_rng(0).uniform(low, high, (SHORT, len(low)))
    optimised = expert.solve(x0).trajectory.actions
    for actions in (optimised, warm, noise):
        raw, rewards = replay_rewards(expert.plant, x0, actions)
        replay_rewards(expert.plant, x0, noise[::-1], expert.warm_start, 50)  # something else in between
        long_raw, long_rewards = replay_rewards(expert.plant, x0, actions, expert.warm_start, SHORT - 1)
        np.testing.assert_array_equal(long_raw, raw)
        np.testing.assert_array_equal(long_rewards[:SHORT], rewards)
        assert float(long_rewards[:SHORT].sum()) == float(rewards.sum())


@pytest.mark.parametrize(
    ("task", "values", "k", "kept"),
    [
        ("pendulum", "window", 0, False),
        ("pendulum", "window", 1, False),
        ("pendulum", "return-to-go", 0, False),
        ("cartpole", "window", 0, False),
        ("cartpole", "return-to-go", 0, False),
        ("pendulum", "window", 2, True),
        ("pendulum", "return-to-go", 2, True),
    ],
)
def test_fewer_replays_give_the_same_answer_bit_for_bit(task: str, values: str, k: int, kept: bool) -> None:
    """The expert's two replays answer exactly what one replay per purpose answers: states, actions,
    values, W_x and the kept-warm-start decision. A heavy torque cost makes iLQR's answer replay
    worse than the warm start from (0.5, 0.5), so the warm start is kept (the cases marked kept)."""
    from npp_ros.tasks.builtin.pendulum import SwingUpCost

    extra = {"cost": SwingUpCost(control_weight=100.0)} if kept else {}
    expert, reference = swingup_expert(task, values, **extra), swingup_expert(task, values, **extra)
    s0 = start_of(task, k)
    solution = expert.solve(s0)
    raw, values_ref, result, kept_ref = separate_replays(reference, s0)
    assert solution.kept_warm_start == kept_ref == kept
    np.testing.assert_array_equal(solution.raw_states, raw)
    np.testing.assert_array_equal(solution.trajectory.values, values_ref)
    np.testing.assert_array_equal(solution.trajectory.actions, result.actions)
    np.testing.assert_array_equal(solution.optimization.value_gradient, result.value_gradient)
    assert solution.optimization.iterations == result.iterations
    assert solution.expert_return == values_ref[0]


class FakeClock:
    """The expert's clock, moved only by the test: a phase takes the seconds the test says."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def recording_budgets(expert: OptimizingExpert) -> list[float]:
    """Every time budget the expert hands iLQR, in order (the optimizer itself is untouched)."""
    budgets: list[float] = []
    solve = expert.optimizer.solve

    def record(*args: object, **kwargs: object) -> TrajOptResult:
        budgets.append(kwargs["time_budget"])
        return solve(*args, **kwargs)

    expert.optimizer.solve = record  # type: ignore[method-assign]
    return budgets


def test_one_slow_request_leaves_later_requests_their_budget() -> None:
    """Replays that take 1 s a step in the first request (by the expert's clock) shorten that request's
    optimisation to its floor, one fifth of the budget, and nothing after it: the next request gets
    the whole budget back and answers exactly what a fresh expert answers."""
    expert = swingup_expert("pendulum", "window", time_budget=100.0)
    clock = FakeClock()
    expert.clock = clock
    budgets = recording_budgets(expert)
    step, slow = expert.plant.step, [True]

    def step_slowly(action: np.ndarray) -> float:
        clock.now += 1.0 if slow[0] else 0.0
        return step(action)

    expert.plant.step = step_slowly  # type: ignore[method-assign]
    s0 = start_of("pendulum", 0)
    first = expert.solve(s0)
    assert budgets == [pytest.approx(expert.min_optimizer_share * 100.0)]
    assert first.optimization.iterations >= 1
    slow[0] = False
    second = expert.solve(s0)
    assert budgets[1:] == [100.0]  # nothing spent by the clock: all of it, nothing held back for the past
    fresh = swingup_expert("pendulum", "window", time_budget=100.0).solve(s0)
    assert second.optimization.iterations == fresh.optimization.iterations == 5
    np.testing.assert_array_equal(second.trajectory.actions, fresh.trajectory.actions)
    np.testing.assert_array_equal(second.trajectory.values, fresh.trajectory.values)


@pytest.mark.parametrize("values", ["window", "return-to-go"])
def test_the_replay_to_come_is_predicted_from_this_request(values: str) -> None:
    """With the warm start's rollout taking 2 s and its replay 3 s: return-to-go holds back one more
    replay (3 s), window mode the continued one (3 + 3 + 2 s)."""
    expert = swingup_expert("pendulum", values, time_budget=100.0)
    clock = FakeClock()
    expert.clock = clock
    budgets = recording_budgets(expert)
    rollout, replay = expert.optimizer.dynamics.rollout, expert.plant.reset

    def timed_rollout(*args: object, **kwargs: object) -> tuple[np.ndarray, np.ndarray]:
        clock.now += 2.0
        return rollout(*args, **kwargs)

    def timed_reset(state: np.ndarray) -> np.ndarray:
        clock.now += 3.0 if len(budgets) == 0 else 0.0  # the warm start's replay, before iLQR
        return replay(state)

    expert.optimizer.dynamics.rollout = timed_rollout  # type: ignore[method-assign]
    expert.plant.reset = timed_reset  # type: ignore[method-assign]
    expert.solve(start_of("pendulum", 0))
    to_come = 3.0 + 3.0 + 2.0 if values == "window" else 3.0
    assert budgets[0] == 100.0 - (2.0 + 3.0) - to_come


def test_a_machine_too_slow_for_the_budget_still_gets_an_iteration() -> None:
    """A budget already spent by the warm start: iLQR gets its floor and still one iteration."""
    expert = swingup_expert("pendulum", "window", time_budget=1e-6)
    assert expert.budget_stops == 0
    solution = expert.solve(start_of("pendulum", 1))
    assert solution.optimization.iterations == 1
    assert solution.optimization.stop_reason == "time budget"
    assert expert.budget_stops == 1  # counted: npp-learn and the expert node say such answers depend on the machine


# ----------------------------------------------------------------------------- what ends a request
class SlowClock:
    """A machine slowed down: every reading of the clock finds ``step`` more seconds gone."""

    def __init__(self, step: float) -> None:
        self.now, self.step = 0.0, step

    def __call__(self) -> float:
        self.now += self.step
        return self.now


def test_a_slowed_machine_gives_the_same_answer_under_the_iteration_stop() -> None:
    """Under the default stop a request ends by convergence or its cap, so a machine where every phase takes
    half a second more answers bit for bit what a fast one answers; under stop = "time" the same slowed
    machine cuts iLQR short, and the expert counts that answer as machine-dependent."""
    s0 = start_of("pendulum", 0)
    fast = swingup_expert("pendulum", "window", time_budget=None).solve(s0)
    slowed = swingup_expert("pendulum", "window", time_budget=None)
    slowed.clock = SlowClock(0.5)
    answer = slowed.solve(s0)
    assert slowed.stop == "iterations" and slowed.budget_stops == 0
    assert answer.optimization.iterations == fast.optimization.iterations == 5
    np.testing.assert_array_equal(answer.trajectory.states, fast.trajectory.states)
    np.testing.assert_array_equal(answer.trajectory.actions, fast.trajectory.actions)
    np.testing.assert_array_equal(answer.trajectory.values, fast.trajectory.values)
    np.testing.assert_array_equal(answer.optimization.value_gradient, fast.optimization.value_gradient)

    timed = swingup_expert("pendulum", "window", time_budget=None, stop="time")
    timed.clock = SlowClock(0.5)
    cut = timed.solve(s0)
    assert timed.time_budget == DEFAULT_TIME_BUDGET_S
    assert cut.optimization.timed_out and cut.optimization.iterations < 5 and timed.budget_stops == 1


def test_the_guard_stops_a_runaway_request_and_says_so() -> None:
    """The iteration stop keeps the time budget as a guard: a request it stops is counted in budget_stops,
    which npp-learn and the expert node report as answers that depend on the machine's speed."""
    expert = swingup_expert("pendulum", "window", time_budget=3.0, max_iterations=50)
    expert.clock = SlowClock(0.5)
    solution = expert.solve(start_of("pendulum", 0))
    assert solution.optimization.stop_reason == "time budget"
    assert expert.budget_stops == 1


@pytest.mark.parametrize(
    ("task", "options", "budget"),
    [
        ("pendulum_swingup", ExpertOptions(), DEFAULT_GUARD_S),
        ("pendulum_swingup", ExpertOptions(stop="time"), DEFAULT_TIME_BUDGET_S),
        ("acrobot_swingup", ExpertOptions(stop="time"), 10.0),
        ("cartpole_swingup", ExpertOptions(stop="time", time_budget=2.0), 2.0),
    ],
)
def test_the_stop_sets_the_default_time_budget(task: str, options: ExpertOptions, budget: float) -> None:
    """The iteration stop is the default; its time budget is the guard, the time stop's the task's budget."""
    expert = get_task(task).make_expert(0, 50, options)
    assert isinstance(expert, OptimizingExpert)
    assert expert.stop == (options.stop or DEFAULT_STOP) and expert.time_budget == budget


def test_an_unknown_stop_is_refused_in_one_line() -> None:
    with pytest.raises(ValueError, match=r"^stop must be one of iterations, time; got 'clock'$"):
        get_task("pendulum_swingup").make_expert(0, 50, ExpertOptions(stop="clock"))
    with pytest.raises(ValueError, match=r"lqr_2_1 expert is closed form: stop do not apply"):
        get_task("lqr_2_1").make_expert(0, 50, ExpertOptions(stop="time"))
