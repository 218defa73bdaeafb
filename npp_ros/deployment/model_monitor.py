"""Whether the robot's transitions stay inside what its certified set of robots can explain.

The gate places the robot's *description* in the set (robot_set.py); the robot itself may still be another one
(a worn gear, a payload, a delay the description cannot show). While npp-deploy commands it, each transition
s_t -> s_t+1 under the command sent is checked against the set:

    error(d) = |s_t+1 - f_nom(s_t, a_t-d)|                       (the nominal model's one-step error)
    bound(d) = max over the set's corners theta of |f_theta(s_t, a_t-d) - f_nom(s_t, a_t-d)|

for each action the robot may have applied: a delay d of 0..action_delay (the set's), plus ``late`` control
steps a command may miss its period by (a real-time robot then holds the previous one). The error against the
bound is what /diagnostics shows. It is blind to direction (a gear of x0.4 errs less than the set's widest
corner on the other side), so a transition *exceeds* by a sharper test on the same corners: for every d, the
state reached lies farther than ``margin`` x bound(d) + ``floor`` from the convex hull of the corners'
predictions f_theta(s_t, a_t-d). Over one short control step the prediction is close to affine in theta, so
that hull holds every robot of the set up to the margin (the curvature of 1/mass is about a tenth of a
+-20% range) and the floor (rounding). Noise on the states, when the set has some, widens both by
``NOISE_SIGMAS`` standard deviations on each of the two states. The robot is said to be outside when at
least ``alarm_share`` of the last ``window`` checked transitions exceed: one odd transition (a state that came
late, a command that missed two periods) is not an alarm, a sustained excess is.

Only consecutive states are checked (a skipped, refused or stale state breaks the chain), and nothing until
``action_delay + late + 1`` commands were sent since. The corners are 2^k models for k uncertain elements;
above ``max_corners`` a fixed sample of them is used (the bound is then a sample's).
"""

from __future__ import annotations

import copy
import itertools
import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from npp_ros.policy.dataset import FloatArray
from npp_ros.tasks.registry import Plant
from npp_ros.tasks.uncertainty import ModelParameters, Robot, UncertaintySet

NOISE_SIGMAS = 4.0
WINDOW = 20
ALARM_SHARE = 0.5
MARGIN = 0.25
FLOOR = 1e-6
LATE = 1
MAX_CORNERS = 64


@dataclass(frozen=True)
class Check:
    """One transition checked: the nominal error for the action that explains it best, and that action's bound."""

    error: float
    bound: float
    distance: float  # from the state reached to the convex hull of the corners' predictions
    delay: int  # the d of that action
    exceeds: bool


def hull_distance(points: FloatArray, target: FloatArray) -> float:
    """The distance from ``target`` to the convex hull of ``points`` (rows): non-negative least squares with the
    weights' sum held at one by a heavy extra row."""
    from scipy.optimize import nnls

    scale = max(float(np.abs(points).max()), float(np.abs(target).max()), 1.0) * 1e3
    a = np.vstack([points.T, np.full(len(points), scale)])
    b = np.concatenate([target, [scale]])
    weights, _ = nnls(a, b)
    return float(np.linalg.norm(points.T @ weights - target))


class OneStep:
    """One control step of a MuJoCo model from a raw joint state [positions, velocities] with the control held."""

    def __init__(self, model: Any, joints: list[str], substeps: int) -> None:
        import mujoco

        self._mujoco = mujoco
        self.model, self.data = model, mujoco.MjData(model)
        ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name) for name in joints]
        self.qpos = np.array([model.jnt_qposadr[i] for i in ids], dtype=np.intp)
        self.qvel = np.array([model.jnt_dofadr[i] for i in ids], dtype=np.intp)
        self.substeps = substeps

    def __call__(self, raw: FloatArray, action: FloatArray) -> FloatArray:
        m, d, n = self.model, self.data, len(self.qpos)
        self._mujoco.mj_resetData(m, d)
        d.qpos[self.qpos], d.qvel[self.qvel] = raw[:n], raw[n:]
        d.ctrl[:] = action
        for _ in range(self.substeps):
            self._mujoco.mj_step(m, d)
        return np.concatenate([d.qpos[self.qpos], d.qvel[self.qvel]])


def corners(robots: UncertaintySet, model: Any, limit: int = MAX_CORNERS) -> list[Robot]:
    """The robots at the corners of the set's ranges (every element at its low or high end); a fixed sample of
    ``limit`` of them when there are more."""
    parameters = ModelParameters(copy.deepcopy(getattr(model, "ptr", model)))
    ranges = [
        (s.parameter, name, s.low, s.high)
        for s in robots.resolved(model).scales
        for name in s.names
        if _moves(parameters, Robot(((s.parameter, name, 2.0),)))  # a zero a scale cannot move is no corner
    ]
    count = 2 ** len(ranges)
    picks: Any = itertools.product((0, 1), repeat=len(ranges))
    if count > limit:
        rng = np.random.default_rng(0)
        picks = [tuple(int(b) for b in row) for row in rng.integers(0, 2, size=(limit, len(ranges)))]
    return [Robot(tuple((p, n, (lo, hi)[b]) for (p, n, lo, hi), b in zip(ranges, pick, strict=True))) for pick in picks]


def _moves(parameters: ModelParameters, robot: Robot) -> bool:
    values = parameters.values(robot)
    return any(not np.array_equal(values[key], parameters.nominal[key]) for key in values)


class ModelMonitor:
    """The check above, transition by transition; see the module's docstring for what each setting means."""

    def __init__(
        self,
        model: Any,
        joints: list[str],
        robots: UncertaintySet,
        substeps: int = 1,
        *,
        window: int = WINDOW,
        alarm_share: float = ALARM_SHARE,
        margin: float = MARGIN,
        floor: float = FLOOR,
        late: int = LATE,
        max_corners: int = MAX_CORNERS,
    ) -> None:
        model = getattr(model, "ptr", model)
        self.robots = robots
        self.nominal = OneStep(copy.deepcopy(model), joints, substeps)
        self.corners = []
        for robot in corners(robots, model, max_corners):
            twin = copy.deepcopy(model)
            ModelParameters(twin).apply(robot)
            self.corners.append(OneStep(twin, joints, substeps))
        self.delays = robots.action_delay + late
        self.margin, self.floor = margin, floor
        self.noise = NOISE_SIGMAS * robots.state_noise * math.sqrt(2 * len(joints)) * 2  # on both states
        self.window, self.alarm_share = window, alarm_share
        self.recent: deque[Check] = deque(maxlen=window)
        self.checked = self.exceeded = 0
        self._state: FloatArray | None = None
        self._actions: deque[FloatArray] = deque(maxlen=self.delays + 1)  # the newest first

    @classmethod
    def of_plant(cls, plant: Plant, robots: UncertaintySet, **settings: Any) -> ModelMonitor:
        """The monitor of a deployment's plant (a MuJoCo plant: its model, joints and control step)."""
        model = plant.physics.model  # type: ignore[attr-defined]
        return cls(model, list(plant.joint_names), robots, int(getattr(plant, "substeps", 1)), **settings)

    def restart(self) -> None:
        """Forget the chain: the next state starts a new one (after a skipped state, a stop, a resume)."""
        self._state = None
        self._actions.clear()

    def reset(self) -> None:
        """Forget everything: a new activation starts with an empty window and counts."""
        self.restart()
        self.recent.clear()
        self.checked = self.exceeded = 0

    def observe(self, raw: FloatArray, action: FloatArray) -> Check | None:
        """The robot is at ``raw`` and ``action`` was sent in answer: check the transition that led here."""
        state, check = np.asarray(raw, dtype=np.float64), None
        if self._state is not None and len(self._actions) == self.delays + 1:
            check = self.check(self._state, list(self._actions), state)
            self.recent.append(check)
            self.checked += 1
            self.exceeded += int(check.exceeds)
        self._state = state
        self._actions.appendleft(np.asarray(action, dtype=np.float64).copy())
        return check

    def check(self, state: FloatArray, actions: list[FloatArray], reached: FloatArray) -> Check:
        """The transition state -> reached, where ``actions[d]`` is the command sent d steps before the last."""
        errors = [float(np.linalg.norm(reached - self.nominal(state, a))) for a in actions]
        best: Check | None = None
        for d in np.argsort(errors):  # the likeliest action first: an explained transition stops early
            action = actions[d]
            predicted = self.nominal(state, action)
            ends = np.array([f(state, action) for f in self.corners] or [predicted])
            bound = float(np.linalg.norm(ends - predicted, axis=1).max()) + self.noise
            distance = hull_distance(ends, reached)
            exceeds = distance > self.margin * bound + self.noise + self.floor
            check = Check(errors[d], bound, distance, int(d), exceeds)
            if best is None or not exceeds:
                best = check
            if not exceeds:
                break
        assert best is not None
        return best

    @property
    def outside(self) -> bool:
        """A sustained excess: at least alarm_share of a full window of checked transitions exceed."""
        full = len(self.recent) == self.window
        return full and sum(c.exceeds for c in self.recent) >= self.alarm_share * self.window

    def summary(self) -> str:
        """The measure and its bound, in words, for /diagnostics and the log."""
        if not self.recent:
            return f"no transition checked yet ({self.checked} so far)"
        last = self.recent[-1]
        share = sum(c.exceeds for c in self.recent)
        worst = max(self.recent, key=lambda c: c.error - c.bound)
        return (
            f"{share} of the last {len(self.recent)} transitions exceed what the certified set explains "
            f"(alarm at {math.ceil(self.alarm_share * self.window)} of {self.window}); last: nominal one-step error "
            f"{last.error:.3g} against the set's bound {last.bound:.3g}; worst: {worst.error:.3g} against "
            f"{worst.bound:.3g}; {self.exceeded} of {self.checked} exceeded since activation"
        )
