"""The set's parameters fitted to a robot's motion: which robot of the set (or beside it) this one is.

Model: each state read is the previous one stepped through MuJoCo with the robot's scales applied (the same
:class:`~npp_ros.tasks.uncertainty.ModelParameters` a run draws robots with) under the command sent ``d`` control
steps before (the delay). For each delay candidate d = 0..max_delay the log-scales z (one per (parameter, element)
of the set) minimise the weighted one-step prediction errors (``steps`` > 1: each prediction runs that many steps);
the weights are each state entry's residual spread, refitted once. The delay with the smallest residual (the
Gaussian likelihood, sum of log RMS per entry) is the robot's; every candidate's residual is reported.

What the motion can tell: the Jacobian J of the weighted residuals in z at the optimum, J = U S V'. A direction of
z with a singular value below ``NULL_TOLERANCE`` x the largest changes no prediction: the parameters it moves cannot
be told apart (a pendulum's mass, gear and damping scaled together scale every force and inertia alike and leave
its motion unchanged). The identifiable combinations are the log-linear functionals orthogonal to those directions,
written against reference parameters (mass first) as products of factors (gear / mass), each with a t-interval
from the Gauss-Newton covariance s^2 (J'J)^+ with s^2 the residual variance. The estimate is then moved along the
directions the data cannot see to the set if it can reach it: a robot is inside when some robot of the set has its
combinations (and its delay), and the one nearest it is named when none does.
"""

from __future__ import annotations

import copy
import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from npp_ros.identification.recording import Recording
from npp_ros.policy.dataset import FloatArray
from npp_ros.tasks.registry import Plant, Task, get_task
from npp_ros.tasks.uncertainty import MAX_ACTION_DELAY, ModelParameters, Robot, UncertaintySet

NULL_TOLERANCE = 1e-5  # relative singular value below which a direction changes no prediction (rounding level)
FD_STEP = 1e-5  # central differences in log-scale: residual differences stay far above rounding
LOG_BOUND = math.log(50.0)  # the fit searches factors in [1/50, 50] of the nominal model
TIMING_TOLERANCE = 0.25  # a state period further than this share from the control step breaks the chain there
REFERENCE_ORDER = ("mass", "armature", "gear", "damping", "frictionloss")  # reference parameters, preferred first
READ_RESOLUTION = 1e-6  # the finest a state entry is taken to be read (rad, m, per s): the noise is never below
EXTRA_DELAYS = 2  # delay candidates tried beyond the set's largest: a robot outside in its delay shows as one


@dataclass(frozen=True)
class Combination:
    """One product of factors the motion determines: prod factor_j ** exponent_j, its estimate and interval."""

    label: str
    exponents: tuple[tuple[str, str, float], ...]  # (parameter, element, exponent on its factor)
    value: float
    low: float
    high: float

    def record(self) -> dict[str, Any]:
        return {"label": self.label, "exponents": [list(e) for e in self.exponents], "value": self.value,
                "low": self.low, "high": self.high}  # fmt: skip


@dataclass(frozen=True)
class DelayFit:
    """One delay candidate's best fit: its weighted-residual score (lower is better) and RMS error per entry."""

    delay: int
    score: float  # sum over state entries of log RMS residual: the Gaussian likelihood, up to constants
    rms: tuple[float, ...]  # per state entry
    factors: tuple[float, ...]  # the fitted scale per fitted parameter

    def record(self) -> dict[str, Any]:
        return {"delay": self.delay, "score": self.score, "rms": list(self.rms), "factors": list(self.factors)}


@dataclass(frozen=True)
class Identification:
    """What one recording says about the robot: see the module's docstring for how each field is made."""

    task: str
    parameters: tuple[tuple[str, str], ...]  # (parameter, element) fitted, in z's order
    fixed: tuple[str, ...]  # parameters of the set not fitted, and why
    robots: UncertaintySet  # the set it was placed against
    estimate: Robot  # the fitted factors moved (along what the data cannot see) nearest the set; delay; set's noise
    delay: int
    delays: tuple[DelayFit, ...]
    combinations: tuple[Combination, ...]
    unidentifiable: tuple[str, ...]  # each direction the data cannot see, in words
    singular_values: tuple[float, ...]  # of the weighted Jacobian, largest first
    noise: tuple[float, ...]  # residual RMS per state entry at the chosen delay (noise and what the model misses)
    transitions: int
    confidence: float
    inside: bool  # some robot of the set has the estimated combinations and the delay
    reaches: bool  # some robot of the set lies within the combinations' intervals (and has the delay)
    reasons: tuple[str, ...]  # why the estimate lies outside the set (empty: inside)
    wall_time: float
    _z: tuple[float, ...] = ()  # the estimate in log-scale
    _w: tuple[tuple[float, ...], ...] = ()  # the combinations' exponent rows

    @property
    def verdict(self) -> str:
        """inside, outside, or near the edge (outside at the estimate, but its intervals reach into the set)."""
        return "inside" if self.inside else "near the edge" if self.reaches else "outside"

    def region(self) -> list[Robot]:
        """The estimate and the corners of the combinations' intervals (every combination at its low or high end,
        the directions the data cannot see left where the estimate has them): the points a check runs at."""
        z = np.array(self._z)
        w = np.array(self._w).reshape(len(self.combinations), len(z))
        points = [self.estimate]
        if len(self.combinations) == 0:
            return points
        centre = np.log([c.value for c in self.combinations])
        ends = np.log([[c.low, c.high] for c in self.combinations])
        pinv = np.linalg.pinv(w)
        for pick in np.ndindex(*(2,) * len(self.combinations)):
            target = ends[np.arange(len(pick)), list(pick)]
            zc = z + pinv @ (target - centre)
            points.append(self._robot(zc))
        return points

    def _robot(self, z: FloatArray) -> Robot:
        scales = tuple((p, n, float(math.exp(v))) for (p, n), v in zip(self.parameters, z, strict=True))
        return Robot(scales, self.delay, self.estimate.state_noise, self.estimate.noise_seed)

    def record(self) -> dict[str, Any]:
        """Everything as JSON-ready values (npp-identify --json)."""
        return {
            "task": self.task,
            "verdict": self.verdict,
            "inside": self.inside,
            "reaches": self.reaches,
            "reasons": list(self.reasons),
            "set": self.robots.describe(),
            "delay": self.delay,
            "delays": [delay.record() for delay in self.delays],
            "combinations": [c.record() for c in self.combinations],
            "unidentifiable": list(self.unidentifiable),
            "fixed": list(self.fixed),
            "parameters": [list(p) for p in self.parameters],
            "estimate": json.loads(self.estimate.record()),
            "region": [json.loads(robot.record()) for robot in self.region()],  # what a check before moving runs at
            "singular_values": list(self.singular_values),
            "noise": list(self.noise),
            "transitions": self.transitions,
            "confidence": self.confidence,
            "wall_time": self.wall_time,
        }

    def summary(self) -> str:
        """The result in words, as npp-identify prints it."""
        level = f"{100 * self.confidence:g}%"
        lines = [f"identified from {self.transitions} transitions in {self.wall_time:.1f} s:"]
        lines.append(f"  what the motion determines ({level} intervals):")
        for c in self.combinations:
            lines.append(f"    {c.label:<40} {c.value:.4f}  [{c.low:.4f}, {c.high:.4f}]")
        for why in self.unidentifiable:
            lines.append(f"  not identifiable: {why}")
        for why in self.fixed:
            lines.append(f"  not fitted: {why}")
        scores = ", ".join(f"{d.delay}: {d.score:.2f}" for d in self.delays)
        ranked = sorted(self.delays, key=lambda d: d.score)
        gap = f", next best by {ranked[1].score - ranked[0].score:.2f}" if len(ranked) > 1 else ""
        lines.append(f"  delay: {self.delay} control steps (residual score per candidate, lower is better: {scores}"
                     f"{gap})")  # fmt: skip
        lines.append(f"  against the set ({self.robots.describe()}):")
        if self.inside:
            lines.append(f"    inside: a robot of the set has these combinations and this delay, e.g. "
                         f"{self.estimate.describe()}")  # fmt: skip
        else:
            edge = ("its intervals reach into the set, the estimate does not" if self.reaches
                    else "no robot of the set lies within the intervals")  # fmt: skip
            lines.append(f"    {self.verdict} ({edge}); nearest robot: {self.estimate.describe()}")
            lines += [f"    - {reason}" for reason in self.reasons]
        return "\n".join(lines)


# ------------------------------------------------------------------------------------------------ predictions
class Predictor:
    """Batched predictions through the task's MuJoCo model: from each state, ``steps`` control steps under given
    commands, for any number of robots at once (one model copy per robot, one rollout call)."""

    def __init__(self, plant: Plant, parameters: Sequence[tuple[str, str]], steps: int) -> None:
        import mujoco
        import mujoco.rollout

        self._mujoco, self._rollout = mujoco, mujoco.rollout
        model = getattr(plant.physics.model, "ptr", plant.physics.model)  # type: ignore[attr-defined]
        if plant.state_dim != model.nq + model.nv:
            raise ValueError(f"{plant.task}: identification needs a plant whose state is [qpos, qvel]")
        self.model = copy.deepcopy(model)
        self.parameters = tuple(parameters)
        self.substeps = int(getattr(plant, "substeps", 1))
        self.steps = int(steps)
        self.nq, self.nv, self.nu = int(model.nq), int(model.nv), int(model.nu)
        self._copies: list[tuple[Any, ModelParameters]] = []
        full = mujoco.mjtState.mjSTATE_FULLPHYSICS
        data = mujoco.MjData(self.model)
        self._data = data
        self._template = np.empty(mujoco.mj_stateSize(self.model, full))
        mujoco.mj_getState(self.model, data, self._template, full)
        self._qpos_at = mujoco.mj_stateSize(self.model, mujoco.mjtState.mjSTATE_TIME)
        hinge = [int(model.jnt_qposadr[j]) for j in range(model.njnt) if int(model.jnt_type[j]) == 3]
        self.wrapped = np.array(hinge, dtype=np.intp)  # position entries a one-step error is wrapped on

    def _models(self, count: int) -> list[tuple[Any, ModelParameters]]:
        while len(self._copies) < count:
            twin = copy.deepcopy(self.model)
            self._copies.append((twin, ModelParameters(twin)))
        return self._copies[:count]

    def robot(self, z: FloatArray) -> Robot:
        return Robot(tuple((p, n, float(math.exp(v))) for (p, n), v in zip(self.parameters, z, strict=True)))

    def predict(self, zs: FloatArray, states: FloatArray, controls: FloatArray) -> FloatArray:
        """For each row of ``zs`` (k, p): the states (k, N, steps, n) reached from ``states`` (N, n) under
        ``controls`` (N, steps, nu)."""
        k, count = len(zs), len(states)
        models = self._models(k)
        for (_, parameters), z in zip(models, zs, strict=False):
            parameters.apply(self.robot(z))
        initial = np.tile(self._template, (count, 1))
        initial[:, self._qpos_at : self._qpos_at + self.nq + self.nv] = states
        control = np.repeat(controls, self.substeps, axis=1)
        every = [m for m, _ in models for _ in range(count)]
        out = self._rollout.rollout(every, self._data, np.tile(initial, (k, 1)), np.tile(control, (k, 1, 1)))[0]
        ends = out[:, self.substeps - 1 :: self.substeps, self._qpos_at : self._qpos_at + self.nq + self.nv]
        return ends.reshape(k, count, self.steps, self.nq + self.nv)

    def errors(self, predicted: FloatArray, reached: FloatArray) -> FloatArray:
        """predicted - reached, hinge angles wrapped (a recording may store them wrapped)."""
        diff = predicted - reached
        if len(self.wrapped):
            diff[..., self.wrapped] = (diff[..., self.wrapped] + math.pi) % (2 * math.pi) - math.pi
        return diff


# ------------------------------------------------------------------------------------------------ the fit
def fitted_parameters(plant: Plant, robots: UncertaintySet) -> tuple[list[tuple[str, str]], list[str]]:
    """The (parameter, element) pairs of the set a scale can change (a zero in the model stays zero), and the others
    with why."""
    model = copy.deepcopy(getattr(plant.physics.model, "ptr", plant.physics.model))  # type: ignore[attr-defined]
    values = ModelParameters(model)
    kept, fixed = [], []
    for scale in robots.resolved(model).scales:
        for name in scale.names:
            moved = values.values(Robot(((scale.parameter, name, 2.0),)))
            if any(not np.array_equal(moved[key], values.nominal[key]) for key in moved):
                kept.append((scale.parameter, name))
            else:
                fixed.append(f"{scale.parameter} of {name}: the model's value is zero, which no scale changes")
    return kept, fixed


def usable_rows(recording: Recording, dt: float, back: int, ahead: int) -> FloatArray:
    """The rows t whose transitions t -> t+ahead and commands t-back .. t come one control step apart each."""
    gaps = np.diff(recording.times)
    good = np.abs(gaps - dt) <= TIMING_TOLERANCE * dt  # good[i]: rows i and i+1 are one step apart
    rows = []
    for t in range(back, len(recording) - ahead):
        if good[t - back : t + ahead].all():
            rows.append(t)
    return np.array(rows, dtype=np.intp)


def identify(
    task: Task | str,
    recording: Recording,
    robots: UncertaintySet | None = None,
    *,
    seed: int = 0,
    max_delay: int | None = None,
    steps: int = 1,
    confidence: float = 0.95,
    progress: Callable[[str], None] | None = None,
) -> Identification:
    """The set's parameters, the delay and the robot's place against the set, from ``recording`` (raw [qpos, qvel]
    as read, commands as sent, one row per control step). ``robots``: the set (default: the task's own); ``seed``:
    the task's plant seed; ``max_delay``: the largest delay tried (default: the set's + 2); ``steps``: control steps
    per prediction."""
    started = time.perf_counter()
    task = get_task(task) if isinstance(task, str) else task
    robots = task.uncertainty if robots is None else robots
    if not robots.scales:
        raise ValueError(f"{task.name}: the set names no parameter to identify ({robots.describe()})")
    if not 0 < confidence < 1 or steps < 1:
        raise ValueError(f"confidence must lie in (0, 1) and steps be >= 1, got {confidence}, {steps}")
    plant = task.make_plant(seed)
    model = plant.physics.model  # type: ignore[attr-defined]
    robots = robots.resolved(model)
    if recording.states.shape[1] != plant.state_dim or recording.commands.shape[1] != plant.action_dim:
        raise ValueError(
            f"{task.name} has states of {plant.state_dim} and commands of {plant.action_dim} entries; the recording "
            f"has {recording.states.shape[1]} and {recording.commands.shape[1]}"
        )
    parameters, fixed = fitted_parameters(plant, robots)
    if not parameters:
        raise ValueError(f"{task.name}: no parameter of the set changes the model ({'; '.join(fixed)})")
    largest = robots.action_delay + EXTRA_DELAYS if max_delay is None else int(max_delay)
    if not 0 <= largest <= MAX_ACTION_DELAY:
        raise ValueError(f"max_delay must lie in [0, {MAX_ACTION_DELAY}], got {largest}")
    rows = usable_rows(recording, plant.dt, largest, steps)
    if len(rows) < 4 * len(parameters) + 2:
        raise ValueError(
            f"the recording has {len(rows)} usable transitions (states one control step of {plant.dt:g} s apart); "
            f"{4 * len(parameters) + 2} are the least for {len(parameters)} parameters"
        )
    predictor = Predictor(plant, parameters, steps)
    say = progress or (lambda _text: None)
    starts = recording.states[rows]
    reached = np.stack([recording.states[rows + j] for j in range(1, steps + 1)], axis=1)
    fits = []
    for delay in range(largest + 1):
        controls = np.stack([recording.commands[rows + j - delay] for j in range(steps)], axis=1)
        fits.append(_fit_delay(predictor, starts, controls, reached, delay, say))
    exact = [f for f in fits if f.exact]
    # Several delays that each reproduce the motion to rounding (a robot come to rest at an equilibrium, where every
    # delay and every factor predicts the same) are not told apart by their rounding: the smallest is the robot's.
    best = min(exact, key=lambda f: f.delay) if len(exact) > 1 else min(fits, key=lambda f: f.score)
    jacobian, residuals = best.jacobian, best.residuals
    result = _combinations(predictor, best.z, jacobian, residuals, confidence)
    z_hat, inside, reaches, reasons = _place(predictor, best.z, result, robots, best.delay)
    estimate = predictor.robot(z_hat)
    estimate = Robot(estimate.scales, best.delay, robots.state_noise, 0)
    say(f"delay {best.delay} chosen; {len(result.combinations)} combinations identifiable")
    return Identification(
        task=task.name,
        parameters=tuple(parameters),
        fixed=tuple(fixed),
        robots=robots,
        estimate=estimate,
        delay=best.delay,
        delays=tuple(DelayFit(f.delay, f.score, f.rms, tuple(np.exp(f.z).tolist())) for f in fits),
        combinations=result.combinations,
        unidentifiable=result.unidentifiable,
        singular_values=result.singular_values,
        noise=best.rms,
        transitions=len(rows),
        confidence=confidence,
        inside=inside,
        reaches=reaches,
        reasons=tuple(reasons),
        wall_time=time.perf_counter() - started,
        _z=tuple(z_hat.tolist()),
        _w=tuple(tuple(row) for row in result.rows.tolist()),
    )


@dataclass
class _DelayResult:
    delay: int
    z: FloatArray
    score: float
    rms: tuple[float, ...]
    jacobian: FloatArray
    residuals: FloatArray
    exact: bool = False  # the nominal model with this delay reproduces every step to rounding


def _fit_delay(
    predictor: Predictor,
    starts: FloatArray,
    controls: FloatArray,
    reached: FloatArray,
    delay: int,
    say: Callable[[str], None],
) -> _DelayResult:
    """The least-squares fit for one delay: weights from the nominal model's errors, then refitted once with the
    weights of the fit's own errors."""
    p = len(predictor.parameters)

    def errors(zs: FloatArray) -> FloatArray:
        return predictor.errors(predictor.predict(zs, starts, controls), reached[None])  # (k, N, steps, n)

    def spread(err: FloatArray) -> FloatArray:
        rms = np.sqrt(np.mean(err.reshape(-1, err.shape[-1]) ** 2, axis=0))
        # A robot read without noise (a simulated one) is fitted to rounding: a spread that small would make a
        # direction the motion barely shows (a pendulum's mass beside its armature) look certain. No robot's reads
        # are finer than READ_RESOLUTION, so the weights never assume they are.
        return np.maximum(rms, READ_RESOLUTION)

    z = np.zeros(p)
    nominal = errors(z[None])[0]
    if float(np.abs(nominal).max()) <= 1e-12 * max(1.0, float(np.abs(reached).max())):
        # Rounding alone: the nominal model with this delay reproduces every step (a simulated robot without noise).
        # That is the fit, exactly; weights from such errors would make any other factor look certain instead.
        rms = np.maximum(np.sqrt(np.mean(nominal.reshape(-1, nominal.shape[-1]) ** 2, axis=0)), 1e-300)
        say(f"delay {delay}: the nominal model reproduces the motion to rounding")
        jac = _central_jacobian(errors, z, np.full_like(rms, 1.0 / READ_RESOLUTION))  # weighted as any fit's
        return _DelayResult(
            delay, z, float(np.sum(np.log(rms))), tuple(rms.tolist()), jac, np.zeros(nominal.size), exact=True
        )
    weights = 1.0 / spread(nominal)
    for _ in range(2):
        w = weights

        def residual(x: FloatArray, w: FloatArray = w) -> FloatArray:
            return (errors(x[None])[0] * w).ravel()

        def jacobian(x: FloatArray, w: FloatArray = w) -> FloatArray:
            return _central_jacobian(errors, x, w)

        # scipy.optimize and .stats load on first use: npp-deploy imports this module, and they take a second to load
        from scipy import optimize

        fit = optimize.least_squares(
            residual, z, jac=jacobian, bounds=(-LOG_BOUND, LOG_BOUND), method="trf", tr_solver="exact",
            x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=100,
        )  # fmt: skip
        z = fit.x
        weights = 1.0 / spread(errors(z[None])[0])
    err = errors(z[None])[0]
    rms = spread(err)
    jac = _central_jacobian(errors, z, weights)
    score = float(np.sum(np.log(rms)))
    factors = ", ".join(f"{parameter} of {name} x{math.exp(v):.4f}" for (parameter, name), v in
                        zip(predictor.parameters, z, strict=True))  # fmt: skip
    say(f"delay {delay}: residual score {score:.3f} ({factors})")
    return _DelayResult(delay, z, score, tuple(rms.tolist()), jac, (err * weights).ravel())


def _central_jacobian(errors: Callable[[FloatArray], FloatArray], z: FloatArray, weights: FloatArray) -> FloatArray:
    """d(weighted errors)/dz by central differences, every perturbed model in one batched rollout."""
    p = len(z)
    steps = np.vstack([z + FD_STEP * np.eye(p), z - FD_STEP * np.eye(p)])
    err = errors(steps) * weights
    return ((err[:p] - err[p:]).reshape(p, -1) / (2 * FD_STEP)).T


@dataclass
class _Combinations:
    combinations: tuple[Combination, ...]
    rows: FloatArray  # (k, p): each combination's exponents
    unidentifiable: tuple[str, ...]
    singular_values: tuple[float, ...]


def _combinations(
    predictor: Predictor, z: FloatArray, jacobian: FloatArray, residuals: FloatArray, confidence: float
) -> _Combinations:
    names = predictor.parameters
    _, s, vt = np.linalg.svd(jacobian, full_matrices=False)
    null = s < NULL_TOLERANCE * s[0]
    basis, kernel = vt[~null], vt[null]  # rows: directions the data sees, and those it does not
    dof = max(len(residuals) - int((~null).sum()), 1)
    # The residuals are weighted by 1 / max(spread, READ_RESOLUTION): about 1 each where the reads are noisier than
    # that, below where the fit reproduces them more finely; the noise is taken as at least the resolution.
    s2 = max(float(residuals @ residuals) / dof, 1.0)
    covariance = s2 * (basis.T / s[~null] ** 2) @ basis  # (J'J)^+ on what the data sees
    from scipy import stats

    t = float(stats.t.ppf(0.5 + confidence / 2, dof))
    refs = _references(names, kernel)
    rows, labels = [], []
    if kernel.shape[0] == 0:
        rows = list(np.eye(len(names)))
    else:
        nref = kernel[:, refs].T  # (k, k): the kernel restricted to the references, invertible by choice
        for j in range(len(names)):
            if j in refs:
                continue
            row = np.zeros(len(names))
            row[j] = 1.0
            row[refs] = -np.linalg.solve(nref.T, kernel[:, j])
            rounded = np.round(row * 2) / 2
            rows.append(rounded if np.abs(rounded - row).max() < 0.02 else row)
    combinations = []
    for row in rows:
        row = np.asarray(row)
        seen = basis.T @ (basis @ row)  # its part the data sees (the rest changes no prediction)
        value = float(row @ z)
        half = t * math.sqrt(max(float(seen @ covariance @ seen), 0.0))
        exponents = tuple((p, n, float(e)) for (p, n), e in zip(names, row, strict=True) if abs(e) > 1e-9)
        labels.append(_label(exponents))
        low, high = math.exp(max(value - half, -700.0)), math.exp(min(value + half, 700.0))
        combinations.append(Combination(labels[-1], exponents, math.exp(value), low, high))
    unidentifiable = tuple(_why(names, direction, float(sv / s[0])) for direction, sv in zip(kernel, s[null],
                                                                                             strict=True))  # fmt: skip
    return _Combinations(tuple(combinations), np.array(rows).reshape(len(rows), len(names)), unidentifiable,
                         tuple(float(v) for v in s))  # fmt: skip


def _references(names: Sequence[tuple[str, str]], kernel: FloatArray) -> list[int]:
    """One parameter per unseen direction to write the combinations against: masses first, each one adding a rank."""
    if kernel.shape[0] == 0:
        return []
    order = sorted(range(len(names)), key=lambda j: (REFERENCE_ORDER.index(names[j][0]), j))
    refs: list[int] = []
    for j in order:
        trial = [*refs, j]
        if np.linalg.svd(kernel[:, trial], compute_uv=False).min() > 0.1 * np.abs(kernel).max():
            refs = trial
        if len(refs) == kernel.shape[0]:
            break
    if len(refs) < kernel.shape[0]:  # no well-conditioned choice in that order: the kernel's largest entries
        refs = sorted(np.argsort(-np.abs(kernel).max(axis=0))[: kernel.shape[0]].tolist())
    return refs


def _name(parameter: str, element: str) -> str:
    return f"{parameter}[{element}]"


def _label(exponents: Sequence[tuple[str, str, float]]) -> str:
    def term(p: str, n: str, e: float) -> str:
        e = abs(e)
        return _name(p, n) if abs(e - 1) < 1e-9 else f"{_name(p, n)}^{e:g}"

    top = " * ".join(term(*x) for x in exponents if x[2] > 0) or "1"
    bottom = " * ".join(term(*x) for x in exponents if x[2] < 0)
    return f"{top} / {bottom}" if bottom else top


def _why(names: Sequence[tuple[str, str]], direction: FloatArray, relative: float) -> str:
    """A direction the data cannot see, in words: which parameters, moved how, and why when it is the scaling."""
    direction = direction / direction[np.argmax(np.abs(direction))]
    moved = [(names[j], direction[j]) for j in range(len(names)) if abs(direction[j]) > 1e-3]
    parts = ", ".join(f"{_name(*pn)} x c^{e:.3g}" if abs(e - 1) > 1e-3 else f"{_name(*pn)} x c" for pn, e in moved)
    kinds = {pn[0] for pn, _ in moved}
    if len(moved) == len(names) and np.allclose([e for _, e in moved], 1.0, atol=1e-3):
        because = (
            "every inertia and every force of the model (gravity's through the masses, the motor's through the gear, "
            "the joints' through damping and friction) is scaled by c, so the accelerations, and the motion, are "
            "the same"
        )
    elif len(kinds) == 1 and len(moved) == 1:
        because = "the recording does not excite it"
    else:
        because = "their effects on the recorded motion cancel"
    return (
        f"{parts} for any c > 0 changes the one-step predictions by {relative:.1e} of the best-determined "
        f"direction: {because}; only the combinations above are determined"
    )


def _place(
    predictor: Predictor, z: FloatArray, result: _Combinations, robots: UncertaintySet, delay: int
) -> tuple[FloatArray, bool, bool, list[str]]:
    """The estimate moved along what the data cannot see to the set's nearest point; whether that reaches the set,
    whether the intervals do, and why not, naming each parameter and its range."""
    names = predictor.parameters
    ranges = {(s.parameter, n): (s.low, s.high) for s in robots.scales for n in s.names}
    low = np.log([ranges[pn][0] for pn in names])
    high = np.log([ranges[pn][1] for pn in names])
    rows = result.rows
    p = len(names)
    # min ||z + K a - y||^2 over a (free) and y in the set's box: the kernel's span K leaves every prediction as it is
    kernel = _kernel(rows, p)
    a_count = kernel.shape[1]
    matrix = np.hstack([kernel, -np.eye(p)])
    lower = np.concatenate([np.full(a_count, -np.inf), low])
    upper = np.concatenate([np.full(a_count, np.inf), high])
    from scipy import optimize

    solved = optimize.lsq_linear(matrix, -z, bounds=(lower, upper), method="bvls")
    z_hat = z + kernel @ solved.x[:a_count]
    outside = [j for j in range(p) if not low[j] - 1e-9 <= z_hat[j] <= high[j] + 1e-9]
    reasons = []
    if outside:
        for combination, row in zip(result.combinations, rows, strict=True):
            reach = (np.minimum(row * low, row * high).sum(), np.maximum(row * low, row * high).sum())
            if not reach[0] - 1e-9 <= math.log(combination.value) <= reach[1] + 1e-9:
                reasons.append(
                    f"{combination.label} = {combination.value:.4g} [{combination.low:.4g}, {combination.high:.4g}]; "
                    f"the set's robots have it in [{math.exp(reach[0]):.4g}, {math.exp(reach[1]):.4g}]"
                )
        if not reasons:
            reasons.append("each combination lies within what the set's robots reach, but no robot of the set has "
                           "them all together")  # fmt: skip
        for j in outside:
            parameter, name = names[j]
            lo, hi = ranges[parameter, name]
            reasons.append(f"the robot nearest the set with these combinations has {parameter} of {name} "
                           f"x{math.exp(z_hat[j]):.4g}, outside the set's [{lo:g}, {hi:g}]")  # fmt: skip
    if delay > robots.action_delay:
        reasons.append(f"action delay {delay} exceeds the set's 0..{robots.action_delay} control steps")
    inside = not reasons
    # do the intervals reach the set? a robot y in the box with every combination within its interval
    bounds_lo = np.log([c.low for c in result.combinations])
    bounds_hi = np.log([c.high for c in result.combinations])
    from scipy import optimize

    feasible = optimize.linprog(
        np.zeros(p), A_ub=np.vstack([rows, -rows]), b_ub=np.concatenate([bounds_hi, -bounds_lo]),
        bounds=list(zip(low, high, strict=True)), method="highs",
    )  # fmt: skip
    reaches = bool(feasible.status == 0) and delay <= robots.action_delay
    return z_hat, inside, reaches, reasons


def _kernel(rows: FloatArray, p: int) -> FloatArray:
    """The directions (columns) no combination sees: the null space of the combinations' rows."""
    if rows.shape[0] == 0:
        return np.eye(p)
    _, s, vt = np.linalg.svd(rows)
    rank = int((s > 1e-9 * s[0]).sum())
    return vt[rank:].T
