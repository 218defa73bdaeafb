"""Model uncertainty: the set of robots a certificate covers, the robot each episode draws, and that robot as a model.

No real robot is its MuJoCo model. A task may declare what is uncertain (:class:`UncertaintySet`): physical
parameters as scales of the model's own values, each in a range (body masses and inertias, actuator gear, joint
damping, friction loss and armature), a delay of 0..k control steps between a command and the actuator, and noise
on the joint states the policy reads. A run with the set on draws one robot theta per episode
(:meth:`UncertaintySet.draw`, from the run's seed and the episode's index only, so a resumed run and the graph draw
the same robots) and every check of that episode runs on it. The claim is then about
(s0, theta) ~ rho x Theta, and the certificate names the set.

Invariants:
- theta depends on (seed, episode) only, on a stream of its own: the s0 stream is the one a run without
  uncertainty draws, so turning the set on changes no s0.
- A scale multiplies the model's nominal value, so a parameter the model sets to zero stays zero.
- Applying a robot to a model and restoring the nominal one are exact (the nominal arrays are kept, not
  divided back); a model is shared by a plant, its clones and the optimizer's dynamics, so a robot applied to
  one is applied to all of them until restored.
"""

from __future__ import annotations

import json
import math
import weakref
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np

from npp_ros.policy.dataset import FloatArray

ROBOT_STREAM = 1  # the spawn key of theta's stream beside (seed, episode); s0 uses (seed, episode) alone
MAX_ACTION_DELAY = 50  # control steps: a longer delay is a different robot, not an uncertain one

# parameter -> (the kind of element it scales, what it is, for help texts and certificates)
PARAMETERS: dict[str, tuple[str, str]] = {
    "mass": ("body", "body mass and rotational inertia, scaled together (a body's density)"),
    "gear": ("actuator", "actuator gear (the motor's torque or force per unit of command)"),
    "damping": ("joint", "joint viscous damping"),
    "frictionloss": ("joint", "joint dry friction loss"),
    "armature": ("joint", "joint armature (rotor inertia reflected through the gear)"),
}


def robot_rng(seed: int, episode: int) -> np.random.Generator:
    """theta's own stream per (seed, episode), apart from s0's (npp_ros.tasks.task.episode_rng)."""
    return np.random.default_rng([int(seed), int(episode), ROBOT_STREAM])


@dataclass(frozen=True)
class ScaleRange:
    """One uncertain parameter: each named element's value is its nominal value times a factor in [low, high]."""

    parameter: str  # a key of PARAMETERS
    low: float
    high: float
    names: tuple[str, ...] = ()  # the bodies, actuators or joints it scales; () = every one of that kind

    def __post_init__(self) -> None:
        if self.parameter not in PARAMETERS:
            raise ValueError(f"unknown uncertain parameter {self.parameter!r}; known: {', '.join(PARAMETERS)}")
        if not (math.isfinite(self.low) and math.isfinite(self.high) and 0 < self.low <= self.high):
            raise ValueError(f"{self.parameter}: a scale range needs 0 < low <= high, got [{self.low}, {self.high}]")

    def widened(self, factor: float) -> ScaleRange:
        """The range with its distance from 1 multiplied by ``factor`` (0: exactly nominal)."""
        low, high = 1 + factor * (self.low - 1), 1 + factor * (self.high - 1)
        return ScaleRange(self.parameter, max(low, 1e-6), max(high, 1e-6), self.names)

    def describe(self) -> str:
        where = f" of {', '.join(self.names)}" if self.names else f" of every {PARAMETERS[self.parameter][0]}"
        return f"{self.parameter}{where} x [{self.low:g}, {self.high:g}]"


@dataclass(frozen=True)
class Robot:
    """One theta: a factor per (parameter, element), the action delay in control steps, and the state noise.

    ``noise_seed`` seeds the noise the policy reads during the episode, so the sim and a local replay add the same.
    """

    scales: tuple[tuple[str, str, float], ...] = ()  # (parameter, element name, factor)
    action_delay: int = 0
    state_noise: float = 0.0  # standard deviation on each stored state entry (the joint's own unit)
    noise_seed: int = 0

    def record(self) -> str:
        """The robot as one JSON text: the episode's row, the messages and the certificate carry this."""
        return json.dumps(
            {
                "scales": [[p, n, float(f)] for p, n, f in self.scales],
                "action_delay": self.action_delay,
                "state_noise": self.state_noise,
                "noise_seed": self.noise_seed,
            },
            sort_keys=True,
        )

    @classmethod
    def from_record(cls, text: str) -> Robot:
        """The robot a record names; a ValueError naming what is wrong with a damaged or foreign one."""
        try:
            item = json.loads(text)
            scales = tuple((str(p), str(n), float(f)) for p, n, f in item["scales"])
            robot = cls(scales, int(item["action_delay"]), float(item["state_noise"]), int(item["noise_seed"]))
        except (ValueError, KeyError, TypeError) as err:
            raise ValueError(f"not a robot record ({type(err).__name__}: {err}): {text[:80]!r}") from None
        for parameter, _, factor in robot.scales:
            if parameter not in PARAMETERS or not (math.isfinite(factor) and factor > 0):
                raise ValueError(f"a robot record scales {parameter!r} by {factor!r}")
        if not 0 <= robot.action_delay <= MAX_ACTION_DELAY or not robot.state_noise >= 0:
            raise ValueError(f"a robot record's delay {robot.action_delay} or noise {robot.state_noise} is not valid")
        return robot

    def describe(self) -> str:
        parts = [f"{p}[{n}] x{f:.3f}" for p, n, f in self.scales]
        if self.action_delay:
            parts.append(f"delay {self.action_delay}")
        if self.state_noise:
            parts.append(f"noise {self.state_noise:g}")
        return ", ".join(parts) or "nominal"

    @property
    def changes_model(self) -> bool:
        return any(f != 1.0 for _, _, f in self.scales)


NOMINAL = Robot()


@dataclass(frozen=True)
class UncertaintySet:
    """Theta: what a task's robot may be. Scales are drawn uniformly and independently per element, the delay
    uniformly from 0..action_delay; the noise has one level. The empty set is the exact model."""

    scales: tuple[ScaleRange, ...] = ()
    action_delay: int = 0  # the largest delay, in control steps
    state_noise: float = 0.0

    def __post_init__(self) -> None:
        if isinstance(self.action_delay, bool) or not 0 <= int(self.action_delay) <= MAX_ACTION_DELAY:
            raise ValueError(f"action_delay must be an integer in [0, {MAX_ACTION_DELAY}], got {self.action_delay!r}")
        if not (math.isfinite(self.state_noise) and self.state_noise >= 0):
            raise ValueError(f"state_noise must be finite and >= 0, got {self.state_noise!r}")
        seen = [(s.parameter, name) for s in self.scales for name in (s.names or ("*",))]
        if len(seen) != len(set(seen)):
            raise ValueError("an uncertain parameter names the same element twice")

    @property
    def empty(self) -> bool:
        return not self.scales and self.action_delay == 0 and self.state_noise == 0

    def widened(self, factor: float) -> UncertaintySet:
        """The set with every range's distance from 1, the delay and the noise multiplied by ``factor``."""
        if not (math.isfinite(factor) and factor >= 0):
            raise ValueError(f"the uncertainty factor must be finite and >= 0, got {factor!r}")
        if factor == 0:
            return EXACT
        return UncertaintySet(
            tuple(s.widened(factor) for s in self.scales),
            min(MAX_ACTION_DELAY, round(self.action_delay * factor)),
            self.state_noise * factor,
        )

    def resolved(self, model: Any) -> UncertaintySet:
        """The set checked against a MuJoCo model, every range naming its elements (none named: all of its kind),
        so that a record of it draws the same robots without the model."""
        elements = model_elements(model)
        scales = []
        for scale in self.scales:
            kind = PARAMETERS[scale.parameter][0]
            unknown = [name for name in scale.names if name not in elements[kind]]
            if unknown:
                raise ValueError(
                    f"uncertainty: {scale.parameter} names {kind} {unknown[0]!r}, which the model does not have "
                    f"(its {kind}s: {', '.join(elements[kind]) or 'none'})"
                )
            scales.append(ScaleRange(scale.parameter, scale.low, scale.high, scale.names or elements[kind]))
        return UncertaintySet(tuple(scales), self.action_delay, self.state_noise)

    def targets(self, scale: ScaleRange) -> tuple[str, ...]:
        """The elements a range scales (a set read from a model or a record names them all)."""
        return scale.names

    def draw(self, seed: int, episode: int) -> Robot:
        """The robot of ``episode``: its own stream of (seed, episode), so every process draws the same one."""
        rng = robot_rng(seed, episode)
        scales = tuple(
            (scale.parameter, name, float(rng.uniform(scale.low, scale.high)))
            for scale in self.scales
            for name in self.targets(scale)
        )
        delay = int(rng.integers(0, self.action_delay + 1))
        noise_seed = int(rng.integers(0, 2**31 - 1))
        return Robot(scales, delay, float(self.state_noise), noise_seed)

    def contains(self, robot: Robot) -> list[str]:
        """Why ``robot`` lies outside the set (empty: inside), one reason per parameter that does."""
        ranges = {(s.parameter, name): s for s in self.scales for name in self.targets(s)}
        reasons = []
        for parameter, name, factor in robot.scales:
            scale = ranges.get((parameter, name))
            low, high = (1.0, 1.0) if scale is None else (scale.low, scale.high)
            if not low * (1 - 1e-9) <= factor <= high * (1 + 1e-9):
                reasons.append(f"{parameter} of {name}: x{factor:.4g} lies outside [{low:g}, {high:g}]")
        if robot.action_delay > self.action_delay:
            reasons.append(f"action delay {robot.action_delay} exceeds {self.action_delay}")
        return reasons

    def describe(self) -> str:
        """The set in words, as the certificate and the run's output state it."""
        if self.empty:
            return "the exact model"
        parts = [s.describe() for s in self.scales]
        if self.action_delay:
            parts.append(f"action delay 0..{self.action_delay} control steps")
        if self.state_noise:
            parts.append(f"noise on the states read of standard deviation {self.state_noise:g}")
        return "; ".join(parts) + " (each drawn uniformly and independently per element and episode)"

    def record(self) -> str:
        """The set as one JSON text, for the run file's metadata (an empty set: '')."""
        if self.empty:
            return ""
        return json.dumps(
            {
                "scales": [[s.parameter, s.low, s.high, list(s.names)] for s in self.scales],
                "action_delay": self.action_delay,
                "state_noise": self.state_noise,
            },
            sort_keys=True,
        )

    @classmethod
    def from_record(cls, text: str) -> UncertaintySet:
        if not text:
            return cls()
        try:
            item = json.loads(text)
            scales = tuple(ScaleRange(str(p), float(lo), float(hi), tuple(map(str, names)))
                           for p, lo, hi, names in item["scales"])  # fmt: skip
            return cls(scales, int(item["action_delay"]), float(item["state_noise"]))
        except (ValueError, KeyError, TypeError) as err:
            raise ValueError(f"not an uncertainty record ({type(err).__name__}: {err}): {text[:80]!r}") from None


EXACT = UncertaintySet()


# ---------------------------------------------------------------------------------------------- a robot as a model
def _raw(model: Any) -> Any:
    return getattr(model, "ptr", model)  # dm_control's wrapper holds the MjModel as .ptr


def model_elements(model: Any) -> dict[str, tuple[str, ...]]:
    """The model's bodies (the world left out), actuators and joints by name, in the model's order."""
    import mujoco

    m = _raw(model)

    def names(kind: Any, count: int, start: int = 0) -> tuple[str, ...]:
        return tuple(mujoco.mj_id2name(m, kind, i) or f"#{i}" for i in range(start, count))

    return {
        "body": names(mujoco.mjtObj.mjOBJ_BODY, m.nbody, 1),
        "actuator": names(mujoco.mjtObj.mjOBJ_ACTUATOR, m.nu),
        "joint": names(mujoco.mjtObj.mjOBJ_JOINT, m.njnt),
    }


class ModelParameters:
    """The nominal values of a MuJoCo model's uncertain parameters, and the model made into a robot from them."""

    def __init__(self, model: Any) -> None:
        import mujoco

        self._mujoco = mujoco
        self.model = _raw(model)
        m = self.model
        self.elements = model_elements(m)
        self.nominal = {
            "body_mass": m.body_mass.copy(),
            "body_inertia": m.body_inertia.copy(),
            "actuator_gear": m.actuator_gear.copy(),
            "dof_damping": m.dof_damping.copy(),
            "dof_frictionloss": m.dof_frictionloss.copy(),
            "dof_armature": m.dof_armature.copy(),
        }
        self.current: Robot = NOMINAL
        self._scratch: Any = None

    def _index(self, kind: str, name: str) -> int:
        try:
            position = self.elements[kind].index(name)
        except ValueError:
            raise ValueError(f"the model has no {kind} {name!r}") from None
        return position + 1 if kind == "body" else position

    def values(self, robot: Robot) -> dict[str, FloatArray]:
        """The arrays the model holds as ``robot``."""
        out = {key: value.copy() for key, value in self.nominal.items()}
        m = self.model
        for parameter, name, factor in robot.scales:
            i = self._index(PARAMETERS[parameter][0], name)
            if parameter == "mass":
                out["body_mass"][i] *= factor
                out["body_inertia"][i] *= factor
            elif parameter == "gear":
                out["actuator_gear"][i, 0] *= factor
            else:
                out[f"dof_{parameter}"][int(m.jnt_dofadr[i])] *= factor
        return out

    def apply(self, robot: Robot) -> None:
        """Write ``robot`` into the model in place (every holder of the model sees it) and refresh its constants."""
        if robot == self.current:
            return
        for key, value in self.values(robot).items():
            getattr(self.model, key)[:] = value
        if self._scratch is None:  # mj_setConst's workspace, made once: a new MjData per robot costs as much
            self._scratch = self._mujoco.MjData(self.model)
        self._mujoco.mj_setConst(self.model, self._scratch)
        self.current = robot


_PARAMETERS: weakref.WeakKeyDictionary[Any, ModelParameters] = weakref.WeakKeyDictionary()


def parameters_of(plant: Any) -> ModelParameters:
    """The plant's model parameters, made once per model: a clone sharing the model shares them, so the nominal
    values are read while the model is still nominal, never from a robot another holder applied."""
    model = _raw(plant.physics.model)
    cached = _PARAMETERS.get(model)
    if cached is None:
        cached = _PARAMETERS[model] = ModelParameters(model)
    return cached


def supports_robots(plant: Any) -> bool:
    """Whether a plant's model can be made into a drawn robot (a MuJoCo plant with the state [qpos, qvel])."""
    return hasattr(getattr(plant, "physics", None), "model")


@contextmanager
def as_robot(plant: Any, robot: Robot | None) -> Iterator[None]:
    """The plant's model is ``robot`` inside the block and nominal again after it (None: left as it is)."""
    if robot is None or not robot.changes_model:
        yield
        return
    parameters = parameters_of(plant)
    parameters.apply(robot)
    try:
        yield
    finally:
        parameters.apply(NOMINAL)


class RobotEffects:
    """What a drawn robot does beside its model, step by step: the delay between a command and the actuator,
    and the noise on the states the policy reads. The sim node and the local rollout use this one class."""

    def __init__(self, robot: Robot, action_dim: int) -> None:
        self.robot = robot
        self._noise = np.random.default_rng(robot.noise_seed)
        self._queue = [np.zeros(action_dim) for _ in range(robot.action_delay)]

    def observe(self, state: FloatArray) -> FloatArray:
        """The state the policy reads: the true one plus the robot's noise (the true one when it has none)."""
        if self.robot.state_noise == 0:
            return state
        return state + self._noise.normal(0.0, self.robot.state_noise, size=np.shape(state))

    def command(self, action: FloatArray) -> FloatArray:
        """The action the actuator applies now: the one commanded ``action_delay`` steps ago (zero before)."""
        if not self._queue:
            return np.asarray(action, dtype=np.float64)
        self._queue.append(np.asarray(action, dtype=np.float64).copy())
        return self._queue.pop(0)


# The built-in swing-ups' set, off unless a run asks for it: masses and inertias known to 20%, the motor constant to
# 20%, damping to a factor of 1.5, and a command that may arrive one control step late.
SWINGUP_UNCERTAINTY = UncertaintySet(
    (ScaleRange("mass", 0.8, 1.2), ScaleRange("gear", 0.8, 1.2), ScaleRange("damping", 0.5, 1.5)), action_delay=1
)


def describe_robots(record: str) -> str:
    """A run's set of robots in words from its record ('' for the exact model, which a claim need not name)."""
    return UncertaintySet.from_record(record).describe() if record else ""


UNCERTAINTY_HELP = (
    "model uncertainty: 0 (the default) checks the exact model; 1 draws each episode's robot from the set the task "
    "declares (a task file's [uncertainty] table; the swing-ups: masses x [0.8, 1.2], gear x [0.8, 1.2], damping "
    "x [0.5, 1.5], a delay of 0 or 1 control step); another factor widens or narrows every range around the "
    "nominal model. The expert plans on each episode's robot, the policy does not know it, and the certificate "
    "names the set"
)


def where_expert_failed(robots: Sequence[Robot], failed: Sequence[bool]) -> str:
    """Where in the set the expert failed the task, in words ("" when it never did): the range each parameter
    took over the robots of its failed answers beside the range it took over all of them, and their delays.

    A set must stay within what the expert can do; this says which corner of it the expert could not."""
    bad = [robot for robot, lost in zip(robots, failed, strict=True) if lost]
    if not bad:
        return ""

    def spread(group: Sequence[Robot]) -> dict[tuple[str, str], tuple[float, float]]:
        values: dict[tuple[str, str], list[float]] = {}
        for robot in group:
            for parameter, name, factor in robot.scales:
                values.setdefault((parameter, name), []).append(factor)
        return {key: (min(v), max(v)) for key, v in values.items()}

    failing, every = spread(bad), spread(robots)
    parts = [
        f"{parameter} of {name} x[{low:.2f}, {high:.2f}] (all answers x[{every[parameter, name][0]:.2f}, "
        f"{every[parameter, name][1]:.2f}])"
        for (parameter, name), (low, high) in failing.items()
    ]
    delays = sorted({robot.action_delay for robot in bad})
    parts.append(f"delay {', '.join(map(str, delays))}")
    return f"the expert failed on {len(bad)} of {len(robots)} answers, on robots with " + "; ".join(parts)
