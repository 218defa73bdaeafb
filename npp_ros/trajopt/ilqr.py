"""Iterative LQR (box-constrained, Levenberg-Marquardt) on MuJoCo's own derivatives of the plant.

The optimizer is the TrajectoryOptimizer of Algorithm 1 for plants without a closed form; its
dynamics are :class:`~npp_ros.trajopt.dynamics.MujocoDynamics`, the plant's own model.

Cost convention (as dm_control scores a step on the state *after* it): the objective of a
request from x_0 with actions u_0 .. u_{T-1} is

    J = sum_{t<T} [ c(u_t) + s(x_{t+1}) ],

``s`` the state cost, ``c`` the control cost. On the lqr tasks s(x) = 0.5 x'Qc x and
c(u) = 0.5 u'Ru make J = T - (the T-step return), so the optimum is the exact finite-horizon
optimum of the task. Other tasks (the pendulum) use a smooth surrogate; the values handed to the
dataset are always the *true* rewards, replayed on the plant
(:func:`~npp_ros.trajopt.expert.replay_return_to_go`).

Determinism: every operation is sequential floating point on fixed inputs, so a request (start
state, horizon, warm start, options) gives the same arrays bit for bit whenever it stops by
convergence or the iteration cap. A stop by the time budget depends on the machine's speed by
nature; the result says so (``stop_reason``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike

from npp_ros.policy.dataset import FloatArray
from npp_ros.trajopt.dynamics import DEFAULT_FD_EPS, MujocoDynamics, PhysicsPlant

MU_MIN = 1e-8
MU_MAX = 1e10
LINE_SEARCH_STEPS = tuple(0.5**i for i in range(11))
BATCH_FROM = 4  # step sizes a line search rolls out in one batch at the least (fewer go one at a time)


class StageCost(Protocol):
    """Smooth cost split as the task's reward is: state cost on post-step states, control cost.

    Both are batched over rows, returning (values (N,), gradients (N, k), Hessians (N, k, k)).
    """

    def state_terms(self, states: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]: ...

    def control_terms(self, actions: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]: ...


@dataclass(frozen=True)
class QuadraticCost:
    """s(x) = 0.5 (x - x*)'Q(x - x*), c(u) = 0.5 u'Ru."""

    state_weight: FloatArray
    control_weight: FloatArray
    target: FloatArray | None = None

    def state_terms(self, states: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        dx = states if self.target is None else states - self.target
        grad = dx @ self.state_weight.T
        value = 0.5 * np.einsum("ij,ij->i", dx, grad)
        hess = np.broadcast_to(self.state_weight, (len(states), *self.state_weight.shape))
        return value, grad, hess

    def control_terms(self, actions: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        grad = actions @ self.control_weight.T
        value = 0.5 * np.einsum("ij,ij->i", actions, grad)
        hess = np.broadcast_to(self.control_weight, (len(actions), *self.control_weight.shape))
        return value, grad, hess


def lqr_task_cost(plant: object) -> QuadraticCost:
    """The lqr tasks' exact cost: 1 - r = 0.5 q'q + 0.5 u'Ru on the post-step state."""
    return QuadraticCost(np.asarray(plant.state_cost, dtype=np.float64), np.asarray(plant.control_cost, np.float64))


@dataclass(frozen=True)
class TrajOptResult:
    """An optimised trajectory: x_0 .. x_{T-1}, u_0 .. u_{T-1}, and the backward pass's W_x.

    ``value_gradient[t]`` is the gradient of the cost-to-go J_t(x) = sum_{k>=t} c(u_k) + s(x_{k+1})
    at x_t under the returned actions' local policy. At a stationary point of the box-constrained
    problem the feedforward terms vanish (k = 0 on free controls, K = 0 on clamped ones), so
    W_x = Q_x = A'(s_x + W_x)_{t+1}: the costate recursion, i.e. the exact first-order slope of the
    optimal cost-to-go along the trajectory (envelope theorem; the Gauss-Newton approximation only
    touches second derivatives). Its norm is the slope of the expert's value at each visited state.
    """

    states: FloatArray  # (T, n)
    final_state: FloatArray  # (n,)
    actions: FloatArray  # (T, m)
    value_gradient: FloatArray  # (T, n)
    cost: float
    iterations: int
    converged: bool
    stop_reason: str
    wall_time: float
    cost_history: tuple[float, ...]
    timings: dict[str, float] = field(default_factory=dict)
    max_transition_norm: float = math.nan  # max_t |A_t|_2 along the returned trajectory (L_f seen)
    # K_t of the last successful backward pass at the returned trajectory, (T, m, n): the optimizer's local
    # feedback law u = u_t + K_t (x - x_t) (zero on clamped controls); None when no pass succeeded there.
    gains: FloatArray | None = None

    @property
    def timed_out(self) -> bool:
        return self.stop_reason == "time budget"

    @property
    def max_value_slope(self) -> float:
        """max_t |W_x(x_t)|: the steepest slope of the cost-to-go seen along this trajectory."""
        return float(np.max(np.linalg.norm(self.value_gradient, axis=1)))


def check_time_budget(budget: float) -> float:
    if isinstance(budget, bool) or not isinstance(budget, (int, float, np.floating, np.integer)):
        raise ValueError(f"time_budget must be a number of seconds, got {budget!r}")
    if not (math.isfinite(budget) and budget > 0):
        raise ValueError(f"time_budget must be finite and > 0 seconds, got {budget!r}")
    return float(budget)


class ILQR:
    """Box-constrained iterative LQR (Tassa, Mansard & Todorov 2014) on a MuJoCo plant.

    Regularisation: Levenberg-Marquardt on Quu (mu grows on a non-positive-definite Quu or a
    failed line search, shrinks on success). Line search: alpha in 1, 1/2, ..., 1/1024; a step
    is accepted when it lowers the cost by at least a tenth of the predicted decrease (or at all,
    when the predicted decrease is at rounding level). Bounds are the actuators' ctrlrange.

    The search rolls out several step sizes at once (:meth:`MujocoDynamics.closed_loops`) and
    accepts the first that passes, in the order above: the step the one-at-a-time search accepts.
    ``threads`` and ``reference`` are :class:`MujocoDynamics`'; ``reference=True`` also searches one
    step size at a time and takes the cost from ``state_terms``, as the optimizer always did.
    """

    def __init__(
        self,
        plant: PhysicsPlant,
        cost: StageCost,
        fd_eps: float = DEFAULT_FD_EPS,
        *,
        threads: int = 1,
        reference: bool = False,
    ) -> None:
        from npp_ros.trajopt import kernels as ilqr_kernels  # numba loads with the optimizer, not with a plant

        self.dynamics = MujocoDynamics(plant, fd_eps, threads=threads, reference=reference)
        ilqr_kernels.compile_kernels()
        self._backward_pass = ilqr_kernels.backward_pass
        self.cost = cost
        self.state_dim = self.dynamics.state_dim
        self.action_dim = self.dynamics.action_dim
        self._search_tries = 1  # step sizes the last line search tried: how many the next one rolls out first
        self.clock: Callable[[], float] = time.perf_counter  # what the budget is read on (a test may slow it)

    def total_cost(self, states: FloatArray, actions: FloatArray) -> float:
        state_values = getattr(self.cost, "state_values", None)
        if state_values is None or self.dynamics.reference:
            s, _, _ = self.cost.state_terms(states[1:])
        else:
            s = state_values(states[1:])
        c, _, _ = self.cost.control_terms(actions)
        return float(s.sum() + c.sum())

    @staticmethod
    def _accepts(cost: float, new_cost: float, alpha: float, dv1: float, dv2: float) -> bool:
        expected = -(alpha * dv1 + alpha * alpha * dv2)
        actual = cost - new_cost
        return math.isfinite(new_cost) and actual > 0 and (actual >= 0.1 * expected or expected < 1e-12 * abs(cost))

    def _line_search(
        self,
        states: FloatArray,
        actions: FloatArray,
        cost: float,
        k: FloatArray,
        gains: FloatArray,
        dv1: float,
        dv2: float,
    ) -> tuple[FloatArray, FloatArray, float] | None:
        """The first step of LINE_SEARCH_STEPS the search accepts (states, actions, cost), or None.

        A batch of k closed loops costs less than k single ones but far more than one (the
        simulations themselves dominate), so it pays only for step sizes likely to be needed:
        after a search that tried at least BATCH_FROM step sizes, this one rolls out that many at
        once, then all the rest at once; otherwise it tries BATCH_FROM - 1 one at a time
        (:meth:`MujocoDynamics.closed_loop`), then all the rest at once.
        """
        dyn = self.dynamics
        if dyn.reference:
            for alpha in LINE_SEARCH_STEPS:
                new_states, new_actions = dyn.closed_loop(states, actions, k, gains, alpha)
                new_cost = self.total_cost(new_states, new_actions)
                if self._accepts(cost, new_cost, alpha, dv1, dv2):
                    return new_states, new_actions, new_cost
            return None
        tries = self._search_tries
        first = [tries] if tries >= BATCH_FROM else [1] * (BATCH_FROM - 1)
        start = 0
        for size in [*first, len(LINE_SEARCH_STEPS)]:
            alphas = LINE_SEARCH_STEPS[start : start + size]
            if not alphas:
                break
            if len(alphas) == 1:
                rolled = dyn.closed_loop(states, actions, k, gains, alphas[0])
                chunk_states, chunk_actions = rolled[0][None], rolled[1][None]
            else:
                chunk_states, chunk_actions = dyn.closed_loops(states, actions, k, gains, alphas)
            for i, alpha in enumerate(alphas):
                # Copies: the cost sees arrays laid out as the one-at-a-time search's own.
                new_states, new_actions = chunk_states[i].copy(), chunk_actions[i].copy()
                new_cost = self.total_cost(new_states, new_actions)
                if self._accepts(cost, new_cost, alpha, dv1, dv2):
                    self._search_tries = start + i + 1
                    return new_states, new_actions, new_cost
            start += len(alphas)
        self._search_tries = len(LINE_SEARCH_STEPS)
        return None

    def check_request(self, x0: ArrayLike, horizon: int, actions: ArrayLike | None) -> tuple[FloatArray, int]:
        x = np.asarray(x0, dtype=np.float64)
        if x.shape != (self.state_dim,):
            raise ValueError(f"initial state must have {self.state_dim} entries (qpos then qvel), got shape {x.shape}")
        if not np.isfinite(x).all():
            bad = int(np.argwhere(~np.isfinite(x))[0, 0])
            raise ValueError(f"initial state[{bad}] is {float(x[bad])}; it must be finite")
        if isinstance(horizon, bool) or not isinstance(horizon, (int, np.integer)) or horizon < 1:
            raise ValueError(f"horizon must be an integer >= 1, got {horizon!r}")
        if actions is not None:
            u = np.asarray(actions, dtype=np.float64)
            if u.shape != (int(horizon), self.action_dim):
                raise ValueError(
                    f"warm-start actions must have shape ({int(horizon)}, {self.action_dim}), got {u.shape}"
                )
            if not np.isfinite(u).all():
                where = tuple(int(i) for i in np.argwhere(~np.isfinite(u))[0])
                raise ValueError(f"warm-start actions[{where[0]}, {where[1]}] is not finite")
        return x, int(horizon)

    def solve(
        self,
        x0: ArrayLike,
        horizon: int,
        *,
        time_budget: float,
        initial_actions: ArrayLike | None = None,
        initial_policy: Callable[[FloatArray], ArrayLike] | None = None,
        max_iterations: int = 100,
        min_iterations: int = 0,
        tolerance: float = 1e-7,
    ) -> TrajOptResult:
        """Optimise the actions from x0; warm start from an action sequence or a feedback policy.

        Stops when the relative cost decrease of an accepted step falls below ``tolerance`` or the
        feedforward is negligible (converged), at ``max_iterations``, when no step helps even at
        the largest regularisation, or when the budget would be exceeded by another iteration
        (the returned trajectory is then the best so far, and its W_x is from its own backward
        pass: the search stops early enough to leave time for that pass). The budget cannot stop
        the first ``min_iterations`` iterations: a caller that must improve on the warm start even
        on a slow machine asks for them, and overruns the budget by their time.
        """
        clock = self.clock
        start = clock()
        budget = check_time_budget(time_budget)
        if initial_actions is not None and initial_policy is not None:
            raise ValueError("give initial_actions or initial_policy, not both")
        if isinstance(max_iterations, bool) or not isinstance(max_iterations, (int, np.integer)) or max_iterations < 0:
            raise ValueError(f"max_iterations must be an integer >= 0, got {max_iterations!r}")
        if isinstance(min_iterations, bool) or not isinstance(min_iterations, (int, np.integer)) or min_iterations < 0:
            raise ValueError(f"min_iterations must be an integer >= 0, got {min_iterations!r}")
        x, horizon = self.check_request(x0, horizon, initial_actions)
        dyn = self.dynamics
        timings = {"rollout": 0.0, "derivatives": 0.0, "backward": 0.0, "line_search": 0.0}

        tick = clock()
        if initial_policy is not None:
            states, actions = dyn.rollout(x, horizon, policy=initial_policy)
        else:
            warm = np.zeros((horizon, self.action_dim)) if initial_actions is None else np.asarray(initial_actions)
            states, actions = dyn.rollout(x, horizon, actions=np.asarray(warm, dtype=np.float64))
        timings["rollout"] += clock() - tick
        cost = self.total_cost(states, actions)
        history = [cost]
        self._search_tries = 1  # a request's searches start afresh, whatever the last request's did
        mu, delta = 1e-6, 1.0
        k_prev = np.zeros((horizon, self.action_dim))
        iterations = 0
        converged = False
        last_decrease = math.inf
        need_derivatives = True
        pass_time = search_time = 0.0
        feedback: FloatArray | None = None  # the gains of a successful pass at the current trajectory

        while True:
            # Derivatives and backward pass at the current trajectory (whose W_x is returned).
            tick = clock()
            if need_derivatives:
                a, b = dyn.jacobians(states, actions)
                _, sx, sxx = self.cost.state_terms(states)
                _, cu, cuu = self.cost.control_terms(actions)
                sx, sxx = np.ascontiguousarray(sx), np.ascontiguousarray(sxx)
                cu, cuu = np.ascontiguousarray(cu), np.ascontiguousarray(cuu)
                timings["derivatives"] += clock() - tick
                need_derivatives = False
            tock = clock()
            while True:
                k, gains, wx, dv1, dv2, failed = self._backward_pass(
                    a, b, sx, sxx, cu, cuu, actions, dyn.lower, dyn.upper, mu, k_prev
                )
                if failed < 0 or mu > MU_MAX:
                    break
                delta = max(2.0, 2.0 * delta)
                mu = max(MU_MIN, mu * delta)
            timings["backward"] += clock() - tock
            pass_time = max(pass_time, clock() - tick)
            if failed >= 0:
                stop_reason = "regularisation limit"
                break
            feedback = gains
            k_prev = k
            step_size = float(np.mean(np.max(np.abs(k) / (np.abs(actions) + 1.0), axis=1)))
            if step_size < 1e-6 or last_decrease < tolerance:
                converged = True
                stop_reason = "converged"
                break
            if iterations >= max_iterations:
                stop_reason = "max iterations"
                break
            # Another iteration costs a line search and the next pass; leave time for both.
            if iterations >= min_iterations and clock() - start + search_time + pass_time > budget:
                stop_reason = "time budget"
                break

            tick = clock()
            step = self._line_search(states, actions, cost, k, gains, dv1, dv2)
            search_time = max(search_time, clock() - tick)
            timings["line_search"] += clock() - tick
            iterations += 1
            if step is not None:
                new_states, new_actions, new_cost = step
                last_decrease = (cost - new_cost) / max(abs(cost), 1e-12)
                states, actions, cost = new_states, new_actions, new_cost
                history.append(cost)
                need_derivatives = True
                feedback = None  # the pass was at the trajectory just left
                delta = min(0.5, delta / 2.0)
                mu = mu * delta if mu * delta > MU_MIN else 0.0
            else:
                delta = max(2.0, 2.0 * delta)
                mu = max(MU_MIN, mu * delta)
                if mu > MU_MAX:
                    stop_reason = "no improving step"
                    break

        return TrajOptResult(
            states=states[:-1].copy(),
            final_state=states[-1].copy(),
            actions=actions.copy(),
            value_gradient=wx,
            cost=float(cost),
            iterations=iterations,
            converged=converged,
            stop_reason=stop_reason,
            wall_time=clock() - start,
            cost_history=tuple(history),
            timings=timings,
            max_transition_norm=float(np.max(np.linalg.norm(a, 2, axis=(1, 2)))),
            gains=None if feedback is None else np.array(feedback, dtype=np.float64),
        )
