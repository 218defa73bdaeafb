"""A dm_control suite task as a plant: ``substeps`` MuJoCo steps per control step, an explicit horizon, no termination.

Every swing-up plant is the same machine around its suite task: reset to a given [qpos, qvel],
step with the control clamped to ctrlrange (as MuJoCo does for a ctrllimited actuator) and held for
``substeps`` MuJoCo steps (dm_control's n_sub_steps: one for the suite's swing-ups, k for a task
file whose control_timestep is k model timesteps), read dm_control's own reward from the physics
after the last of them, fingerprint the compiled model. A task
module says only which suite task it wraps, what its state's entries are, how a state is stored
(:meth:`SuitePlant.represent`) and which model arrays define its dynamics.
"""

from __future__ import annotations

import copy
import hashlib
import math
import operator
import os
from typing import ClassVar

import numpy as np
from numpy.typing import ArrayLike

from npp_ros.policy.dataset import FloatArray
from npp_ros.policy.vectors import finite_vector


def substeps_per_control_step(control_timestep: float, timestep: float) -> int | None:
    """k such that control_timestep = k x timestep (to rounding), k >= 1; None when no whole k fits."""
    k = round(control_timestep / timestep)
    return k if k >= 1 and math.isclose(k * timestep, control_timestep, rel_tol=1e-9) else None


class SuitePlant:
    """One dm_control suite task driven step by step; subclasses fill in the class attributes."""

    task: ClassVar[str]  # npp_ros's task name
    suite: ClassVar[tuple[str, str]]  # (domain, task) for dm_control's suite.load
    state_entries: ClassVar[str]  # what the state's entries are, in order (named in refusals)
    fingerprint_fields: ClassVar[tuple[str, ...]]  # model attributes (dotted) that define its dynamics
    angles: tuple[int, ...] = ()  # the state entries that represent() wraps to (-pi, pi]
    substeps: int = 1  # MuJoCo steps per control step, the control held (the optimizer's dynamics read it too)

    def __init__(self, seed: int = 0) -> None:
        os.environ.setdefault("MUJOCO_GL", "disable")
        from dm_control import suite

        domain, name = self.suite
        env = suite.load(domain, name, task_kwargs={"random": int(seed)})
        n_sub = round(env.control_timestep() / env.physics.model.opt.timestep)
        if n_sub != 1:
            raise RuntimeError(f"{domain} control step is {n_sub} physics steps; this plant assumes 1")
        self.seed = int(seed)
        self.physics = env.physics
        self._task = env.task
        model = self.physics.model
        self.dt = float(env.control_timestep())
        self.positions = int(model.nq)
        self.state_dim = int(model.nq + model.nv)
        self.action_dim = int(model.nu)
        self.joint_names = [model.id2name(i, "joint") for i in range(model.njnt)]
        self.actuated_joint_names = [model.id2name(int(model.actuator_trnid[i, 0]), "joint") for i in range(model.nu)]
        self.action_low = model.actuator_ctrlrange[:, 0].astype(np.float64)
        self.action_high = model.actuator_ctrlrange[:, 1].astype(np.float64)
        self.steps = 0

    @staticmethod
    def represent(raw: ArrayLike) -> FloatArray:
        """Raw [qpos, qvel] -> the stored state (the task wraps its angles here)."""
        raise NotImplementedError

    def model_sha256(self) -> str:
        """Fingerprint of the compiled model's dynamics, so an expert can prove it models this plant."""
        model = self.physics.model
        parts = [operator.attrgetter(name)(model) for name in self.fingerprint_fields]
        blob = b"".join(np.ascontiguousarray(np.asarray(x, dtype=np.float64)).tobytes() for x in parts)
        return hashlib.sha256(blob).hexdigest()

    def clone(self) -> SuitePlant:
        twin = copy.copy(self)
        twin.physics = self.physics.copy(share_model=True)
        twin.steps = 0
        return twin

    def check_state(self, state: ArrayLike, what: str = "state") -> FloatArray:
        return finite_vector(state, self.state_dim, what, f"{self.state_entries} of {self.task}")

    def check_action(self, action: ArrayLike) -> FloatArray:
        return finite_vector(np.ravel(action), self.action_dim, "action", f"one per actuator of {self.task}")

    def reset(self, state: ArrayLike) -> FloatArray:
        """Set [qpos, qvel] (any finite angles); returns the stored representation."""
        x = self.check_state(state)
        with self.physics.reset_context():
            self.physics.data.qpos[:] = x[: self.positions]
            self.physics.data.qvel[:] = x[self.positions :]
        self.steps = 0
        return self.represent(x)

    def raw_state(self) -> FloatArray:
        return np.concatenate([self.physics.data.qpos, self.physics.data.qvel]).astype(np.float64)

    def state(self) -> FloatArray:
        return self.represent(self.raw_state())

    def step(self, action: ArrayLike) -> float:
        """Apply u (clamped to ctrlrange, as MuJoCo does) for one control step; return dm_control's reward.

        The control is held for ``substeps`` MuJoCo steps, as dm_control's control.Environment does; the
        reward is computed from the physics after the last of them, with the applied (clamped) control.
        """
        u = np.clip(self.check_action(action), self.action_low, self.action_high)
        self.physics.set_control(u)
        self.physics.step(self.substeps)
        self.steps += 1
        return float(self._task.get_reward(self.physics))
