"""The dm_control lqr plants and their closed-form optimal controller (the expert oracle).

Value convention (the README's "Value convention"): with the default gamma = 1 the value is the
undiscounted H-step return scale, V*(x) = H - J*(x), J* the infinite-horizon optimal cost; with
gamma < 1 it is V*(x) = 1 / (1 - gamma) - J*_gamma(x).

dm_control scores each step on the state *after* it: r = 1 - 0.5|q'|^2 - 0.05|u|^2, with
x' = A x + B u. In terms of the pre-step state the stage cost is therefore
c(x, u) = 0.5 (Ax + Bu)' Qc (Ax + Bu) + 0.5 u' R u, a DARE with a cross term, which this module
solves exactly, so the expert's values equal its measured returns up to the horizon's tail.
"""

from __future__ import annotations

import copy
import hashlib
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.linalg import solve_discrete_are, solve_discrete_lyapunov

from npp_ros.certificate.certifier import CheckedQuantity
from npp_ros.certificate.values import ValueBasis, theorem_34_condition
from npp_ros.policy.dataset import FloatArray, Trajectory
from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.policy.vectors import finite_vector
from npp_ros.tasks.registry import DEFAULT_OPTIONS, Expert, ExpertOptions, Plant, Task, UnknownTaskError, check_horizon
from npp_ros.tasks.registry import MAX_HORIZON as MAX_HORIZON  # re-exported: callers of the lqr module use them
from npp_ros.tasks.registry import episode_rng as episode_rng
from npp_ros.tasks.rollout import rollout, rollout_batch
from npp_ros.tasks.success import SuccessCriterion, WithinBand
from npp_ros.tasks.uncertainty import Robot

TASKS: dict[str, tuple[int, int]] = {"lqr_2_1": (2, 1), "lqr_6_2": (6, 2)}
"""Task name -> (bodies, actuators)."""

PAPER_LIPSCHITZ: dict[str, float] = {"lqr_2_1": 50.0, "lqr_6_2": 200.0}
PAPER_EPSILON: dict[str, float] = {"lqr_2_1": 50.0, "lqr_6_2": 300.0}
DEFAULT_HORIZON = 1000
INITIAL_RADIUS = math.sqrt(2.0)
# The analytic L is a supremum computed in floating point (relative error ~1e-15); it is used with
# this relative margin so that rounding can never put a slope of V above it.
ANALYTIC_MARGIN = 1e-6
# Slack for the rounding of stored values, bounds and returns (absolute error ~1e-13 at H = 1000).
ROUNDING_SLACK = 1e-9
SUCCESS_SHARE = 0.1  # the last 10% of an episode: 100 steps (3 s) at H = 1000
SUCCESS_BAND: dict[str, float] = {"lqr_2_1": 0.15, "lqr_6_2": 0.4}
"""Settled: every joint position within this of 0 over the last 10% of the episode. From rho's sphere of radius
sqrt(2) the optimal closed loop's largest |q_i| over steps 900 .. 999 is sqrt(2) max_t max_i |(Phi^t)_(q_i, q)| =
0.105 on lqr_2_1 and 0.331 on lqr_6_2 (its slowest closed-loop mode decays as 0.999^t), so at H = 1000 the optimal
expert meets the band from every s0, with room for a policy that follows it closely; without control the springs
keep positions near their start (1.2 to 1.4 on lqr_2_1 over those steps). At a shorter horizon the expert has not
settled yet (0.53 on lqr_2_1 at H = 200) and the criterion says so."""


def check_task(task: str) -> tuple[int, int]:
    if task not in TASKS:
        raise UnknownTaskError(f"unknown task {task!r}; known tasks: {', '.join(sorted(TASKS))}")
    return TASKS[task]


def sample_initial_state(task: str, rng: np.random.Generator) -> FloatArray:
    """s0 ~ rho: positions uniform on the sphere of radius sqrt(2), zero velocity (as dm_control)."""
    bodies, _ = check_task(task)
    unit = rng.standard_normal(bodies)
    return np.concatenate([INITIAL_RADIUS * unit / np.linalg.norm(unit), np.zeros(bodies)])


def initial_state_diameter() -> float:
    """diam(S0) for the lqr tasks: the position sphere of radius sqrt(2)."""
    return 2 * INITIAL_RADIUS


class LQRPlant:
    """A dm_control lqr task driven step by step, with an explicit horizon and no termination."""

    def __init__(self, task: str, seed: int) -> None:
        self.bodies, self.actuators = check_task(task)
        os.environ.setdefault("MUJOCO_GL", "disable")  # nothing renders; silence the GLFW probe
        from dm_control import suite

        env = suite.load("lqr", task, task_kwargs={"random": int(seed)})
        self.task = task
        self.seed = int(seed)
        self.physics = env.physics
        self._task = env.task
        model = self.physics.model
        self.dt = float(model.opt.timestep)
        self.state_dim = 2 * self.bodies
        self.action_dim = self.actuators
        self.joint_names = [model.id2name(i, "joint") for i in range(model.njnt)]
        self.actuated_joint_names = [model.id2name(int(model.actuator_trnid[i, 0]), "joint") for i in range(model.nu)]
        self.control_cost_coef = float(self._task.control_cost_coef)
        self.angles: tuple[int, ...] = ()  # positions of linear springs: nothing wraps
        self.action_low = np.full(self.action_dim, -np.inf)  # the lqr actuators are not ctrllimited
        self.action_high = np.full(self.action_dim, np.inf)

    # -------------------------------------------------------------- description
    @property
    def state_cost(self) -> FloatArray:
        """Qc: the reward penalises positions only."""
        return np.diag(np.concatenate([np.ones(self.bodies), np.zeros(self.bodies)]))

    @property
    def control_cost(self) -> FloatArray:
        return self.control_cost_coef * np.eye(self.action_dim)

    def model_sha256(self) -> str:
        """Fingerprint of the compiled model, so an expert can prove it models this plant."""
        m = self.physics.model
        parts = [m.jnt_stiffness, m.dof_damping, m.opt.timestep, m.actuator_gear, m.body_mass]
        blob = b"".join(np.ascontiguousarray(np.asarray(x, dtype=np.float64)).tobytes() for x in parts)
        return hashlib.sha256(blob).hexdigest()

    def linearization(self) -> tuple[FloatArray, FloatArray]:
        """x' = A x + B u, exact: the plant is linear, so centred differences are exact to rounding."""
        import mujoco

        saved = self.state()
        self.reset(np.zeros(self.state_dim))
        m, d = self.physics.model.ptr, self.physics.data.ptr
        nx = 2 * m.nv + m.na
        a = np.zeros((nx, nx))
        b = np.zeros((nx, m.nu))
        mujoco.mjd_transitionFD(m, d, 1e-6, True, a, b, None, None)
        self.reset(saved)
        return a, b

    def clone(self) -> LQRPlant:
        """Another plant on the same compiled model with its own MuJoCo data (cheap, for batches)."""
        twin = copy.copy(self)
        twin.physics = self.physics.copy(share_model=True)
        return twin

    # -------------------------------------------------------------- stepping
    def check_state(self, state: ArrayLike, what: str = "state") -> FloatArray:
        return finite_vector(state, self.state_dim, what, f"qpos then qvel of {self.bodies} joints of {self.task}")

    def check_action(self, action: ArrayLike) -> FloatArray:
        return finite_vector(np.ravel(action), self.action_dim, "action", f"one per actuator of {self.task}")

    def reset(self, state: ArrayLike) -> FloatArray:
        x = self.check_state(state)
        with self.physics.reset_context():
            self.physics.data.qpos[:] = x[: self.bodies]
            self.physics.data.qvel[:] = x[self.bodies :]
        return x

    def state(self) -> FloatArray:
        return np.concatenate([self.physics.data.qpos, self.physics.data.qvel]).astype(np.float64)

    def step(self, action: ArrayLike) -> float:
        """Apply u for one control step; return the task's reward for that step."""
        u = self.check_action(action)
        self.physics.set_control(u)
        self.physics.step()
        return float(self._task.get_reward(self.physics))


class LQRExpert:
    """The TrajectoryOptimizer of Algorithm 1: closed-form optimal control of the same plant."""

    def __init__(self, task: str, seed: int, horizon: int = DEFAULT_HORIZON, gamma: float = 1.0) -> None:
        if not 0 < gamma <= 1:
            raise ValueError(f"gamma must lie in (0, 1], got {gamma!r}")
        self.horizon = check_horizon(horizon)
        self.gamma = float(gamma)
        self.plant = LQRPlant(task, seed)  # its own instance: rollouts never disturb the caller's plant
        self.task, self.seed = task, int(seed)
        a, b = self.plant.linearization()
        self.A, self.B = a, b
        qc, r = self.plant.state_cost, self.plant.control_cost
        qx = a.T @ qc @ a
        ru = r + b.T @ qc @ b
        cross = a.T @ qc @ b
        scale = math.sqrt(self.gamma)
        p = solve_discrete_are(scale * a, scale * b, qx, ru, s=cross)
        self.P = 0.5 * (p + p.T)
        self.K = np.linalg.solve(ru + self.gamma * b.T @ self.P @ b, self.gamma * b.T @ self.P @ a + cross.T)
        self.offset = float(self.horizon) if self.gamma == 1.0 else 1.0 / (1.0 - self.gamma)

    @property
    def closed_loop(self) -> FloatArray:
        return self.A - self.B @ self.K

    def action(self, state: ArrayLike) -> FloatArray:
        return -self.K @ np.asarray(state, dtype=np.float64)

    def value(self, states: ArrayLike) -> float | FloatArray:
        """V*(x) = offset - 0.5 x'Px, single state or batch."""
        x = np.asarray(states, dtype=np.float64)
        quad = np.einsum("...i,ij,...j->...", x, self.P, x)
        out = self.offset - 0.5 * quad
        return float(out) if np.ndim(out) == 0 else out

    def slope(self, states: ArrayLike) -> float | FloatArray:
        """|grad V*(x)| = |P x|."""
        x = np.asarray(states, dtype=np.float64)
        out = np.linalg.norm(x @ self.P, axis=-1)
        return float(out) if np.ndim(out) == 0 else out

    def trajectory(self, initial_state: ArrayLike, horizon: int | None = None) -> Trajectory:
        """Optimal trajectory from ``initial_state``, rolled out in MuJoCo, with Q_t = V*(s_t).

        ``expert_return`` is the rollout's measured return: the expert's own H-step value at s0.
        """
        x0 = self.plant.check_state(initial_state, "requested state")
        steps = self.horizon if horizon is None or horizon == 0 else check_horizon(horizon)
        run = rollout(self.plant, self.action, x0, steps)
        values = np.asarray(self.value(run.states), dtype=np.float64)
        gains = np.broadcast_to(-self.K, (len(values), *self.K.shape)).copy()  # u = -K x: its own feedback law
        return Trajectory(run.states, run.actions, values, expert_return=run.total_return, gains=gains)

    def finite_horizon_cost(self, steps: int) -> FloatArray:
        """P_H with J_H(x) = 0.5 x'P_H x the optimal cost of ``steps`` steps (no terminal cost).

        The Riccati recursion of the same stage cost as the DARE; P_H increases to P as H grows, so
        the optimal H-step return H - J_H(x) exceeds the stationary value H - J*(x) by
        0.5 x'(P - P_H)x >= 0.
        """
        a, b = self.A, self.B
        qc, r = self.plant.state_cost, self.plant.control_cost
        qx, ru, cross = a.T @ qc @ a, r + b.T @ qc @ b, a.T @ qc @ b
        p = np.zeros_like(self.P)
        for _ in range(int(steps)):
            gain = np.linalg.solve(ru + b.T @ p @ b, b.T @ p @ a + cross.T)
            p = qx + a.T @ p @ a - (a.T @ p @ b + cross) @ gain
            p = 0.5 * (p + p.T)
        return p

    def _slack(self, x: FloatArray) -> float:
        return ROUNDING_SLACK * (self.offset + 0.5 * abs(float(x @ self.P @ x)))

    def value_basis(self) -> ValueBasis:
        """What the certificate's value is, and the bound tail(s0) >= V_H(s0) - V(s0) for it."""
        if self.gamma != 1.0:
            return ValueBasis(value=f"the discounted value (gamma = {self.gamma:g})", tail=None,
                              tail_detail="no bound on the H-step return for gamma < 1")  # fmt: skip
        gap = self.P - self.finite_horizon_cost(self.horizon)

        def tail(s0: FloatArray) -> float:
            x = np.asarray(s0, dtype=np.float64)
            return max(0.0, 0.5 * float(x @ gap @ x)) + self._slack(x)

        return ValueBasis(
            value=f"the optimal H-step return V*_H (H = {self.horizon}, the best any controller achieves)",
            tail=tail,
            tail_detail=(
                "tail(s0) = 0.5 s0'(P - P_H)s0, P_H from the H-step Riccati recursion: the exact excess of the "
                "optimal H-step return over the stationary value H - J*(s0) that the data store"
            ),
        )

    def theorem_34_condition(self, lipschitz: float) -> tuple[bool, str]:
        """Theorem 3.4's condition for this plant: L_f = |A|, L_r = |A' Qc| sup |x'| over the expert's states."""
        phi, x, radius = self.closed_loop, np.eye(self.plant.state_dim)[:, : self.plant.bodies], 0.0
        for _ in range(self.horizon):
            radius = max(radius, INITIAL_RADIUS * float(np.linalg.norm(x, 2)))
            x = phi @ x
        reward_slope = float(np.linalg.norm(self.A.T @ self.plant.state_cost, 2)) * radius
        where = "L_r on the expert's states from S0"
        return theorem_34_condition(lipschitz, self.gamma, float(np.linalg.norm(self.A, 2)), reward_slope, where)

    def analytic_lipschitz(self) -> LipschitzConstant:
        """sup |P x| over every state the expert visits from S0 within the horizon.

        For quadratic V*, |V*(s) - V*(s')| <= |s - s'| max(|Ps|, |Ps'|), so this bounds the slope
        between any two states of that region. x_t = Phi^t E_q q0 with |q0| = sqrt(2), so the sup at
        step t is sqrt(2) times the largest singular value of P Phi^t E_q.
        """
        phi = self.closed_loop
        x = np.eye(self.plant.state_dim)[:, : self.plant.bodies]  # Phi^t E_q, t = 0
        best, best_t = 0.0, 0
        for t in range(self.horizon):
            sigma = float(np.linalg.norm(self.P @ x, 2))
            if sigma > best:
                best, best_t = sigma, t
            x = phi @ x
        value = INITIAL_RADIUS * best * (1 + ANALYTIC_MARGIN)
        detail = (
            f"sup |P x| over the expert's trajectories from S0 within H = {self.horizon} "
            f"(largest at step {best_t}), x (1 + {ANALYTIC_MARGIN:g}) for rounding, {self.task} seed {self.seed}"
        )
        return LipschitzConstant(value, "lqr-analytic", detail, margin=ANALYTIC_MARGIN)


class DetunedLQRExpert(LQRExpert):
    """A deliberately suboptimal expert (Appendix B): LQR designed with the control cost scaled.

    The gain K~ solves the DARE with R replaced by ``control_weight * R``; its values are exact
    for the plant's true cost: P~ solves the Lyapunov equation of the closed loop A - B K~ with
    stage cost (A - B K~)' Qc (A - B K~) + K~' R K~. So the data are (s, pi~(s), V^pi~(s)), as
    Theorem B.1 assumes. ``control_weight`` < 1 makes the controller over-aggressive, which keeps
    its closed loop fast enough that its infinite-horizon values match H-step returns.
    """

    def __init__(
        self,
        task: str,
        seed: int,
        control_weight: float = 0.1,
        horizon: int = DEFAULT_HORIZON,
        gamma: float = 1.0,
    ) -> None:
        if not (math.isfinite(control_weight) and control_weight > 0):
            raise ValueError(f"control_weight must be finite and > 0, got {control_weight!r}")
        super().__init__(task, seed, horizon=horizon, gamma=gamma)
        self.control_weight = float(control_weight)
        a, b = self.A, self.B
        qc, r = self.plant.state_cost, self.plant.control_cost
        ru = self.control_weight * r + b.T @ qc @ b
        cross = a.T @ qc @ b
        scale = math.sqrt(self.gamma)
        p_design = solve_discrete_are(scale * a, scale * b, a.T @ qc @ a, ru, s=cross)
        self.K = np.linalg.solve(ru + self.gamma * b.T @ p_design @ b, self.gamma * b.T @ p_design @ a + cross.T)
        phi = a - b @ self.K
        stage = phi.T @ qc @ phi + self.K.T @ r @ self.K
        p = solve_discrete_lyapunov(scale * phi.T, stage)
        self.P = 0.5 * (p + p.T)

    def analytic_lipschitz(self) -> LipschitzConstant:
        base = super().analytic_lipschitz()
        detail = f"{base.detail}; detuned expert (control cost x {self.control_weight:g}), its own P"
        return LipschitzConstant(base.value, base.source, detail, margin=base.margin)

    def value_basis(self) -> ValueBasis:
        """The claim is relative to this expert: V^E_H(s0) = H - J~(s0) + J~(x_H), x_H = Phi~^H s0."""
        if self.gamma != 1.0:
            return super().value_basis()
        reach = np.linalg.matrix_power(self.closed_loop, self.horizon)
        end = reach.T @ self.P @ reach

        def tail(s0: FloatArray) -> float:
            x = np.asarray(s0, dtype=np.float64)
            return 0.5 * float(x @ end @ x) + self._slack(x)

        return ValueBasis(
            value=(
                f"the detuned expert's own H-step return V^E_H (H = {self.horizon}); the claim is relative to "
                "this suboptimal expert, not to the optimum"
            ),
            tail=tail,
            tail_detail="tail(s0) = J~(x_H) = 0.5 x_H' P~ x_H, x_H = Phi~^H s0: the expert's cost left after H steps",
        )


# ----------------------------------------------------------------------------- the registry's entries
@dataclass(frozen=True)
class LQRTask(Task):
    """An lqr task: closed-form optimal expert (or the detuned one), analytic L, V* known at any s0."""

    default_certify: CheckedQuantity = "rollout"
    experts: tuple[str, ...] = ("optimal", "detuned")
    optimal_expert: bool = True

    def make_plant(self, seed: int) -> LQRPlant:
        return LQRPlant(self.name, seed)

    def make_expert(self, seed: int, horizon: int, options: ExpertOptions = DEFAULT_OPTIONS) -> LQRExpert:
        kind = self.expert_kind(options)
        optimizer_options = ("time_budget", "max_iterations", "stop", "values")
        given = [name for name in optimizer_options if getattr(options, name) is not None]
        if given:
            raise ValueError(f"the {self.name} expert is closed form: {', '.join(given)} do not apply to it")
        if kind == "detuned":
            return DetunedLQRExpert(self.name, seed, options.control_weight, horizon=horizon, gamma=options.gamma)
        return LQRExpert(self.name, seed, horizon=horizon, gamma=options.gamma)

    def sample_initial_state(self, rng: np.random.Generator) -> FloatArray:
        return sample_initial_state(self.name, rng)

    def analytic_lipschitz(self, expert: Expert) -> LipschitzConstant:
        assert isinstance(expert, LQRExpert)
        return expert.analytic_lipschitz()

    def expert_value(self, expert: Expert) -> Callable[[FloatArray], float]:
        assert isinstance(expert, LQRExpert)
        return expert.value  # type: ignore[return-value]  # a float for one state

    def value_slope(self, expert: Expert) -> Callable[[ArrayLike], FloatArray]:
        assert isinstance(expert, LQRExpert)
        return expert.slope  # type: ignore[return-value]  # an array for rows

    def optimal_returns(self, expert: Expert, plant: Plant, states: FloatArray, horizon: int) -> FloatArray:
        """The exact optimal H-step return H - 0.5 s0'P_H s0 (the plant's P_H, whatever the expert's kind)."""
        optimal = expert if type(expert) is LQRExpert else LQRExpert(self.name, expert.seed, horizon=horizon)
        assert isinstance(optimal, LQRExpert)
        p_h = optimal.finite_horizon_cost(horizon)
        return horizon - 0.5 * np.einsum("bi,ij,bj->b", states, p_h, states)

    def expert_returns(
        self,
        expert: Expert,
        plant: Plant,
        states: FloatArray,
        horizon: int,
        progress: Callable[[int, int], None] | None = None,
        robots: Sequence[Robot] | None = None,
    ) -> FloatArray:
        """The expert's controller rolled out in MuJoCo from each s0, in lockstep (one batch: no progress). Its
        gains are the nominal model's: it cannot plan on a drawn robot (a run refuses uncertainty for it)."""
        assert isinstance(expert, LQRExpert)
        if robots is not None:
            raise ValueError(f"the {self.name} expert cannot plan on a drawn robot")
        runs = rollout_batch(plant, lambda xs: np.array([expert.action(x) for x in xs]), states, horizon)
        return np.array([run.total_return for run in runs])


def _lqr_task(name: str) -> LQRTask:
    bodies, actuators = TASKS[name]
    band = SUCCESS_BAND[name]
    return LQRTask(
        name=name,
        state_dim=2 * bodies,
        action_dim=actuators,
        stored_state=f"qpos then qvel of {bodies} joints",
        initial_state_diameter=initial_state_diameter(),
        paper_lipschitz=PAPER_LIPSCHITZ[name],
        paper_epsilon=PAPER_EPSILON[name],
        reward_range=(-math.inf, 1.0),  # 1 - 0.5|q|^2 - 0.05|u|^2
        success=SuccessCriterion(
            f"every joint position within {band:g} of 0",
            WithinBand(tuple(range(bodies)), -band, band),
            share=SUCCESS_SHARE,
        ),
    )


LQR_2_1 = _lqr_task("lqr_2_1")
LQR_6_2 = _lqr_task("lqr_6_2")
