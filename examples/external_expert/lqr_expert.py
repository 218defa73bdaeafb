#!/usr/bin/env python3
"""An expert for the lqr tasks served from its own process, on rclpy, npp_interfaces and the expert_api helper only.

Its own solver: the plant (dm_control's lqr task for the sim's task and seed) linearised once at
the origin with MuJoCo's centred differences, and scipy's discrete Riccati solver for the optimal
stationary gain. dm_control scores a step on the state after it, r = 1 - 0.5|q'|^2 - 0.5 c|u|^2,
so the stage cost of (x, u) is 0.5 (Ax + Bu)'Qc(Ax + Bu) + 0.5 u'Ru, a Riccati equation with a
cross term. Values follow npp_ros's convention: Q_t = H - 0.5 x_t'P x_t, the undiscounted H-step
value of x_t (H the run's horizon); expert_return is the trajectory's own return.

Run it in place of npp-expert (README, "Experts from any process"):

    NPP_RUN_KEY=... python examples/external_expert/lqr_expert.py
"""

from __future__ import annotations

import math
import os
import sys

import numpy as np
import rclpy
from npp_interfaces.msg import PlantDescription
from npp_interfaces.srv import ExpertTrajectory
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from scipy.linalg import solve_discrete_are

from npp_ros_graph.transport.expert_api import (
    EXPERT_SERVICE,
    NOT_READY,
    PLANT_QOS,
    PLANT_TOPIC,
    SERVICE_QOS,
    AnswerSeal,
    SealError,
    answer_seal,
    robot_refusal,
)

LQR_TASKS = ("lqr_2_1", "lqr_6_2")
MAX_HORIZON = 100_000


class RiccatiSolver:
    """Optimal control of one dm_control lqr plant, from its own linearisation and the DARE."""

    def __init__(self, task: str, seed: int, horizon: int) -> None:
        os.environ.setdefault("MUJOCO_GL", "disable")
        import mujoco
        from dm_control import suite

        env = suite.load("lqr", task, task_kwargs={"random": int(seed)})
        self.physics, self.task = env.physics, env.task
        model = self.physics.model.ptr
        self.nq, self.nu, self.horizon = int(model.nq), int(model.nu), int(horizon)
        n = 2 * self.nq
        with self.physics.reset_context():
            self.physics.data.qpos[:] = 0.0
            self.physics.data.qvel[:] = 0.0
        a, b = np.zeros((n, n)), np.zeros((n, self.nu))
        mujoco.mjd_transitionFD(model, self.physics.data.ptr, 1e-6, True, a, b, None, None)
        state_cost = np.diag(np.concatenate([np.ones(self.nq), np.zeros(self.nq)]))
        control_cost = self.task.control_cost_coef * np.eye(self.nu)
        cross = a.T @ state_cost @ b
        weight_u = control_cost + b.T @ state_cost @ b
        p = solve_discrete_are(a, b, a.T @ state_cost @ a, weight_u, s=cross)
        self.p = 0.5 * (p + p.T)
        self.gain = np.linalg.solve(weight_u + b.T @ self.p @ b, b.T @ self.p @ a + cross.T)

    def trajectory(self, x0: np.ndarray, steps: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """States, actions, values and the return of the optimal controller from x0, stepped in MuJoCo."""
        states, actions, rewards = np.empty((steps, 2 * self.nq)), np.empty((steps, self.nu)), np.empty(steps)
        with self.physics.reset_context():
            self.physics.data.qpos[:] = x0[: self.nq]
            self.physics.data.qvel[:] = x0[self.nq :]
        for t in range(steps):
            x = np.concatenate([self.physics.data.qpos, self.physics.data.qvel])
            u = -self.gain @ x
            states[t], actions[t] = x, u
            self.physics.set_control(u)
            self.physics.step()
            rewards[t] = self.task.get_reward(self.physics)
        values = self.horizon - 0.5 * np.einsum("ti,ij,tj->t", states, self.p, states)
        return states, actions, values, float(rewards.sum())


class ExternalLQRExpert(Node):
    """Serves the run's expert service for an lqr plant; refuses other tasks and bad requests with the reason."""

    def __init__(self) -> None:
        super().__init__("external_lqr_expert")
        self.description: PlantDescription | None = None
        self.solver: RiccatiSolver | None = None
        self.seal: AnswerSeal | None = None
        self.refusal = f"{NOT_READY} no plant description from the sim yet"
        self.create_subscription(PlantDescription, PLANT_TOPIC, self.on_plant, PLANT_QOS)
        self.create_service(ExpertTrajectory, EXPERT_SERVICE, self.on_request, qos_profile=SERVICE_QOS)

    def on_plant(self, description: PlantDescription) -> None:
        try:
            seal = answer_seal(description)
        except SealError as exc:
            self.get_logger().error(f"ignored: {exc}", throttle_duration_sec=5.0)
            return
        if self.description is not None:
            return  # keeps the first plant; restart to model another
        self.description, self.seal = description, seal
        if description.task not in LQR_TASKS:
            self.refusal = f"this expert serves {', '.join(LQR_TASKS)}, not {description.task}"
            self.get_logger().error(self.refusal)
            return
        self.solver = RiccatiSolver(description.task, description.seed, description.horizon)
        self.refusal = ""
        self.get_logger().info(f"modelling {description.task} seed {description.seed}, horizon {description.horizon}")

    def on_request(self, request: ExpertTrajectory.Request, response: ExpertTrajectory.Response):
        problem = self.refusal or self.problem(request)
        if problem:
            response.success, response.message = False, problem
        else:
            assert self.solver is not None and self.description is not None
            steps = int(request.horizon) or int(self.description.horizon)
            states, actions, values, ret = self.solver.trajectory(np.asarray(request.state, dtype=np.float64), steps)
            response.success, response.message = True, f"{steps} steps of {self.description.task}"
            self.fill(response, states, actions, values, ret)
        return response if self.seal is None else self.seal.seal(response, request)

    def problem(self, request: ExpertTrajectory.Request) -> str:
        assert self.description is not None
        if request.robot:  # its Riccati solution is the nominal plant's: it cannot plan on a drawn robot
            return robot_refusal(self.description.task)
        n = int(self.description.state_dim)
        state = list(request.state)
        if len(state) != n or not all(math.isfinite(x) for x in state):
            return f"state must be {n} finite numbers (qpos then qvel), got {state}"
        if int(request.horizon) > MAX_HORIZON:
            return f"horizon {request.horizon} exceeds {MAX_HORIZON}"
        return ""

    @staticmethod
    def fill(
        response: ExpertTrajectory.Response, states: np.ndarray, actions: np.ndarray, values: np.ndarray, ret: float
    ) -> None:
        """The answer's arrays, row-major, and its return."""
        response.state_dim, response.action_dim = states.shape[1], actions.shape[1]
        response.states = states.ravel().tolist()
        response.actions = actions.ravel().tolist()
        response.values = values.tolist()
        response.expert_return = ret


def main(node_class: type[ExternalLQRExpert] = ExternalLQRExpert) -> int:
    if any(a in ("-h", "--help") for a in sys.argv[1:]):
        print(__doc__)
        return 0
    rclpy.init()
    node = node_class()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
