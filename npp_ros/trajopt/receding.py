"""Receding-horizon planners for an expert whose single iLQR over the whole horizon finds nothing.

One iLQR over a long horizon from u = 0 cannot swing an underactuated robot up: its derivatives
through seconds of a chaotic swing lead nowhere. Short windows can: optimise ``window`` steps from
where the committed actions left the plant, commit the first ``commit`` of them, shift the rest as
the next window's warm start, and go on to the horizon. A window is optimised by one of:

- ``"receding"``: ``window_iterations`` iLQR iterations on the expert's smooth cost;
- ``"sampling"``: predictive sampling (as MuJoCo MPC's planner): ``samples`` - 1 perturbations of
  the shifted plan, piecewise linear between ``knots`` knots, rolled out at once, and the
  cheapest of them and the plan itself kept, ``sample_rounds`` times; then ``window_iterations``
  iLQR iterations from it.

The cost is the expert's own (its StageCost), nothing else: the planner knows no task's physics.
When a plan does not do the task (a judge, e.g. a task's success criterion, says no), up to
``restarts`` more plans are made (sampling with the next random stream, iLQR windows half again
as long), and the first that does the task is taken, else the one with the best true return.

Every window stops by its iteration cap or convergence, every sample comes from a random stream
seeded by the run's seed and the request's start state, so a plan depends on (seed, s0) alone,
bit for bit, on any machine. The expert then polishes the plan over the whole horizon
(:class:`~npp_ros.trajopt.expert.OptimizingExpert`), whose last backward pass gives the answer's
feedback gains.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from npp_ros.policy.dataset import FloatArray
from npp_ros.trajopt.dynamics import PhysicsPlant
from npp_ros.trajopt.expert import OptimizingExpert, replay_rewards
from npp_ros.trajopt.ilqr import ILQR, StageCost

PLANNERS = ("ilqr", "receding", "sampling")
DEFAULT_PLANNER = "ilqr"  # one iLQR over the whole horizon, from the warm start: what an expert did before planners
WINDOW_GUARD_S = 600.0  # a window's time budget: a guard never reached by the iteration caps below


class SettingError(ValueError):
    """A planner setting out of its range; ``key`` names it."""

    def __init__(self, key: str, problem: str) -> None:
        super().__init__(f"{key} {problem}")
        self.key, self.problem = key, problem


@dataclass(frozen=True)
class PlannerSettings:
    """How an expert plans before its iLQR over the whole horizon (see the module's docstring)."""

    planner: str = DEFAULT_PLANNER
    window: int = 200  # steps per window
    commit: int = 25  # steps of each window kept before the next is planned
    window_iterations: int = 5  # iLQR iterations per window
    samples: int = 32  # rollouts per sampling round, the shifted plan among them
    knots: int = 10  # knots of a sampled perturbation over a window
    noise: float = 0.3  # a perturbation knot's standard deviation, as a fraction of half the control range
    sample_rounds: int = 1  # sampling rounds per window
    restarts: int = 2  # more plans when a plan does not do the task

    def __post_init__(self) -> None:
        if self.planner not in PLANNERS:
            raise SettingError("planner", f"must be one of {', '.join(PLANNERS)}, got {self.planner!r}")
        for key, least in (("window", 1), ("commit", 1), ("samples", 2), ("knots", 1), ("sample_rounds", 1),
                           ("window_iterations", 0), ("restarts", 0)):  # fmt: skip
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
                raise SettingError(key, f"must be an integer >= {least}, got {value!r}")
        if self.commit > self.window:
            raise SettingError("commit", f"must be at most window ({self.window}), got {self.commit}")
        noise = self.noise
        if isinstance(noise, bool) or not isinstance(noise, (int, float)) or not math.isfinite(noise) or noise <= 0:
            raise SettingError("noise", f"must be a finite number > 0, got {noise!r}")

    @staticmethod
    def planners_using(key: str) -> tuple[str, ...]:
        """The planners a setting applies to (a file that sets it for another planner is refused)."""
        if key == "planner":
            return PLANNERS
        return ("sampling",) if key in SAMPLING_KEYS else ("receding", "sampling")

    def describe(self) -> str:
        """The planner and the keys it uses, as a task file writes them."""
        if not self.plans:
            return 'planner = "ilqr" (no plan: one iLQR from the warm start)'
        used = [key for key in PLANNER_KEYS if key != "planner" and self.planner in self.planners_using(key)]
        return f'planner = "{self.planner}": ' + ", ".join(f"{key} {getattr(self, key):g}" for key in used)

    @property
    def plans(self) -> bool:
        """Whether requests are planned by windows (else one iLQR over the horizon, from the warm start)."""
        return self.planner != "ilqr"


PLANNER_KEYS = tuple(f.name for f in fields(PlannerSettings))
SAMPLING_KEYS = ("samples", "knots", "noise", "sample_rounds")


class BatchRollouts:
    """Open-loop rollouts of many action sequences from one state, in one ``mujoco.rollout`` call.

    Each starts from a reset MjData at the state, as :meth:`MujocoDynamics.rollout` does, and steps on the
    plant's own control step: ``substeps`` MuJoCo steps per action, the action held (a plan scored at one
    model step per action would be scored on a clock k times slower than the plant's). A row's states are
    that rollout's, bit for bit.
    """

    def __init__(self, model: Any, state_dim: int, substeps: int = 1) -> None:
        import mujoco
        from mujoco import rollout as mj_rollout

        self._mujoco, self._rollout = mujoco, mj_rollout
        self.model = model
        self.data = mujoco.MjData(model)
        spec = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)
        self._at = int(mujoco.mj_stateSize(model, int(mujoco.mjtState.mjSTATE_TIME)))
        self._template = np.empty(mujoco.mj_stateSize(model, spec))
        mujoco.mj_getState(model, self.data, self._template, spec)
        self._control_spec = int(mujoco.mjtState.mjSTATE_CTRL)
        self.state_dim = int(state_dim)
        self.substeps = int(substeps)  # MuJoCo steps per action, the action held

    def __call__(self, x0: FloatArray, actions: FloatArray) -> FloatArray:
        """States (N, T + 1, n) of the N action sequences (N, T, m) from x0."""
        count, steps, _ = actions.shape
        n, at, k = self.state_dim, self._at, self.substeps
        initial = np.repeat(self._template[None, :], count, axis=0)
        initial[:, at : at + n] = x0
        held = np.ascontiguousarray(np.repeat(actions, k, axis=1))  # each action held for its k MuJoCo steps
        out, _ = self._rollout.rollout(
            self.model, self.data, initial, held, control_spec=self._control_spec, nstep=steps * k
        )
        states = np.empty((count, steps + 1, n))
        states[:, 0] = x0
        states[:, 1:] = out[:, k - 1 :: k, at : at + n]  # the state after each control step's last MuJoCo step
        return states


def window_costs(cost: StageCost, states: FloatArray, actions: FloatArray) -> FloatArray:
    """Each rollout's sum_t c(u_t) + s(x_{t+1}), as iLQR totals its trajectory's cost."""
    count, steps, m = actions.shape
    post = states[:, 1:].reshape(count * steps, -1)
    state_values = getattr(cost, "state_values", None)
    s = state_values(post) if state_values is not None else cost.state_terms(post)[0]
    c, _, _ = cost.control_terms(actions.reshape(count * steps, m))
    return (s.reshape(count, steps) + c.reshape(count, steps)).sum(axis=1)


class RecedingPlanner:
    """An H-step plan from windows (see the module's docstring); ``plan`` makes one."""

    def __init__(
        self, optimizer: ILQR, settings: PlannerSettings, controller: Callable[[FloatArray], ArrayLike] | None = None
    ) -> None:
        self.optimizer = optimizer
        self.settings = settings
        self.controller = controller  # extends each window's guess past the shifted plan (None: zeros)
        dynamics = optimizer.dynamics
        self.rollouts = BatchRollouts(dynamics.model, dynamics.state_dim, dynamics.substeps)
        self.lower, self.upper = dynamics.lower, dynamics.upper
        # A perturbation's scale per control: half its range (1 for an unlimited control).
        self.scale = np.where(np.isfinite(self.upper - self.lower), (self.upper - self.lower) / 2, 1.0)
        self.window_budget_stops = 0  # windows the guard stopped (never, unless a step hangs)

    def plan(
        self, x0: FloatArray, steps: int, rng: np.random.Generator | None, window: int | None = None
    ) -> FloatArray:
        """The plan's ``steps`` actions from x0; sampled windows draw from ``rng``."""
        settings, dynamics = self.settings, self.optimizer.dynamics
        window = settings.window if window is None else int(window)
        width = self.optimizer.action_dim
        actions = np.zeros((steps, width))
        state = np.asarray(x0, dtype=np.float64)
        guess = self._continued(state, np.zeros((0, width)), window)
        for t in range(0, steps, settings.commit):
            if settings.planner == "sampling":
                assert rng is not None
                guess = self._sample(state, guess, rng)
            if settings.window_iterations:
                best = self.optimizer.solve(
                    state, window, time_budget=WINDOW_GUARD_S, initial_actions=guess,
                    max_iterations=settings.window_iterations,
                )  # fmt: skip
                self.window_budget_stops += best.timed_out
                guess = best.actions
            n = min(settings.commit, steps - t)
            actions[t : t + n] = guess[:n]
            state = dynamics.rollout(x0, t + n, actions=actions[: t + n])[0][-1]
            guess = self._continued(state, guess[n:], window)
        return actions

    def _continued(self, state: FloatArray, kept: FloatArray, window: int) -> FloatArray:
        """A window's guess: ``kept`` (the last plan's uncommitted actions), then the controller's."""
        width = self.optimizer.action_dim
        if self.controller is None:
            return np.concatenate([kept, np.zeros((window - len(kept), width))])
        counter = iter(range(window))

        def act(x: FloatArray) -> ArrayLike:
            t = next(counter)
            return kept[t] if t < len(kept) else self.controller(x)

        return self.optimizer.dynamics.rollout(state, window, policy=act)[1]

    def _sample(self, state: FloatArray, nominal: FloatArray, rng: np.random.Generator) -> FloatArray:
        """The cheapest of the plan and its sampled perturbations, ``sample_rounds`` times."""
        settings = self.settings
        window, width = nominal.shape
        knots = np.linspace(0.0, window - 1, settings.knots + 1)
        grid = np.arange(window)
        for _ in range(settings.sample_rounds):
            kicks = rng.standard_normal((settings.samples - 1, len(knots), width)) * settings.noise * self.scale
            perturbations = np.empty((settings.samples - 1, window, width))
            for i in range(settings.samples - 1):
                for j in range(width):
                    perturbations[i, :, j] = np.interp(grid, knots, kicks[i, :, j])
            candidates = np.concatenate([nominal[None], np.clip(nominal[None] + perturbations, self.lower, self.upper)])
            costs = window_costs(self.optimizer.cost, self.rollouts(state, candidates), candidates)
            nominal = candidates[int(np.argmin(costs))]
        return nominal


class PlanningExpert(OptimizingExpert):
    """:class:`OptimizingExpert` whose iLQR over the whole horizon starts from a receding-horizon plan.

    With ``settings.planner == "ilqr"`` it is OptimizingExpert itself (the warm-start controller's
    rollout is the start). Otherwise a request plans (:class:`RecedingPlanner`, up to
    ``settings.restarts`` more plans while ``judge`` says a plan's replayed raw states do not do the
    task), then runs OptimizingExpert's own pipeline from the plan: at most ``max_iterations`` iLQR
    iterations over the whole horizon (under ``stop = "iterations"`` the time budget is a guard),
    the replays for the true rewards, and the plan kept when the polish scores worse. The answer's
    gains come from that last iLQR's backward pass, at the actions it returns.
    """

    def __init__(
        self,
        plant: PhysicsPlant,
        cost: StageCost,
        warm_start: Callable[[FloatArray], ArrayLike],
        represent: Callable[[FloatArray], FloatArray],
        *,
        settings: PlannerSettings,
        seed: int,
        judge: Callable[[FloatArray], bool] | None = None,
        **options: Any,
    ) -> None:
        super().__init__(plant, cost, warm_start, represent, **options)
        self.settings = settings
        self.seed = int(seed)
        self.judge = judge
        self.planner = RecedingPlanner(self.optimizer, settings, warm_start) if settings.plans else None
        self.plans_made = 0  # plans over every request (restarts included)

    def warm_actions(self, x0: FloatArray, steps: int) -> FloatArray:
        """The plan's actions, clamped as a rollout applies them (OptimizingExpert's start without a planner)."""
        if self.planner is None:
            return super().warm_actions(x0, steps)
        best, best_return = None, -math.inf
        for attempt in range(self.settings.restarts + 1):
            window = self.settings.window
            if self.settings.planner == "receding":  # iLQR windows are deterministic: another try looks further
                window = round(window * 1.5**attempt)
            plan = self.planner.plan(x0, steps, self.random_stream(x0, attempt), window)
            self.plans_made += 1
            raw, rewards = replay_rewards(self.plant, x0, plan)
            if self.judge is not None and self.judge(raw):
                best = plan
                break
            if float(rewards.sum()) > best_return:
                best, best_return = plan, float(rewards.sum())
        assert best is not None
        _, actions = self.optimizer.dynamics.rollout(x0, steps, actions=best)
        return actions

    def random_stream(self, x0: FloatArray, attempt: int) -> np.random.Generator:
        """The samples of one plan: seeded by the run's seed, the plan's attempt and s0's bytes."""
        words = np.frombuffer(np.ascontiguousarray(x0, dtype=np.float64).tobytes(), dtype=np.uint32)
        return np.random.default_rng(np.random.SeedSequence([self.seed, attempt, *words.tolist()]))
