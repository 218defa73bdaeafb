"""dm_control's acrobot swing-up as a task registered through the plug-in path, with an iLQR expert.

Task (``suite.load("acrobot", "swingup")``): two links hanging from a shoulder hinge, one motor at
the elbow (gear 2, u in [-1, 1]): underactuated. One control step is one RK4 MuJoCo step of 0.01 s;
H = 1000 is dm_control's 10 s episode. The reward is dm_control's smooth one: tolerance(distance from
the tip to the target above the shoulder, within 0.2, Gaussian margin 1). s0 ~ rho as dm_control:
both angles uniform in [-pi, pi), at rest. Stored state: [shoulder, elbow] wrapped to (-pi, pi],
then their rates.

It is registered as an entry point of npp_ros's own package (pyproject.toml, group npp_ros.tasks),
the path any plug-in takes. Its expert is npp_ros's iLQR on a smooth surrogate of the reward, the
task-file cost (:class:`~npp_ros.tasks.task_file.TermCost`) on the tip-target distance, warm-started at
u = 0: a local optimiser, so claims are relative to its own returns (oracle mode).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from npp_ros.policy.dataset import FloatArray
from npp_ros.tasks.registry import OptimizerTask
from npp_ros.tasks.suite_plant import SuitePlant, wrap_angle
from npp_ros.trajopt.ilqr import OptimizingExpert

TASK = "acrobot_swingup"
DEFAULT_HORIZON = 1000
DEFAULT_TIME_BUDGET = 10.0
TARGET_RADIUS = 0.2


def represent(raw: ArrayLike) -> FloatArray:
    """Raw [qpos, qvel] -> stored [wrapped shoulder, wrapped elbow, rates]."""
    x = np.array(raw, dtype=np.float64, copy=True)
    x[..., :2] = wrap_angle(x[..., :2])
    return x


def sample_initial_state(rng: np.random.Generator) -> FloatArray:
    """s0 ~ rho as dm_control's swing-up: both angles uniform in [-pi, pi), at rest."""
    return np.concatenate([rng.uniform(-np.pi, np.pi, 2), np.zeros(2)])


class AcrobotPlant(SuitePlant):
    """The swing-up task driven step by step, with an explicit horizon and no termination."""

    task = TASK
    suite = ("acrobot", "swingup")
    state_entries = "shoulder angle, elbow angle, shoulder rate, elbow rate"
    fingerprint_fields = (
        "opt.timestep", "opt.gravity", "opt.integrator", "dof_damping", "body_mass", "body_inertia", "body_ipos",
        "body_pos", "actuator_gear", "actuator_ctrlrange", "site_pos", "site_size",
    )  # fmt: skip
    represent = staticmethod(represent)


def tip_cost_terms(plant: AcrobotPlant) -> tuple:
    """The surrogate's one term: the tip-target distance beyond the target's radius, scaled by the margin 1."""
    from npp_ros.tasks.task_file import Term

    model = plant.physics.model
    tip, target = model.name2id("tip", "site"), model.name2id("target", "site")
    return (Term("site_distance", (tip, target), 0, (0.0, TARGET_RADIUS), 1.0, "gaussian", 0.1, 1.0, "tip-target"),)


class AcrobotExpert(OptimizingExpert):
    """iLQR on the tip-target surrogate, warm-started at u = 0."""

    def __init__(
        self,
        seed: int = 0,
        horizon: int = DEFAULT_HORIZON,
        time_budget: float = DEFAULT_TIME_BUDGET,
        max_iterations: int = 60,
        values: str = "window",
    ) -> None:
        from npp_ros.tasks.task_file import TermCost

        plant = AcrobotPlant(seed)
        zero = np.zeros(plant.action_dim)
        weights = {"velocity_weight": 1e-3, "control_weight": 1e-2}
        cost = TermCost(tip_cost_terms(plant), plant.physics.model.ptr, weights)
        super().__init__(
            plant, cost, lambda _x: zero, represent,
            horizon=horizon, time_budget=time_budget, max_iterations=max_iterations, values=values,
        )  # fmt: skip
        self.seed = int(seed)
        self.task = TASK
        self.reward_lipschitz_detail = "not computed for the smooth swing-up reward"


SWINGUP = OptimizerTask(
    name=TASK,
    state_dim=4,
    action_dim=1,
    stored_state="shoulder and elbow angles wrapped to (-pi, pi], their rates",
    initial_state_diameter=2 * math.pi * math.sqrt(2),
    no_analytic_lipschitz="its iLQR expert computes no bound on its value's slope",
    plant_factory=AcrobotPlant,
    expert_factory=AcrobotExpert,
    sampler=sample_initial_state,
    default_time_budget=DEFAULT_TIME_BUDGET,
    reward_range=(0.0, 1.0),
)
