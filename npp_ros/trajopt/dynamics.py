"""One control step of the plant's own MuJoCo model, rolled out and differenced.

The optimizer works on the plant's own compiled model (``plant.physics.model.ptr``), with its own
``MjData``, so the dynamics it optimises are the dynamics the sim runs: one control step is the
plant's ``substeps`` ``mj_step`` calls from (qpos, qvel, ctrl), the control held (one, unless the
plant says otherwise), and the linearisation of that step is ``mujoco.mjd_transitionFD`` with
centred differences (for one Euler substep; otherwise the same centred differences of whole control
steps, simulated). There is no second model.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike

from npp_ros.policy.dataset import FloatArray
from npp_ros.trajopt import batch_steps

DEFAULT_FD_EPS = 1e-6


class PhysicsPlant(Protocol):
    """What the optimizer needs from a plant: dm_control physics and its dimensions."""

    physics: object
    state_dim: int
    action_dim: int


def substeps_of(plant: object) -> int:
    """MuJoCo steps per control step, the control held (dm_control's n_sub_steps); a plant that says nothing: 1."""
    substeps = getattr(plant, "substeps", 1)
    if isinstance(substeps, bool) or not isinstance(substeps, (int, np.integer)) or substeps < 1:
        raise ValueError(f"substeps must be an integer >= 1, got {substeps!r}")
    return int(substeps)


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
        self.substeps = substeps_of(plant)
        # mjd_transitionFD does not support RK4 (dm_control's cartpole) and differences one MuJoCo step; the
        # same centred differences of a whole control step are then taken by simulating it, batched.
        self.batched_fd = int(m.opt.integrator) == int(mujoco.mjtIntegrator.mjINT_RK4) or self.substeps > 1
        self._spec = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)
        self._qpos_at = int(mujoco.mj_stateSize(m, int(mujoco.mjtState.mjSTATE_TIME)))
        self.reference = bool(reference)
        self._threads = batch_steps.check_threads(threads)
        self._differences = batch_steps.BatchDifferences(m, self._threads, self.substeps)
        self._closed_loops = batch_steps.BatchClosedLoops(m, self.substeps)

    @property
    def threads(self) -> int:
        """Threads of the batched centred differences (the answers are the same at any count)."""
        return self._threads

    @threads.setter
    def threads(self, threads: int) -> None:
        self._threads = batch_steps.check_threads(threads)
        self._differences = batch_steps.BatchDifferences(self.model, self._threads, self.substeps)

    @property
    def derivatives_by(self) -> str:
        """How :meth:`jacobians` takes its centred differences, for reports."""
        if not self.batched_fd:
            return "mujoco.mjd_transitionFD"
        why = "RK4" if self.substeps == 1 else f"{self.substeps} MuJoCo steps per control step"
        if self.reference:
            return f"batched one-step rollouts (mujoco.rollout, {why})"
        return f"one-step simulations on mujoco.batch, {self._threads} thread{'s' * (self._threads > 1)} ({why})"

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
        self._mujoco.mj_step(self.model, self.data, self.substeps)
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
        self._mujoco.mj_step(self.model, self.data, self.substeps)
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
        """Centred differences from 2 (n + m) one-control-step rollouts per step, all in one C call.

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
        k = self.substeps
        out, _ = mj_rollout.rollout(
            self.model,
            self.data,
            initial,
            np.repeat(us.reshape(-1, 1, m), k, axis=1),  # the control held over the control step's substeps
            control_spec=int(self._mujoco.mjtState.mjSTATE_CTRL),
            nstep=k,
        )
        nxt = out[:, k - 1, lo : lo + n].reshape(horizon, width, n)
        return batch_steps.centred_quotients(nxt, up, down, eps)
