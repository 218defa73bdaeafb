"""A task from a file: a MuJoCo model (MJCF) and a TOML description of its task, no Python.

``--task path/to/task.toml`` (and the sim's ``task`` parameter) loads one; README "Your own robot"
describes every key. In short::

    model = "arm.xml"              # MJCF, relative to this file
    control_timestep = 0.01        # optional; k x the model's timestep: k MuJoCo steps per control step (default 1)
    horizon = 200                  # default episode length
    epsilon = 40.0                 # default target gap
    lipschitz = 100.0              # default L of the policy's bounds (a choice, not a bound); or "data" (the default)
    certify = "oracle"             # default certification mode
    actuators = ["shoulder_motor", "elbow_motor"]   # optional check: the model's actuators, in order

    [state]
    joints = ["shoulder", "elbow"] # every joint of the model (hinge or slide), in the model's order
    wrap = ["shoulder"]            # hinge angles stored wrapped to (-pi, pi]
    invariant = []                 # joints whose position changes neither dynamics nor reward (checked at load)
    target = []                    # or the x, y, z slide joints of a point no torque moves (a reach's target)

    [state.weights]                # optional: each entry's weight in the policy's distance (default 1)
    shoulder = 2.0                 # a joint's position; or { position = 2.0, velocity = 0.5 }

    [rho]                          # s0 uniform in these ranges; joints not named start at 0, at rest
    shoulder = { position = [-3.14, 3.14], velocity = [0.0, 0.0] }

    [reward]
    combine = "sum"                # or "product"
    [[reward.terms]]               # dm_control.utils.rewards.tolerance of one named quantity
    site_distance = ["fingertip", "target"]
    bounds = [0.0, 0.02]
    margin = 0.3
    sigmoid = "gaussian"           # and value_at_margin, weight (sum only)
    # or: function = "my_module:reward", called as reward(physics) -> float after each step

    [expert]                       # the iLQR expert (npp_ros.trajopt.expert.OptimizingExpert)
    max_iterations = 30            # a request ends by convergence or this cap: the same answer on any machine
    stop = "iterations"            # or "time": iLQR within time_budget, fewer iterations on a loaded machine
    time_budget = 60.0             # s per request: under "iterations" a guard against a runaway request
    warm_start = "zero"            # or "gravity": the torques that hold the start at rest
    planner = "ilqr"               # or "receding", "sampling": windows first (npp_ros.trajopt.receding: window,
                                   # commit, window_iterations, restarts; samples, knots, noise, sample_rounds)

    [success]                      # optional: when an episode did the task (npp_ros.tasks.task_file.success)
    distance = ["fingertip", "target"]   # or joint = NAME, site = NAME with axis = "x", "y" or "z", or speed = SITE
    within = [0.0, 0.02]
    last_seconds = 0.5             # several bands: one [[success]] table each, all must hold

Quantities: ``joint_position``, ``joint_velocity`` (a joint), ``site_position`` (a site, with
``axis`` x, y or z), ``site_distance`` (two sites), ``control`` (an actuator). The reward is
computed from the physics after each step with the applied (clamped) control, as dm_control's
suite does (npp_ros.tasks.task_file.terms).

The expert optimises a smooth surrogate of the reward (npp_ros.tasks.task_file.cost): each term
costs 0.5 w ((q - clip(q, bounds)) / margin)^2, zero exactly where its tolerance is 1; the values it
stores are the true rewards replayed on the plant, as for every iLQR expert. ``[[expert.terms]]``
replaces the reward's terms as that cost, and may add ``energy = { joint = position, ... }``: the
mechanical energy less that pose's at rest, which an underactuated swing-up must pump; a distance
term there may take ``hessian = "offset"`` (the Gauss-Newton Hessian of the offset vector, not of the
scalar distance: npp_ros.tasks.task_file.cost.TermCost).

Agreement: the task's name is the file's absolute path and its content's SHA-256
(``/abs/task.toml#sha256=...``); the sim publishes that name, and the expert and the supervisor
load the file at that path and refuse it when its content differs (naming both hashes). The
compiled model is compared by its fingerprint, as for every task.

A bad file is refused with one line naming the file, the key and the problem (:class:`TaskFileError`).

This module makes the task (plant, expert, Task) from a file's definition; reading the file is
schema.py beside it, with the model's parts in model.py, the reward in terms.py and every refusal's wording in
reader.py.
"""

from __future__ import annotations

import functools
import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from npp_ros.certificate.choices import EPSILON_FLAG
from npp_ros.policy.dataset import FloatArray
from npp_ros.tasks.suite_plant import SuitePlant, substeps_per_control_step
from npp_ros.tasks.task import DEFAULT_OPTIONS, Expert, ExpertOptions, OptimizerTask, check_horizon
from npp_ros.tasks.task_file.cost import TermCost
from npp_ros.tasks.task_file.reader import TaskFileError as TaskFileError  # re-exported: what a bad file raises
from npp_ros.tasks.task_file.schema import DEFAULT_MAX_ITERATIONS, HASH_MARK, TaskDefinition, parse
from npp_ros.tasks.task_file.terms import TermReward
from npp_ros.trajopt.expert import DEFAULT_STOP, DEFAULT_VALUES
from npp_ros.trajopt.receding import PlannerSettings, PlanningExpert

FINGERPRINT_FIELDS = (
    "opt.timestep", "opt.gravity", "opt.integrator", "opt.wind", "opt.density", "opt.viscosity", "dof_damping",
    "dof_armature", "dof_frictionloss", "jnt_stiffness", "jnt_range", "jnt_limited", "qpos0", "body_mass",
    "body_inertia", "body_ipos", "body_iquat", "body_pos", "body_quat", "geom_size", "geom_pos", "site_pos",
    "actuator_gear", "actuator_ctrlrange", "actuator_ctrllimited", "actuator_gainprm", "actuator_biasprm",
)  # fmt: skip


class FilePlant(SuitePlant):
    """The file's model, ``control_timestep`` / the model's timestep MuJoCo steps per control step, its reward
    from the file, computed after the last of them."""

    def __init__(self, definition: TaskDefinition, seed: int = 0) -> None:
        os.environ.setdefault("MUJOCO_GL", "disable")
        from dm_control import mujoco as dm_mujoco

        self.definition = definition
        self.task = definition.name
        self.state_entries = definition.stored_state()
        self.fingerprint_fields = FINGERPRINT_FIELDS
        self.represent = definition.represent  # type: ignore[method-assign]  # the file's wrapping, per instance
        self.angles = tuple(definition.wrapped)
        self.invariant = tuple(definition.invariant)  # the policy's distance ignores them (npp_ros.policy.feedback)
        self.target_joints = tuple(definition.target_joints)  # a robot has none: a deployment reads them as a point
        self.distance_weights = tuple(definition.distance_weights)  # the policy's distance (npp_ros.policy.feedback)
        self.seed = int(seed)
        self.physics = dm_mujoco.Physics.from_xml_path(str(definition.model_path))
        self._task = definition.reward
        model = self.physics.model
        self.dt = definition.dt  # the control step, a whole multiple of the model's timestep (read_timestep)
        substeps = substeps_per_control_step(self.dt, float(model.opt.timestep))
        assert substeps is not None  # read_timestep refused any other
        self.substeps = substeps
        self.positions = int(model.nq)
        self.state_dim = int(model.nq + model.nv)
        self.action_dim = int(model.nu)
        self.joint_names = list(definition.joint_names)
        self.actuated_joint_names = list(definition.actuated_joint_names)
        self.action_low = np.where(model.actuator_ctrllimited, model.actuator_ctrlrange[:, 0], -np.inf)
        self.action_high = np.where(model.actuator_ctrllimited, model.actuator_ctrlrange[:, 1], np.inf)
        self.steps = 0


class GravityHold:
    """The torques that hold the arm still where it is: each actuated joint's gravity torque at the state's
    position (MuJoCo's inverse dynamics at zero velocity and acceleration), over the actuator's gear, clamped.

    A warm start for an arm under gravity: iLQR from u = 0 begins at the arm falling, far from any reach. It is
    computed from the model, so it holds whatever the model's masses are; the policy and the expert's answers
    carry the whole torque (nothing compensates gravity under them).
    """

    def __init__(self, model: object, low: FloatArray, high: FloatArray) -> None:
        import mujoco

        self._mujoco = mujoco
        self.model = model
        self.data = mujoco.MjData(model)
        self.low, self.high = low, high
        self.dofs = np.array([int(model.jnt_dofadr[j]) for j in model.actuator_trnid[:, 0]])
        self.gear = np.asarray(model.actuator_gear[:, 0], dtype=np.float64)
        self._out = np.zeros(model.nv)

    def __call__(self, x: FloatArray) -> FloatArray:
        mj, m, d = self._mujoco, self.model, self.data
        d.qpos[:] = x[: m.nq]
        d.qvel[:] = 0.0
        mj.mj_kinematics(m, d)
        mj.mj_comPos(m, d)
        mj.mj_rne(m, d, 0, self._out)
        return np.clip(self._out[self.dofs] / self.gear, self.low, self.high)


class FileExpert(PlanningExpert):
    """The iLQR expert on the file's model, its smooth cost from the file's terms, warm-started at u = 0 or, with
    ``[expert] warm_start = "gravity"``, at the torques that hold the start (:class:`GravityHold`).

    ``[expert] planner`` (npp_ros.trajopt.receding) plans each request by receding-horizon windows
    before the iLQR over the whole horizon; a plan that misses the file's ``[success]`` is made again
    (``restarts``). The default, ``"ilqr"``, is that iLQR alone from u = 0.
    """

    def __init__(
        self,
        definition: TaskDefinition,
        seed: int = 0,
        horizon: int | None = None,
        time_budget: float | None = None,
        max_iterations: int = DEFAULT_MAX_ITERATIONS,
        values: str = DEFAULT_VALUES,
        stop: str = DEFAULT_STOP,
    ) -> None:
        plant = FilePlant(definition, seed)
        zero = np.zeros(plant.action_dim)
        warm_start = (
            GravityHold(plant.physics.model.ptr, plant.action_low, plant.action_high)
            if definition.expert.get("warm_start") == "gravity"
            else (lambda _x: zero)
        )
        success = definition.success
        super().__init__(
            plant,
            TermCost(definition.cost_terms, plant.physics.model.ptr, definition.expert),
            warm_start,
            definition.represent,
            settings=definition.expert.get("planner", PlannerSettings()),
            seed=seed,
            judge=None if success is None else lambda raw: success.met(definition.represent(raw)),
            horizon=definition.horizon if horizon is None else horizon,
            time_budget=time_budget,
            max_iterations=max_iterations,
            values=values,
            stop=stop,
        )
        self.task = definition.name
        self.reward_lipschitz_detail = "not computed for a task file's reward"


@dataclass(frozen=True)
class FileTask(OptimizerTask):
    """A task from a file: its plant, its iLQR expert, its rho and its defaults, as the file says."""

    definition: TaskDefinition | None = None

    def make_plant(self, seed: int) -> FilePlant:
        assert self.definition is not None
        return FilePlant(self.definition, seed)

    def make_expert(self, seed: int, horizon: int, options: ExpertOptions = DEFAULT_OPTIONS) -> Expert:
        assert self.definition is not None
        self.expert_kind(options)
        if options.gamma != 1.0:
            raise ValueError(
                f"the {self.definition.label} expert computes undiscounted H-step returns; gamma must be 1"
            )
        own = self.definition.expert
        expert = FileExpert(
            self.definition, seed, check_horizon(horizon),
            time_budget=options.time_budget or own.get("time_budget", self.default_time_budget),
            max_iterations=options.max_iterations or own.get("max_iterations", DEFAULT_MAX_ITERATIONS),
            values=options.values or own.get("values", DEFAULT_VALUES),
            stop=options.stop or own.get("stop", DEFAULT_STOP),
        )  # fmt: skip
        if options.threads is not None:
            expert.optimizer.dynamics.threads = options.threads
        return expert

    def sample_initial_state(self, rng: np.random.Generator) -> FloatArray:
        assert self.definition is not None
        return self.definition.sample_initial_state(rng)

    def invariant_entries(self) -> tuple[int, ...]:
        assert self.definition is not None
        return tuple(self.definition.invariant)

    def epsilon(self, given: float | None) -> float:
        if given is not None:
            return float(given)
        if self.definition is None or self.definition.epsilon is None:
            raise ValueError(f"the task file gives no epsilon: add `epsilon = ...` to it or {EPSILON_FLAG}")
        return self.definition.epsilon


def split_name(name: str) -> tuple[Path, str | None]:
    """A task file's path (absolute) and the content hash its name asks for (None: whatever the file holds)."""
    path, mark, digest = name.partition(HASH_MARK)
    return Path(path).expanduser().resolve(), digest if mark else None


def load_task_file(name: str) -> FileTask:
    """The task in a file, by path or by the name a sim published (path and content hash).

    A file whose content differs from the hash in the name is refused, naming both.
    """
    path, expected = split_name(name)
    try:
        content = path.read_bytes()
    except OSError as exc:
        raise TaskFileError(f"task file {path}: cannot be read: {exc.strerror or exc}") from None
    digest = hashlib.sha256(content).hexdigest()
    if expected is not None and digest != expected:
        raise TaskFileError(
            f"task file mismatch: the task is {path}{HASH_MARK}{expected[:16]}..., but the file at that path now holds "
            f"{path}{HASH_MARK}{digest[:16]}...: the processes of a run must read the same task file"
        )
    return _task(path, digest, content)


def target_origin(plant: FilePlant) -> FloatArray:
    """Where the plant's target is when its three joints are at 0: its body's position in the world. A point p in
    the world is the target joints' position p - origin."""
    model = plant.physics.model
    joint = model.joint(plant.target_joints[0])
    return np.array(model.body_pos[int(joint.bodyid[0])], dtype=np.float64)


def sampled_action_range(plant: FilePlant) -> tuple[FloatArray, FloatArray]:
    """The actuator range the load-time checks draw random actions from: the control range, [-1, 1] where an
    actuator has no limit."""
    low = np.where(np.isfinite(plant.action_low), plant.action_low, -1.0)
    high = np.where(np.isfinite(plant.action_high), plant.action_high, 1.0)
    return low, high


TARGET_STEPS = 20  # control steps of random torques a declared target is checked on at load


def check_target(definition: TaskDefinition) -> None:
    """Refuse a ``[state] target`` that a torque moves: from s0 ~ rho, random torques for TARGET_STEPS steps
    must leave the target's positions exactly where they were and its velocities exactly 0."""
    if not definition.target_joints:
        return
    plant = FilePlant(definition)
    rng = np.random.default_rng(0)
    low, high = sampled_action_range(plant)
    entries = [definition.joint_names.index(name) for name in definition.target_joints]
    entries += [plant.positions + i for i in entries]
    s0 = definition.sample_initial_state(rng)
    plant.reset(s0)
    for _ in range(TARGET_STEPS):
        plant.step(rng.uniform(low, high))
    moved = plant.raw_state()[entries] - s0[entries]
    if np.any(moved != 0.0):
        raise TaskFileError(
            f"task file {definition.path}: state.target: random torques moved the target by up to "
            f"{float(np.max(np.abs(moved))):.3g} in {TARGET_STEPS} steps: nothing may act on it"
        )


INVARIANCE_SAMPLES = 8  # (state, action) pairs a declared invariance is checked on at load
INVARIANCE_TOLERANCE = 1e-6  # a next state or reward may differ by this (relative to 1 + its size): rounding


def check_invariance(definition: TaskDefinition) -> None:
    """Refuse a ``[state] invariant`` joint whose position does change the dynamics or the reward.

    For a few states (s0 ~ rho, velocities drawn wider) and actions (uniform over the actuator range) the plant
    steps once from s and once from s with that joint's position shifted: a true invariance gives the same
    reward and the same next state up to the shift. Sampled, so a check that passes is evidence, not a proof; a
    check that fails is a counterexample, named in one line.
    """
    if not definition.invariant:
        return
    plant = FilePlant(definition)
    rng = np.random.default_rng(0)
    low, high = sampled_action_range(plant)
    positions = plant.positions
    for entry in definition.invariant:
        joint = definition.joint_names[int(np.flatnonzero(plant.physics.model.jnt_qposadr == entry)[0])]
        for _ in range(INVARIANCE_SAMPLES):
            s = definition.sample_initial_state(rng)
            s[positions:] += rng.normal(0.0, 1.0, plant.state_dim - positions)
            u = rng.uniform(low, high)
            shift = float(rng.uniform(-np.pi, np.pi))
            moved = s.copy()
            moved[entry] += shift
            plant.reset(s)
            reward = plant.step(u)
            after = plant.raw_state()
            plant.reset(moved)
            moved_reward = plant.step(u)
            moved_after = plant.raw_state()
            moved_after[entry] -= shift
            gap = float(np.max(np.abs(moved_after - after) / (1.0 + np.abs(after))))
            reward_gap = abs(moved_reward - reward) / (1.0 + abs(reward))
            if gap > INVARIANCE_TOLERANCE or reward_gap > INVARIANCE_TOLERANCE:
                what = (
                    f"the reward by {abs(moved_reward - reward):.3g}"
                    if reward_gap > INVARIANCE_TOLERANCE
                    else f"the next state by up to {float(np.max(np.abs(moved_after - after))):.3g}"
                )
                raise TaskFileError(
                    f"task file {definition.path}: state.invariant: joint {joint!r} is not invariant: "
                    f"shifting its position by {shift:.3g} changes {what} (state {np.round(s, 3).tolist()}, "
                    f"action {np.round(u, 3).tolist()})"
                )


@functools.lru_cache(maxsize=32)
def _task(path: Path, digest: str, content: bytes) -> FileTask:
    definition = parse(path, content)
    check_invariance(definition)
    check_target(definition)
    return FileTask(
        name=definition.name,
        state_dim=definition.state_dim,
        action_dim=definition.action_dim,
        stored_state=definition.stored_state(),
        initial_state_diameter=definition.initial_state_diameter(),
        default_certify=definition.certify,  # type: ignore[arg-type]  # checked against CERTIFY_MODES
        default_policy=definition.policy,  # type: ignore[arg-type]  # checked against POLICY_KINDS
        no_analytic_lipschitz="its iLQR expert computes no bound on its value's slope",
        own_lipschitz=definition.lipschitz,
        own_lipschitz_note="the task file's key lipschitz: a choice of the policy's bounds, not a bound on the value",
        default_time_budget=definition.expert.get("time_budget"),
        default_horizon=definition.horizon,
        reward_range=definition.reward.bounds() if isinstance(definition.reward, TermReward) else None,
        success=definition.success,
        uncertainty=definition.uncertainty,
        definition=definition,
    )
