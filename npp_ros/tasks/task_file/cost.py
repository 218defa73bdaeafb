"""The iLQR expert's smooth cost for a task file: each tolerance term as a quadratic penalty outside its bounds.

The reward's tolerance terms (npp_ros.tasks.task_file.terms) are flat far from their bounds (a Gaussian
tolerance is), which gives a gradient-based optimiser nothing to follow; the expert minimises instead
0.5 w ((q - clip(q, bounds)) / margin)^2 per term, zero exactly where the term's tolerance is 1. The values
it stores are the true rewards replayed on the plant, as for every iLQR expert.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from npp_ros.policy.dataset import FloatArray
from npp_ros.tasks.task_file.terms import Term, mechanical_energy

DEFAULT_CONTROL_WEIGHT = 1e-3  # 0.5 w |u|^2 on every control, the file's expert.control_weight
DEFAULT_VELOCITY_WEIGHT = 1e-4  # 0.5 w |qvel|^2 on every state, the file's expert.velocity_weight
ENERGY_STEP = 1e-6  # rad or m: the central difference of the energy in qpos


class TermCost:
    """The iLQR expert's smooth cost from tolerance terms: 0.5 w ((q - clip(q, bounds)) / scale)^2 each.

    scale is the term's margin (1 without one). Zero exactly where the term's tolerance is 1, and
    its gradient points there from anywhere (a Gaussian tolerance is flat far from its bounds).
    State terms are differentiated through MuJoCo's kinematics (site Jacobians); an energy term's
    gradient is M qvel in qvel and a central difference in qpos. The Hessian is Gauss-Newton. Small
    velocity and control weights keep the problem well posed.

    A distance term with ``hessian = "offset"``, beyond its upper bound b, is taken as the offset vector's
    residual, r = (1 - b/d) delta / scale (|r| is the scalar residual, and the gradient is the same), so its
    Gauss-Newton Hessian also holds the curvature across the offset: (1 - b/d)^2 J' (I - n n') J / scale^2 beside
    the scalar's J' n n' J / scale^2.
    Without it the Hessian of a reach is rank one per step, and iLQR steps sideways without limit: on the
    7-joint arm of examples/panda_reach 4 requests of 5 ran out of their 30 iterations, where with it all 5
    converged (results/panda-reach/expert). The default stays the scalar's (the acrobot's swing-up was tuned on it).
    """

    def __init__(self, terms: tuple[Term, ...], model: Any, options: dict[str, Any]) -> None:
        import mujoco

        self._mujoco = mujoco
        self.model = model
        self.data = mujoco.MjData(model)
        self.nq, self.nu = int(model.nq), int(model.nu)
        self.state_terms_list = [t for t in terms if not t.on_control]
        self.control_terms_list = [t for t in terms if t.on_control]
        self.velocity_weight = float(options.get("velocity_weight", DEFAULT_VELOCITY_WEIGHT))
        self.control_weight = float(options.get("control_weight", DEFAULT_CONTROL_WEIGHT))
        self._jac = np.zeros((3, model.nv))
        self._jac2 = np.zeros((3, model.nv))
        self._across = np.zeros(
            (self.nq, self.nq)
        )  # a distance term's curvature across its offset (_value_and_gradient)
        self._energy_data = mujoco.MjData(model)  # apart: the differences must not move the terms' kinematics

    @staticmethod
    def _residual(term: Term, q: float) -> float:
        scale = term.margin if term.margin > 0 else 1.0
        low, high = term.bounds
        q -= term.offset  # an energy term's bounds are about its pose's energy
        return (q - min(max(q, low), high)) / scale

    def _site_jacobian(self, site: int, out: FloatArray) -> None:
        self._mujoco.mj_jacSite(self.model, self.data, out, None, site)

    def _value_and_gradient(self, term: Term, x: FloatArray) -> tuple[float, FloatArray]:
        """The term's quantity at x (kinematics already at x) and its gradient in x = [qpos, qvel].

        For a distance with ``hessian = "offset"``, ``self._across`` is left as J' (I - n n') J in qpos (the curvature
        across the offset); 0 otherwise."""
        n = 2 * self.nq
        grad = np.zeros(n)
        model, data = self.model, self.data
        if term.quantity == "joint_position":
            index = int(model.jnt_qposadr[term.target[0]])
            grad[index] = 1.0
            return float(x[index]), grad
        if term.quantity == "joint_velocity":
            index = self.nq + int(model.jnt_dofadr[term.target[0]])
            grad[index] = 1.0
            return float(x[index]), grad
        if term.quantity == "site_position":
            self._site_jacobian(term.target[0], self._jac)
            grad[: self.nq] = self._jac[term.axis]
            return float(data.site_xpos[term.target[0], term.axis]), grad
        if term.quantity == "energy":
            return self._energy_and_gradient(x)
        a, b = term.target
        delta = data.site_xpos[a] - data.site_xpos[b]
        distance = float(np.linalg.norm(delta))
        self._across.fill(0.0)
        if distance > 1e-12:
            self._site_jacobian(a, self._jac)
            self._site_jacobian(b, self._jac2)
            jac = (self._jac - self._jac2)[:, : self.nq]
            unit = delta / distance
            grad[: self.nq] = unit @ jac
            if term.hessian == "offset":  # only a term that asks for it pays for the curvature across
                sideways = jac - np.outer(unit, unit @ jac)
                self._across = sideways.T @ sideways
        return distance, grad

    def _energy(self, x: FloatArray) -> float:
        return mechanical_energy(self.model, x[: self.nq], x[self.nq :], self._energy_data)

    def _energy_and_gradient(self, x: FloatArray) -> tuple[float, FloatArray]:
        """The mechanical energy at x and its gradient: M qvel in qvel, a central difference in qpos."""
        grad = np.zeros(2 * self.nq)
        for i in range(self.nq):
            up, down = x.copy(), x.copy()
            up[i] += ENERGY_STEP
            down[i] -= ENERGY_STEP
            grad[i] = (self._energy(up) - self._energy(down)) / (2 * ENERGY_STEP)
        energy = self._energy(x)
        self._mujoco.mj_mulM(self.model, self._energy_data, grad[self.nq :], x[self.nq :])
        return energy, grad

    def state_terms(self, states: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        count, n = len(states), 2 * self.nq
        value = 0.5 * self.velocity_weight * np.sum(states[:, self.nq :] ** 2, axis=1)
        grad = np.zeros((count, n))
        grad[:, self.nq :] = self.velocity_weight * states[:, self.nq :]
        hess = np.zeros((count, n, n))
        hess[:, np.arange(self.nq, n), np.arange(self.nq, n)] = self.velocity_weight
        if not self.state_terms_list:
            return value, grad, hess
        mj, model, data = self._mujoco, self.model, self.data
        for k in range(count):
            data.qpos[:] = states[k, : self.nq]
            data.qvel[:] = states[k, self.nq :]
            mj.mj_kinematics(model, data)
            mj.mj_comPos(model, data)
            for term in self.state_terms_list:
                q, dq = self._value_and_gradient(term, states[k])
                scale = term.margin if term.margin > 0 else 1.0
                e = self._residual(term, q)
                value[k] += 0.5 * term.weight * e * e
                if e != 0.0:
                    grad[k] += term.weight * e / scale * dq
                    hess[k] += term.weight / (scale * scale) * np.outer(dq, dq)
                    if term.hessian == "offset" and e > 0.0:
                        shrink = 1.0 - term.bounds[1] / q
                        hess[k, : self.nq, : self.nq] += term.weight / (scale * scale) * shrink * shrink * self._across
        return value, grad, hess

    def state_values(self, states: FloatArray) -> FloatArray:
        """state_terms' values alone, the same numbers: the line search needs no Jacobians, nor the
        centre-of-mass pass they need (site positions come from the kinematics alone)."""
        value = 0.5 * self.velocity_weight * np.sum(states[:, self.nq :] ** 2, axis=1)
        if not self.state_terms_list:
            return value
        mj, model, data = self._mujoco, self.model, self.data
        for k in range(len(states)):
            data.qpos[:] = states[k, : self.nq]
            mj.mj_kinematics(model, data)
            for term in self.state_terms_list:
                e = self._residual(term, self._quantity(term, states[k]))
                value[k] += 0.5 * term.weight * e * e
        return value

    def _quantity(self, term: Term, x: FloatArray) -> float:
        """The term's quantity at x (kinematics already at x), as _value_and_gradient computes it."""
        model, site_xpos = self.model, self.data.site_xpos
        if term.quantity == "joint_position":
            return float(x[int(model.jnt_qposadr[term.target[0]])])
        if term.quantity == "joint_velocity":
            return float(x[self.nq + int(model.jnt_dofadr[term.target[0]])])
        if term.quantity == "site_position":
            return float(site_xpos[term.target[0], term.axis])
        if term.quantity == "energy":
            return self._energy(x)
        a, b = term.target
        return float(np.linalg.norm(site_xpos[a] - site_xpos[b]))

    def control_terms(self, actions: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        count, m = actions.shape
        value = 0.5 * self.control_weight * np.sum(actions * actions, axis=1)
        grad = self.control_weight * actions.copy()
        hess = np.broadcast_to(self.control_weight * np.eye(m), (count, m, m)).copy()
        for term in self.control_terms_list:
            weight = term.weight / len(term.target)  # a mean over several actuators: each its share
            for j in term.target:
                scale = term.margin if term.margin > 0 else 1.0
                low, high = term.bounds
                e = (actions[:, j] - np.clip(actions[:, j], low, high)) / scale
                value += 0.5 * weight * e * e
                grad[:, j] += weight * e / scale
                hess[:, j, j] += np.where(e != 0.0, weight / (scale * scale), 0.0)
        return value, grad, hess
