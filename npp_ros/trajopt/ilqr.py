"""Iterative LQR (box-constrained, Levenberg-Marquardt) on MuJoCo's own derivatives of the plant.

The optimizer is the TrajectoryOptimizer of Algorithm 1 for plants without a closed form. It
works on the plant's own compiled MuJoCo model (``plant.physics.model.ptr``), with its own
``MjData``, so the dynamics it optimises are the dynamics the sim runs: one control step is one
``mj_step`` from (qpos, qvel, ctrl), and the linearisation of that step is
``mujoco.mjd_transitionFD`` with centred differences. There is no second model.

Cost convention (as dm_control scores a step on the state *after* it): the objective of a
request from x_0 with actions u_0 .. u_{T-1} is

    J = sum_{t<T} [ c(u_t) + s(x_{t+1}) ],

``s`` the state cost, ``c`` the control cost. On the lqr tasks s(x) = 0.5 x'Qc x and
c(u) = 0.5 u'Ru make J = T - (the T-step return), so the optimum is the exact finite-horizon
optimum of the task. Other tasks (the pendulum) use a smooth surrogate; the values handed to the
dataset are always the *true* rewards, replayed on the plant (:func:`replay_return_to_go`).

Determinism: every operation is sequential floating point on fixed inputs, so a request (start
state, horizon, warm start, options) gives the same arrays bit for bit whenever it stops by
convergence or the iteration cap. A stop by the time budget depends on the machine's speed by
nature; the result says so (``stop_reason``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike

from npp_ros.certificate.values import ValueBasis, theorem_34_condition
from npp_ros.policy.dataset import FloatArray, Trajectory
from npp_ros.trajopt import batch_steps

DEFAULT_FD_EPS = 1e-6
MU_MIN = 1e-8
MU_MAX = 1e10
LINE_SEARCH_STEPS = tuple(0.5**i for i in range(11))
BATCH_FROM = 4  # step sizes a line search rolls out in one batch at the least (fewer go one at a time)


class PhysicsPlant(Protocol):
    """What the optimizer needs from a plant: dm_control physics and its dimensions."""

    physics: object
    state_dim: int
    action_dim: int


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


# ----------------------------------------------------------------------------- dynamics
class MujocoDynamics:
    """One control step of the plant's own model, and its centred finite-difference Jacobians.

    The state is [qpos, qvel]; that is a coordinate chart only when nq = nv (hinge and slide
    joints, as on the lqr, pendulum and cartpole tasks) and there is no actuator activation.

    RK4 models are differenced on ``mujoco.batch`` with ``threads`` threads (1 unless the caller
    knows the cores are free: see :func:`~npp_ros.trajopt.batch_steps.default_threads`), and the
    line search rolls several step sizes out at once there
    (:mod:`npp_ros.trajopt.batch_steps`); the numbers are those of the one-at-a-time code, which
    ``reference=True`` runs instead (to check against, and to time side by side).
    """

    def __init__(
        self, plant: PhysicsPlant, fd_eps: float = DEFAULT_FD_EPS, *, threads: int = 1, reference: bool = False
    ) -> None:
        import mujoco

        if not (math.isfinite(fd_eps) and fd_eps > 0):
            raise ValueError(f"fd_eps must be finite and > 0, got {fd_eps!r}")
        self._mujoco = mujoco
        self.model = plant.physics.model.ptr
        m = self.model
        if m.nq != m.nv or m.na != 0:
            raise ValueError(
                f"the state [qpos, qvel] needs nq = nv and no activations; got nq={m.nq} nv={m.nv} na={m.na}"
            )
        self.data = mujoco.MjData(m)
        # Views into data's buffers, kept: reading MjData attributes builds a new array each time.
        self._qpos, self._qvel, self._ctrl = self.data.qpos, self.data.qvel, self.data.ctrl
        self.nq = int(m.nq)
        self.state_dim = 2 * self.nq
        self.action_dim = int(m.nu)
        if (plant.state_dim, plant.action_dim) != (self.state_dim, self.action_dim):
            raise ValueError(
                f"plant reports state_dim {plant.state_dim}, action_dim {plant.action_dim}; "
                f"its model has {self.state_dim}, {self.action_dim}"
            )
        self.fd_eps = float(fd_eps)
        limited = np.asarray(m.actuator_ctrllimited, dtype=bool)
        ranges = np.asarray(m.actuator_ctrlrange, dtype=np.float64).reshape(-1, 2)
        self.lower = np.where(limited, ranges[:, 0], -np.inf)
        self.upper = np.where(limited, ranges[:, 1], np.inf)
        # mjd_transitionFD does not support RK4 (dm_control's cartpole); the same centred
        # differences are then taken by batched one-step rollouts in MuJoCo's C rollout.
        self.batched_fd = int(m.opt.integrator) == int(mujoco.mjtIntegrator.mjINT_RK4)
        self._spec = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)
        self._qpos_at = int(mujoco.mj_stateSize(m, int(mujoco.mjtState.mjSTATE_TIME)))
        self.reference = bool(reference)
        self._threads = batch_steps.check_threads(threads)
        self._differences = batch_steps.BatchDifferences(m, self._threads)
        self._closed_loops = batch_steps.BatchClosedLoops(m)

    @property
    def threads(self) -> int:
        """Threads of the batched centred differences (the answers are the same at any count)."""
        return self._threads

    @threads.setter
    def threads(self, threads: int) -> None:
        self._threads = batch_steps.check_threads(threads)
        self._differences = batch_steps.BatchDifferences(self.model, self._threads)

    @property
    def derivatives_by(self) -> str:
        """How :meth:`jacobians` takes its centred differences, for reports."""
        if not self.batched_fd:
            return "mujoco.mjd_transitionFD"
        if self.reference:
            return "batched one-step rollouts (mujoco.rollout, RK4)"
        return f"one-step simulations on mujoco.batch, {self._threads} thread{'s' * (self._threads > 1)} (RK4)"

    def _start(self, x: FloatArray, u: FloatArray) -> None:
        """Fresh data at (x, u), as the plant's reset leaves it: no solver warm start or time carried
        over from an earlier request, so a request's numbers depend on the request alone."""
        self._mujoco.mj_resetData(self.model, self.data)
        self._load(x, u)

    def _load(self, x: FloatArray, u: FloatArray) -> None:
        self._qpos[:] = x[: self.nq]
        self._qvel[:] = x[self.nq :]
        self._ctrl[:] = u

    def step(self, x: FloatArray, u: FloatArray) -> FloatArray:
        self._load(x, u)
        self._mujoco.mj_step(self.model, self.data)
        return np.concatenate([self._qpos, self._qvel])

    def rollout(
        self,
        x0: FloatArray,
        horizon: int,
        actions: FloatArray | None = None,
        policy: Callable[[FloatArray], ArrayLike] | None = None,
    ) -> tuple[FloatArray, FloatArray]:
        """States x_0 .. x_T and the applied (clamped) actions, open loop or under a feedback policy."""
        states = np.empty((horizon + 1, self.state_dim))
        applied = np.empty((horizon, self.action_dim))
        states[0] = x0
        self._start(x0, np.zeros(self.action_dim))
        for t in range(horizon):
            u = actions[t] if policy is None else np.asarray(policy(states[t]), dtype=np.float64).reshape(-1)
            applied[t] = np.minimum(np.maximum(u, self.lower), self.upper)
            self._advance(applied[t], states[t + 1])
        return states, applied

    def _advance(self, u: FloatArray, out: FloatArray) -> None:
        """One step from the state already in ``data`` (the previous step's result, as on the plant)."""
        self._ctrl[:] = u
        self._mujoco.mj_step(self.model, self.data)
        out[: self.nq] = self._qpos
        out[self.nq :] = self._qvel

    def closed_loop(
        self, ref_states: FloatArray, ref_actions: FloatArray, k: FloatArray, gains: FloatArray, alpha: float
    ) -> tuple[FloatArray, FloatArray]:
        """The line search's rollout: u_t = clamp(ubar_t + alpha k_t + K_t (x_t - xbar_t))."""
        horizon = len(ref_actions)
        states = np.empty_like(ref_states)
        actions = ref_actions + alpha * k
        states[0] = ref_states[0]
        self._start(ref_states[0], actions[0])
        lo, hi = self.lower, self.upper
        advance = self._advance
        for t in range(horizon):
            u = actions[t] + gains[t] @ (states[t] - ref_states[t])
            actions[t] = np.minimum(np.maximum(u, lo), hi)
            advance(actions[t], states[t + 1])
        return states, actions

    def closed_loops(
        self, ref_states: FloatArray, ref_actions: FloatArray, k: FloatArray, gains: FloatArray, alphas: Sequence[float]
    ) -> tuple[FloatArray, FloatArray]:
        """:meth:`closed_loop` for each of ``alphas`` at once: states (len(alphas), T + 1, n), actions."""
        feedforward = np.stack([ref_actions + alpha * k for alpha in alphas])
        return self._closed_loops.rollouts(ref_states, feedforward, gains, self.lower, self.upper)

    def jacobians(self, states: FloatArray, actions: FloatArray) -> tuple[FloatArray, FloatArray]:
        """A_t = d x_{t+1} / d x_t, B_t = d x_{t+1} / d u_t by centred differences, per step."""
        if self.batched_fd and not self.reference:
            return self._differences.jacobians(states, actions, self.fd_eps, self.lower, self.upper)
        if self.batched_fd:
            return self._rollout_jacobians(states, actions)
        horizon = len(actions)
        a = np.empty((horizon, self.state_dim, self.state_dim))
        b = np.empty((horizon, self.state_dim, self.action_dim))
        fd = self._mujoco.mjd_transitionFD
        m, d, eps, nq = self.model, self.data, self.fd_eps, self.nq
        qpos, qvel, ctrl = self._qpos, self._qvel, self._ctrl
        self._mujoco.mj_resetData(m, d)
        for t in range(horizon):
            x = states[t]
            qpos[:] = x[:nq]
            qvel[:] = x[nq:]
            ctrl[:] = actions[t]
            fd(m, d, eps, True, a[t], b[t], None, None)
        return a, b

    def _rollout_jacobians(self, states: FloatArray, actions: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Centred differences from 2 (n + m) one-step rollouts per step, all in one C call.

        A control at its bound is differenced one-sidedly (MuJoCo clamps ctrl, so a step past the
        bound would halve the slope), as mjd_transitionFD does.
        """
        from mujoco import rollout as mj_rollout

        horizon, n, m, eps = len(actions), self.state_dim, self.action_dim, self.fd_eps
        x, u = states[:horizon], actions
        width = 2 * (n + m)
        xs = np.repeat(x[:, None, :], width, axis=1)
        us = np.repeat(u[:, None, :], width, axis=1)
        for i in range(n):
            xs[:, 2 * i, i] += eps
            xs[:, 2 * i + 1, i] -= eps
        up = np.minimum(u + eps, self.upper)
        down = np.maximum(u - eps, self.lower)
        for j in range(m):
            us[:, 2 * (n + j), j] = up[:, j]
            us[:, 2 * (n + j) + 1, j] = down[:, j]
        self._mujoco.mj_resetData(self.model, self.data)
        size = self._mujoco.mj_stateSize(self.model, self._spec)
        template = np.empty(size)
        self._mujoco.mj_getState(self.model, self.data, template, self._spec)
        initial = np.repeat(template[None, :], horizon * width, axis=0)
        lo = self._qpos_at
        initial[:, lo : lo + n] = xs.reshape(-1, n)
        out, _ = mj_rollout.rollout(
            self.model,
            self.data,
            initial,
            us.reshape(-1, 1, m),
            control_spec=int(self._mujoco.mjtState.mjSTATE_CTRL),
            nstep=1,
        )
        nxt = out[:, 0, lo : lo + n].reshape(horizon, width, n)
        return batch_steps.centred_quotients(nxt, up, down, eps)


# ----------------------------------------------------------------------------- the optimizer
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
        start = time.perf_counter()
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

        tick = time.perf_counter()
        if initial_policy is not None:
            states, actions = dyn.rollout(x, horizon, policy=initial_policy)
        else:
            warm = np.zeros((horizon, self.action_dim)) if initial_actions is None else np.asarray(initial_actions)
            states, actions = dyn.rollout(x, horizon, actions=np.asarray(warm, dtype=np.float64))
        timings["rollout"] += time.perf_counter() - tick
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
            tick = time.perf_counter()
            if need_derivatives:
                a, b = dyn.jacobians(states, actions)
                _, sx, sxx = self.cost.state_terms(states)
                _, cu, cuu = self.cost.control_terms(actions)
                sx, sxx = np.ascontiguousarray(sx), np.ascontiguousarray(sxx)
                cu, cuu = np.ascontiguousarray(cu), np.ascontiguousarray(cuu)
                timings["derivatives"] += time.perf_counter() - tick
                need_derivatives = False
            tock = time.perf_counter()
            while True:
                k, gains, wx, dv1, dv2, failed = self._backward_pass(
                    a, b, sx, sxx, cu, cuu, actions, dyn.lower, dyn.upper, mu, k_prev
                )
                if failed < 0 or mu > MU_MAX:
                    break
                delta = max(2.0, 2.0 * delta)
                mu = max(MU_MIN, mu * delta)
            timings["backward"] += time.perf_counter() - tock
            pass_time = max(pass_time, time.perf_counter() - tick)
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
            if iterations >= min_iterations and time.perf_counter() - start + search_time + pass_time > budget:
                stop_reason = "time budget"
                break

            tick = time.perf_counter()
            step = self._line_search(states, actions, cost, k, gains, dv1, dv2)
            search_time = max(search_time, time.perf_counter() - tick)
            timings["line_search"] += time.perf_counter() - tick
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
            wall_time=time.perf_counter() - start,
            cost_history=tuple(history),
            timings=timings,
            max_transition_norm=float(np.max(np.linalg.norm(a, 2, axis=(1, 2)))),
            gains=None if feedback is None else np.array(feedback, dtype=np.float64),
        )


# ----------------------------------------------------------------------------- true returns
class SteppablePlant(Protocol):
    def reset(self, state: ArrayLike) -> FloatArray: ...

    def step(self, action: ArrayLike) -> float: ...

    def state(self) -> FloatArray: ...


def replay_rewards(
    plant: SteppablePlant,
    x0: ArrayLike,
    actions: FloatArray,
    continuation: Callable[[FloatArray], ArrayLike] | None = None,
    extra_steps: int = 0,
) -> tuple[FloatArray, FloatArray]:
    """Replay ``actions`` on the plant from x0; then ``extra_steps`` more under ``continuation``.

    Returns the raw states x_0 .. x_{T-1} of the replayed actions and every reward, the task's own
    (``plant.step``). The raw state is ``plant.raw_state()`` where the plant stores another
    representation.
    """
    read = getattr(plant, "raw_state", plant.state)
    horizon = len(actions)
    states = np.empty((horizon, len(np.asarray(x0))))
    rewards = np.empty(horizon + extra_steps)
    plant.reset(x0)
    for t in range(horizon):
        states[t] = read()
        rewards[t] = plant.step(actions[t])
    if extra_steps and continuation is None:
        raise ValueError("extra_steps needs a continuation policy")
    for t in range(horizon, horizon + extra_steps):
        rewards[t] = plant.step(continuation(read()))
    return states, rewards


def return_to_go(rewards: FloatArray) -> FloatArray:
    """Q_t = sum_{k>=t} r_k."""
    return np.cumsum(rewards[::-1])[::-1].copy()


def window_values(rewards: FloatArray, window: int) -> FloatArray:
    """Q_t = sum_{k=t}^{t+window-1} r_k, for every t with a full window (exact for 0/1 rewards)."""
    sums = np.concatenate([[0.0], np.cumsum(rewards)])
    return sums[window:] - sums[:-window]


def replay_return_to_go(plant: SteppablePlant, x0: ArrayLike, actions: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Replay ``actions`` on the plant from x0: raw states x_0 .. x_{T-1} and Q_t = sum_{k>=t} r_k.

    Q_0 is the trajectory's true return.
    """
    states, rewards = replay_rewards(plant, x0, actions)
    return states, return_to_go(rewards)


@dataclass(frozen=True)
class ExpertSolution:
    """What one expert request produced: the dataset trajectory and how it was found."""

    trajectory: Trajectory  # stored states, actions, Q_t (true return-to-go)
    optimization: TrajOptResult
    raw_states: FloatArray  # the plant's [qpos, qvel] as replayed
    kept_warm_start: bool = False  # the warm start's true return beat the optimised one

    @property
    def expert_return(self) -> float:
        return float(self.trajectory.values[0])


VALUE_MODES = ("return-to-go", "window")
DEFAULT_VALUES = "window"  # one value per visited state, as the lqr expert's: what every optimizer expert stores
DEFAULT_TIME_BUDGET_S = 5.0  # wall-clock seconds per request, for every optimizer expert and its task


class OptimizingExpert:
    """An expert oracle from a plant, a smooth cost, a warm-start controller and a state map.

    Each request: roll the warm-start controller out from s0 and replay its actions on the plant,
    refine with :class:`ILQR` in what is left of ``time_budget`` seconds (see
    :meth:`optimizer_budget`), then replay the optimised actions on the plant for the task's true
    rewards, keeping the warm start's actions if they score better. Q_0 is the trajectory's H-step
    return in both value modes; they differ for t > 0:

    - ``"return-to-go"``: Q_t = r_t + ... + r_{H-1}. Q then depends on the time left, not only
      on the state: a state held to the end (the pendulum upright) has Q = H - t, so one state
      carries many values and no finite L fits the data.
    - ``"window"``: Q_t = r_t + ... + r_{t+H-1}, the H-step value of s_t, the trajectory
      continued past H by the warm-start controller. This is the stationary convention of the
      lqr expert (V*(s_t) = H - J*(s_t)).

    Stored states are ``represent(raw state)``.

    The time budget covers the whole request and is wall-clock, so it is met when the machine
    leaves iLQR at least ``min_optimizer_share`` of it; on a slower machine iLQR still gets that
    share and ``min_iterations`` iterations, and the request overruns by them. No timing carries
    over from one request to the next.
    """

    min_optimizer_share = 0.2  # of time_budget: iLQR's at least, whatever the warm start and replays take
    min_iterations = 1  # iLQR iterations the budget cannot cut (convergence and max_iterations can)

    def __init__(
        self,
        plant: PhysicsPlant,
        cost: StageCost,
        warm_start: Callable[[FloatArray], ArrayLike],
        represent: Callable[[FloatArray], FloatArray],
        *,
        horizon: int,
        time_budget: float,
        max_iterations: int = 50,
        values: str = DEFAULT_VALUES,
    ) -> None:
        if values not in VALUE_MODES:
            raise ValueError(f"values must be one of {', '.join(VALUE_MODES)}; got {values!r}")
        if isinstance(horizon, bool) or not isinstance(horizon, (int, np.integer)) or horizon < 1:
            raise ValueError(f"horizon must be an integer >= 1, got {horizon!r}")
        self.values = values
        self.horizon = int(horizon)
        self.time_budget = check_time_budget(time_budget)
        self.max_iterations = int(max_iterations)
        self.plant = plant
        self.cost = cost
        self.optimizer = ILQR(plant, cost)
        self.warm_start = warm_start
        self.represent = represent
        self.max_slope_seen = 0.0
        self.max_transition_norm = 0.0
        self.requests = 0
        self.budget_stops = 0  # requests the time budget stopped (their answers depend on the machine's speed)
        self.clock: Callable[[], float] = time.perf_counter  # times the request's phases (a test may fake it)
        self.task = "mujoco"
        self.reward_lipschitz = math.inf  # a task that knows its reward's slope says so
        self.reward_lipschitz_detail = "not known for this task"
        self.no_lipschitz_bound = ""  # a task whose true values are discontinuous in the state says why

    def solve(self, initial_state: ArrayLike, horizon: int | None = None) -> ExpertSolution:
        """One request. The answer is never worse than the warm start under the true reward: when
        the surrogate's optimum replays to a lower H-step return, the warm start's actions are
        kept (with W_x from a backward pass at them) and ``kept_warm_start`` says so.

        The plant is replayed twice: the warm start's H actions (before iLQR, so their time is
        known when iLQR's budget is set), and the optimised actions, in window mode continued by
        the warm-start controller for H - 1 more steps. The first H rewards of that continued
        replay are the H-step return compared with the warm start's (a replay starts from a reset
        plant, so its first H steps do not depend on what follows them).
        """
        x0 = self.plant.check_state(initial_state, "requested state")
        steps = self.horizon if horizon is None or horizon == 0 else int(horizon)
        window = self.values == "window"
        start = self.clock()
        warm = self.warm_actions(x0, steps)
        rolled = self.clock()
        warm_raw, warm_rewards = replay_rewards(self.plant, x0, warm)
        replayed = self.clock()
        result = self.optimizer.solve(
            x0,
            steps,
            time_budget=self.optimizer_budget(rolled - start, replayed - rolled, replayed - start),
            initial_actions=warm,
            max_iterations=self.max_iterations,
            min_iterations=self.min_iterations,
        )
        stopped_by_budget = result.timed_out  # before a kept warm start replaces the result: it decided that too
        extra = steps - 1 if window else 0
        raw, rewards = replay_rewards(self.plant, x0, result.actions, self.warm_start if window else None, extra)
        kept_warm_start = float(warm_rewards.sum()) > float(rewards[:steps].sum())
        if kept_warm_start:
            result = self.optimizer.solve(x0, steps, time_budget=60.0, initial_actions=warm, max_iterations=0)
            if window:
                raw, rewards = replay_rewards(self.plant, x0, result.actions, self.warm_start, extra)
            else:  # result.actions == warm (the rollout clamped them; clamping again changes nothing)
                raw, rewards = warm_raw, warm_rewards
        values = window_values(rewards, steps) if window else return_to_go(rewards)
        self.max_slope_seen = max(self.max_slope_seen, result.max_value_slope)
        self.max_transition_norm = max(self.max_transition_norm, result.max_transition_norm)
        self.requests += 1
        self.budget_stops += stopped_by_budget
        # Q_0 is the replayed H-step return in both value modes: the expert's own return at s0 (oracle mode).
        trajectory = Trajectory(
            self.represent(raw), result.actions.copy(), values, expert_return=float(values[0]), gains=result.gains
        )
        return ExpertSolution(trajectory, result, raw, kept_warm_start)

    def warm_actions(self, x0: FloatArray, steps: int) -> FloatArray:
        """The ``steps`` actions iLQR starts from: ``warm_start`` rolled out from ``x0`` (clamped).

        A subclass that plans its start another way overrides this; ``warm_start`` still continues
        every replay past H (window values), and ``optimizer_budget`` reads this call's seconds as
        the controller's rollout time.
        """
        _, actions = self.optimizer.dynamics.rollout(x0, steps, policy=self.warm_start)
        return actions

    def optimizer_budget(self, rollout_seconds: float, replay_seconds: float, spent: float) -> float:
        """iLQR's seconds: the budget less what this request has spent and its replay still to come.

        The replay to come is predicted from this request's own, at this moment's machine load: the
        optimised actions' replay takes the warm start's (``replay_seconds``, H plant steps); window
        mode's H - 1 continued steps add as much plus the controller, whose time is within the warm
        start's rollout (``rollout_seconds``, controller and model steps). Never below
        ``min_optimizer_share`` of the budget, so a loaded machine gets a shorter optimisation, not
        none. (A kept warm start's backward pass and replay are not predicted: they are rare.)
        """
        to_come = replay_seconds + (replay_seconds + rollout_seconds if self.values == "window" else 0.0)
        return max(self.time_budget - spent - to_come, self.min_optimizer_share * self.time_budget)

    def trajectory(self, initial_state: ArrayLike, horizon: int | None = None) -> Trajectory:
        return self.solve(initial_state, horizon).trajectory

    def slope_floor(self) -> float:
        """max |W_x| over every request so far (the surrogate cost-to-go's slope; see TrajOptResult).

        A floor for L: the optimizer's own value already rises this steeply along its trajectories.
        It is not a bound (a slope seen is never more than the slope there is).
        """
        return self.max_slope_seen

    def value_basis(self) -> ValueBasis:
        """What the stored values are; a tail bound only where they are a function of the state.

        ``window``: Q at a requested s0 is the replayed H-step return of the expert's actions, so a
        claim about the expert's H-step return from s0 needs no tail (0). ``return-to-go``: the
        stored values depend on the time left, so no tail is offered and rollout mode refuses.
        """
        what = (
            f"the {self.task} iLQR expert's own H-step return (H = {self.horizon}): a local optimum of a "
            "smooth surrogate, not V*_H (Appendix B's setting)"
        )
        if self.values == "window":
            return ValueBasis(
                what, lambda s0: 0.0, "Q_0 is the expert's replayed H-step return from s0",
                no_lipschitz_bound=self.no_lipschitz_bound,
            )  # fmt: skip
        return ValueBasis(
            what, None, "return-to-go values depend on the time left, not only on the state",
            no_lipschitz_bound=self.no_lipschitz_bound,
        )  # fmt: skip

    def theorem_34_condition(self, lipschitz: float) -> tuple[bool, str]:
        """Theorem 3.4's condition with L_f = the largest |A_t| seen on the expert's trajectories."""
        if self.requests == 0:
            return False, "Theorem 3.4's condition is unchecked: no expert trajectory yet gives L_f"
        where = f"L_f seen on {self.requests} expert trajectories; L_r {self.reward_lipschitz_detail}"
        return theorem_34_condition(lipschitz, 1.0, self.max_transition_norm, self.reward_lipschitz, where)


def time_trajectories(
    solve: Callable[[FloatArray], object], initial_states: Sequence[ArrayLike] | FloatArray
) -> FloatArray:
    """Seconds per request of ``solve(s0)`` (wall clock, one request at a time), for benchmarks."""
    out = np.empty(len(initial_states))
    for i, s0 in enumerate(initial_states):
        tick = time.perf_counter()
        solve(np.asarray(s0, dtype=np.float64))
        out[i] = time.perf_counter() - tick
    return out
