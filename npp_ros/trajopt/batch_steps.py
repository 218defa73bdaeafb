"""Many simulations of the plant's model stepped at once on ``mujoco.batch``, for the iLQR expert.

``mujoco.batch`` (experimental in the pinned MuJoCo) keeps each simulation's integration state in a
row of one array and steps the rows in C, on its own threads; a row's step is the step one MjData
takes from that state, bit for bit, at any thread count. Two parts of an iLQR iteration are many
independent simulations of one model:

- the centred differences of a whole trajectory: 2 (n + m) one-step simulations per step
  (:class:`BatchDifferences`, on ``threads`` threads);
- the line search's closed-loop rollouts of several step sizes (:class:`BatchClosedLoops`, one
  thread: a step of a few small simulations is shorter than handing it to a second thread).

Both give the numbers of the one-at-a-time code in :mod:`npp_ros.trajopt.dynamics` bit for bit (every
floating-point operation is the same operation on the same operands), so they change how fast a
request is answered, never its answer.

A batch copies its model when it is made, so a batch kept between requests is made again when the model's
physical parameters have changed since (a drawn robot, npp_ros.tasks.uncertainty, edits the model in place):
every request is planned on the model as it is at that request.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from npp_ros.policy.dataset import FloatArray


def usable_cores() -> int:
    """The cores this process may run on."""
    return max(1, len(os.sched_getaffinity(0)))


def default_threads(processes: int = 1) -> int:
    """Derivative threads per expert process, so that ``processes`` such processes use the cores, no more."""
    return max(1, usable_cores() // max(1, int(processes)))


def check_threads(threads: int) -> int:
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1:
        raise ValueError(f"threads must be an integer >= 1, got {threads!r}")
    return int(threads)


# The model fields a drawn robot edits, and those mj_setConst derives from them: a batch made before they changed
# holds a stale copy of the model.
PHYSICAL_FIELDS = (
    "body_mass", "body_inertia", "actuator_gear", "dof_damping", "dof_frictionloss", "dof_armature",
    "body_subtreemass", "body_invweight0", "dof_invweight0", "actuator_acc0",
)  # fmt: skip


def physical_values(model: Any) -> bytes:
    """The model's physical parameters as they are now, to compare with a batch's copy."""
    return b"".join(np.ascontiguousarray(getattr(model, name)).tobytes() for name in PHYSICAL_FIELDS)


class _Rows:
    """A batch of ``nsim`` simulations, each starting where ``mj_resetData`` leaves an MjData."""

    def __init__(self, model: Any, nsim: int, threads: int) -> None:
        import mujoco
        from mujoco import batch as mj_batch

        self.physical = physical_values(model)  # what the batch's copy of the model holds
        self.batch = mj_batch.Batch(model, nsim, threads)
        data = mujoco.MjData(model)  # freshly made: as mj_resetData leaves it
        spec = int(mujoco.mjtState.mjSTATE_INTEGRATION)
        self.reset_row = np.empty(mujoco.mj_stateSize(model, spec))
        mujoco.mj_getState(model, data, self.reset_row, spec)
        if self.batch.nstate != len(self.reset_row):  # a mujoco whose batch rows hold another state
            raise RuntimeError(f"mujoco.batch rows hold {self.batch.nstate} numbers, not the integration state")
        self.qpos, self.qvel, self.ctrl = self.batch.bind("qpos"), self.batch.bind("qvel"), self.batch.bind("ctrl")

    def reset(self) -> None:
        self.batch.state[:] = self.reset_row

    def current(self, model: Any) -> bool:
        """Whether the batch's copy of the model still holds the model's physical parameters."""
        return self.physical == physical_values(model)


class BatchDifferences:
    """A_t = d x_{t+1} / d x_t and B_t = d x_{t+1} / d u_t at every step, from one batch call.

    The same simulations, perturbations and quotients as :meth:`MujocoDynamics._rollout_jacobians`
    (each from a reset MjData), so the same Jacobians bit for bit.
    """

    def __init__(self, model: Any, threads: int, substeps: int = 1) -> None:
        self.model = model
        self.threads = check_threads(threads)
        self.substeps = substeps  # MuJoCo steps per control step, the control held
        self._rows: _Rows | None = None  # sized to the last trajectory's simulations

    def jacobians(
        self, states: FloatArray, actions: FloatArray, eps: float, lower: FloatArray, upper: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        horizon, m = actions.shape
        n = states.shape[1]
        nq = n // 2
        width = 2 * (n + m)  # simulations per step: +-eps on each state entry, then on each control
        if self._rows is None or self._rows.batch.nsim != horizon * width or not self._rows.current(self.model):
            self._rows = None  # let the old batch's memory go before the new one takes its own
            self._rows = _Rows(self.model, horizon * width, self.threads)
        rows = self._rows
        rows.reset()
        qpos = rows.qpos.reshape(horizon, width, nq)
        qvel = rows.qvel.reshape(horizon, width, nq)
        ctrl = rows.ctrl.reshape(horizon, width, m)
        x = states[:horizon]
        qpos[:] = x[:, None, :nq]
        qvel[:] = x[:, None, nq:]
        ctrl[:] = actions[:, None, :]
        for i in range(n):
            part, entry = (qpos, i) if i < nq else (qvel, i - nq)
            part[:, 2 * i, entry] += eps
            part[:, 2 * i + 1, entry] -= eps
        up = np.minimum(actions + eps, upper)  # a control at its bound is differenced one-sidedly
        down = np.maximum(actions - eps, lower)
        for j in range(m):
            ctrl[:, 2 * (n + j), j] = up[:, j]
            ctrl[:, 2 * (n + j) + 1, j] = down[:, j]
        rows.batch.step(nstep=self.substeps)
        return centred_quotients(np.concatenate([qpos, qvel], axis=2), up, down, eps)


def centred_quotients(nxt: FloatArray, up: FloatArray, down: FloatArray, eps: float) -> tuple[FloatArray, FloatArray]:
    """A_t and B_t from the next states (T, 2 (n + m), n) of the +-eps simulations, in their order.

    A control's quotient divides by its actual span, up - down: one-sided at a bound.
    """
    horizon, _, n = nxt.shape
    m = up.shape[1]
    a = np.empty((horizon, n, n))
    b = np.empty((horizon, n, m))
    for i in range(n):
        a[:, :, i] = (nxt[:, 2 * i] - nxt[:, 2 * i + 1]) / (2 * eps)
    for j in range(m):
        span = (up[:, j] - down[:, j])[:, None]
        b[:, :, j] = (nxt[:, 2 * (n + j)] - nxt[:, 2 * (n + j) + 1]) / span
    return a, b


class BatchClosedLoops:
    """The line search's rollouts of several step sizes at once, one simulation each.

    Each is :meth:`MujocoDynamics.closed_loop`'s rollout for its feedforward, bit for bit: the
    feedback ``gains[t] @ dx`` is taken per simulation by a stacked matmul, which computes each
    product with the same BLAS call as a single one.
    """

    def __init__(self, model: Any, substeps: int = 1) -> None:
        self.model = model
        self.substeps = substeps  # MuJoCo steps per control step, the control held
        self._rows: dict[int, _Rows] = {}  # by the number of step sizes searched at once

    def rollouts(
        self,
        ref_states: FloatArray,
        feedforward: FloatArray,
        gains: FloatArray,
        lower: FloatArray,
        upper: FloatArray,
    ) -> tuple[FloatArray, FloatArray]:
        """States (k, T + 1, n) and clamped actions (k, T, m) of u_t = clamp(ff_t + K_t (x_t - xbar_t))."""
        count, horizon, m = feedforward.shape
        n = ref_states.shape[1]
        nq = n // 2
        rows = self._rows.get(count)
        if rows is None or not rows.current(self.model):
            rows = self._rows[count] = _Rows(self.model, count, 1)
        rows.reset()
        step, qpos, qvel, ctrl, substeps = rows.batch.step, rows.qpos, rows.qvel, rows.ctrl, self.substeps
        states = np.empty((count, horizon + 1, n))
        actions = np.empty((count, horizon, m))
        states[:, 0] = ref_states[0]
        qpos[:] = ref_states[0, :nq]
        qvel[:] = ref_states[0, nq:]
        for t in range(horizon):
            dx = states[:, t] - ref_states[t]
            u = feedforward[:, t] + np.matmul(gains[t], dx[:, :, None])[:, :, 0]
            u = np.minimum(np.maximum(u, lower), upper)
            actions[:, t] = u
            ctrl[:] = u
            step(nstep=substeps)
            states[:, t + 1, :nq] = qpos
            states[:, t + 1, nq:] = qvel
        return states, actions
