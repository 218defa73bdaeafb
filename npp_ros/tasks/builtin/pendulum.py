"""dm_control pendulum swing-up as a plant, and its expert: iLQR from an energy-shaping warm start.

Task (``suite.load("pendulum", "swingup")``): one hinge, angle 0 = upright, gravity 9.81, torque
limited to [-1, 1] (a fifth of the gravity torque at 90 degrees, so the pole must be pumped up
over several swings). One control step is one MuJoCo step of 0.02 s (``control_timestep`` =
``timestep``, ``n_sub_steps`` = 1); H = 1000 steps is dm_control's 20 s episode. The reward is
dm_control's own, from the physics after the step: 1 when the pole's vertical axis is within
8 degrees of upright (``tolerance(pole_zz, (cos 8deg, 1))``, margin 0), else 0.

State representation (what the dataset stores and the policy compares): [angle wrapped to
(-pi, pi], angular velocity], see :func:`represent`. The true state space is a cylinder; the
Euclidean distance on wrapped coordinates is never below the cylinder's geodesic distance
(|a - b| >= |wrap(a - b)| for wrapped a, b), so a value L-Lipschitz on the cylinder is
L-Lipschitz for the stored Euclidean distance: the core's bounds stay valid, only looser for
pairs on either side of the seam at +-pi. It keeps dim(S) = 2, as in the paper's Appendix B.
The plant's ``state()`` returns this representation; ``raw_state()`` returns MuJoCo's
[qpos, qvel], whose angle is continuous (the optimizer works on it) and may leave (-pi, pi].

Action bounds: the optimizer is box-constrained DDP (controls clamped to ctrlrange in the
forward pass, the clamped directions removed from the feedback gains); ``step`` clamps as
MuJoCo does for a ctrllimited actuator, so any finite action is accepted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.linalg import solve_discrete_are

from npp_ros.policy.dataset import FloatArray
from npp_ros.policy.feedback import wrap_angle
from npp_ros.tasks.builtin.swingup import SwingUpExpert
from npp_ros.tasks.registry import OptimizerTask
from npp_ros.tasks.success import SuccessCriterion, UprightAngles, steps_for
from npp_ros.tasks.suite_plant import SuitePlant
from npp_ros.tasks.uncertainty import SWINGUP_UNCERTAINTY

TASK = "pendulum_swingup"
PAPER_LIPSCHITZ = 4300.0
"""The paper's L for this task (Appendix B, with a PPO expert). Not a bound: with 0/1 rewards every
H-step return is an integer, so a value is a staircase in s0 and no finite L bounds its slope
(``scripts/pendulum_expert_report.py`` bisects a step of the expert's Q_0)."""
PAPER_EPSILON = 130.0
UPRIGHT_DEGREES = 8.0
CONTROL_TIMESTEP = 0.02  # dm_control's pendulum: one MuJoCo step per control step (the plant checks it)
SUCCESS = SuccessCriterion(
    f"the pole within {UPRIGHT_DEGREES:g} degrees of upright",
    UprightAngles(((0,),), UPRIGHT_DEGREES),
    steps=steps_for(1.0, CONTROL_TIMESTEP),
    seconds=1.0,
)
"""Swung up and held: the band of dm_control's own reward (1 within 8 degrees), for the last second (50 steps)."""


def represent(raw: ArrayLike) -> FloatArray:
    """Raw [qpos, qvel] (one state or rows) -> stored [wrapped angle, velocity]."""
    x = np.array(raw, dtype=np.float64, copy=True)
    x[..., 0] = wrap_angle(x[..., 0])
    return x


def sample_initial_state(rng: np.random.Generator) -> FloatArray:
    """s0 ~ rho: angle uniform in [-pi, pi), zero velocity (dm_control's initialize_episode)."""
    return np.array([rng.uniform(-np.pi, np.pi), 0.0])


def initial_state_diameter() -> float:
    """diam(S0) in the stored metric: angles span [-pi, pi), velocity is zero."""
    return 2 * np.pi


class PendulumPlant(SuitePlant):
    """The swing-up task driven step by step, with an explicit horizon and no termination."""

    task = TASK
    suite = ("pendulum", "swingup")
    state_entries = "hinge angle, angular velocity"
    fingerprint_fields = (
        "opt.timestep", "opt.gravity", "dof_damping", "jnt_stiffness", "body_mass", "body_inertia",
        "body_ipos", "body_pos", "actuator_gear", "actuator_ctrlrange",
    )  # fmt: skip
    represent = staticmethod(represent)
    angles = (0,)  # the state entries represent() wraps


# ----------------------------------------------------------------------------- surrogate and warm start
@dataclass(frozen=True)
class SwingUpCost:
    """Smooth surrogate of "be within 8 degrees of upright": s = w (1 - cos q) + v_w qdot^2 / 2, c = u_w u^2 / 2.

    1 - cos q is smooth on the cylinder (no wrap needed) and has a single minimum upright; the
    small velocity and torque weights make holding the pole still the cheapest way to stay there.
    """

    angle_weight: float = 1.0
    velocity_weight: float = 0.01
    control_weight: float = 0.01

    def state_terms(self, states: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        q, v = states[:, 0], states[:, 1]
        c, s = np.cos(q), np.sin(q)
        value = self.angle_weight * (1.0 - c) + 0.5 * self.velocity_weight * v * v
        grad = np.stack([self.angle_weight * s, self.velocity_weight * v], axis=1)
        hess = np.zeros((len(states), 2, 2))
        # Gauss-Newton-style floor: cos q < 0 would make the Hessian indefinite far from upright.
        hess[:, 0, 0] = self.angle_weight * np.maximum(c, 0.0)
        hess[:, 1, 1] = self.velocity_weight
        return value, grad, hess

    def control_terms(self, actions: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        value = 0.5 * self.control_weight * np.sum(actions * actions, axis=1)
        grad = self.control_weight * actions
        m = actions.shape[1]
        hess = np.broadcast_to(self.control_weight * np.eye(m), (len(actions), m, m))
        return value, grad, hess


class EnergyShapingController:
    """Pump energy towards the upright rest energy, then catch with LQR near the top.

    E = I qdot^2 / 2 + mgl cos q (I, mgl read from the compiled model); below the target the
    torque follows the velocity's sign at full scale (bang-bang pumping, plus damping
    compensation), above it brakes. Within ``catch_degrees`` of upright an LQR designed on
    MuJoCo's own linearisation at the top takes over. A warm start, not an expert.
    """

    def __init__(self, plant: PendulumPlant, catch_degrees: float = 25.0, gain: float = 5.0) -> None:
        import mujoco

        m = plant.physics.model.ptr
        d = mujoco.MjData(m)
        energies = []
        for q in (0.0, np.pi):
            d.qpos[:] = q
            d.qvel[:] = 0.0
            mujoco.mj_forward(m, d)
            energies.append(float(d.energy[0]))
        mass = np.zeros((1, 1))
        mujoco.mj_fullM(m, d, mass)
        self.inertia = float(mass[0, 0])
        self.mgl = 0.5 * (energies[0] - energies[1])
        self.damping = float(m.dof_damping[0])
        self.umax = float(m.actuator_ctrlrange[0, 1])
        self.gain = float(gain)
        self.catch_cos = math.cos(math.radians(catch_degrees))
        d.qpos[:] = 0.0
        d.qvel[:] = 0.0
        d.ctrl[:] = 0.0
        a = np.zeros((2, 2))
        b = np.zeros((2, 1))
        mujoco.mjd_transitionFD(m, d, 1e-6, True, a, b, None, None)
        q, r = np.diag([1.0, 0.1]), np.array([[1.0]])
        p = solve_discrete_are(a, b, q, r)
        self.K = np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a)

    def energy(self, x: FloatArray) -> float:
        return 0.5 * self.inertia * x[1] * x[1] + self.mgl * math.cos(x[0])

    def __call__(self, x: FloatArray) -> FloatArray:
        angle = float(wrap_angle(x[0]))
        if math.cos(angle) > self.catch_cos:
            u = -float(self.K[0] @ np.array([angle, x[1]]))
        else:
            shortfall = self.mgl - self.energy(x)
            direction = 1.0 if x[1] >= 0.0 else -1.0
            u = self.gain * shortfall * direction + self.damping * x[1]
        return np.array([min(max(u, -self.umax), self.umax)])


# ----------------------------------------------------------------------------- the expert
class PendulumExpert(SwingUpExpert):
    """The TrajectoryOptimizer of Algorithm 1 for the swing-up: iLQR on the plant's own model.

    Each request: roll the energy-shaping controller out from s0 (warm start), refine with
    box-constrained iLQR on :class:`SwingUpCost` to convergence or ``max_iterations`` (``stop``; see
    :class:`OptimizingExpert`), then replay the actions on the plant for dm_control's true rewards
    (see :class:`OptimizingExpert` for the value modes).

    The cap of 50 iterations keeps a request as long as under the earlier 5 s budget:
    ``npp-bench --only experts --expert-tasks pendulum_swingup cartpole_swingup acrobot_swingup
    examples/two_link_arm/task.toml`` (10 requests at H = 1000, seed 0,
    load average 0.9-3.7) found every pendulum request ending by convergence or the cap, none by the
    budget, in 0.13-1.96 s (median 0.90 s).
    """

    plant_class = PendulumPlant
    max_iterations_cap = 50
    reward_lipschitz_note = "is infinite: the reward is 1 within 8 degrees of upright, else 0"

    def make_warm_start(self, plant: PendulumPlant) -> EnergyShapingController:
        return EnergyShapingController(plant)

    def default_cost(self, warm_start: EnergyShapingController) -> SwingUpCost:
        return SwingUpCost()

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.reward_lipschitz = math.inf
        self.no_lipschitz_bound = (
            "with the 0/1 reward every H-step return is a whole number, so the expert's value is a staircase "
            "in s0 and no finite L bounds its slope (scripts/pendulum_expert_report.py finds a step)"
        )


SWINGUP = OptimizerTask(
    name=TASK,
    state_dim=2,
    action_dim=1,
    stored_state="hinge angle wrapped to (-pi, pi], angular velocity",
    initial_state_diameter=initial_state_diameter(),
    paper_lipschitz=PAPER_LIPSCHITZ,
    paper_epsilon=PAPER_EPSILON,
    paper_lipschitz_note=(
        "the paper's choice (Appendix B); not a bound: 0/1 rewards make every H-step value a staircase in s0"
    ),
    no_analytic_lipschitz="its 0/1 reward makes every H-step value a staircase in s0, so no finite L bounds it",
    plant_factory=PendulumPlant,
    expert_factory=PendulumExpert,
    sampler=sample_initial_state,
    reward_range=(0.0, 1.0),  # dm_control's tolerance-based reward
    success=SUCCESS,
    uncertainty=SWINGUP_UNCERTAINTY,
)
"""Stored values are ``window`` (the H-step return of each stored state), not ``return-to-go``: an upright
state held to the end is stored with value H - t under return-to-go, one state with many values, which
no L fits and which give rollout mode no bound; window values are one number per visited state."""
