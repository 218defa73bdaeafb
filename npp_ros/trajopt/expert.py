"""The optimizing expert: iLQR from a warm start, scored by replaying the plant's true rewards.

An expert request rolls a warm-start controller out, refines its actions with
:class:`~npp_ros.trajopt.ilqr.ILQR` on a smooth surrogate cost, and replays the result on the plant
for the task's own rewards: the values a dataset stores are always true rewards, never the
surrogate's.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike

from npp_ros.certificate.values import ValueBasis, theorem_34_condition
from npp_ros.policy.dataset import FloatArray, Trajectory
from npp_ros.trajopt.dynamics import PhysicsPlant
from npp_ros.trajopt.ilqr import ILQR, StageCost, TrajOptResult, check_time_budget


class SteppablePlant(Protocol):
    def reset(self, state: ArrayLike) -> FloatArray: ...

    def step(self, action: ArrayLike) -> float: ...

    def state(self) -> FloatArray: ...


def replay_rewards(
    plant: SteppablePlant,
    x0: ArrayLike,
    actions: FloatArray,
    continuation: Callable[[FloatArray], ArrayLike] | None = None,
    extra_steps: int = 0,
) -> tuple[FloatArray, FloatArray]:
    """Replay ``actions`` on the plant from x0; then ``extra_steps`` more under ``continuation``.

    Returns the raw states x_0 .. x_{T-1} of the replayed actions and every reward, the task's own
    (``plant.step``). The raw state is ``plant.raw_state()`` where the plant stores another
    representation.
    """
    read = getattr(plant, "raw_state", plant.state)
    horizon = len(actions)
    states = np.empty((horizon, len(np.asarray(x0))))
    rewards = np.empty(horizon + extra_steps)
    plant.reset(x0)
    for t in range(horizon):
        states[t] = read()
        rewards[t] = plant.step(actions[t])
    if extra_steps and continuation is None:
        raise ValueError("extra_steps needs a continuation policy")
    for t in range(horizon, horizon + extra_steps):
        rewards[t] = plant.step(continuation(read()))
    return states, rewards


def return_to_go(rewards: FloatArray) -> FloatArray:
    """Q_t = sum_{k>=t} r_k."""
    return np.cumsum(rewards[::-1])[::-1].copy()


def window_values(rewards: FloatArray, window: int) -> FloatArray:
    """Q_t = sum_{k=t}^{t+window-1} r_k, for every t with a full window (exact for 0/1 rewards)."""
    sums = np.concatenate([[0.0], np.cumsum(rewards)])
    return sums[window:] - sums[:-window]


def replay_return_to_go(plant: SteppablePlant, x0: ArrayLike, actions: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Replay ``actions`` on the plant from x0: raw states x_0 .. x_{T-1} and Q_t = sum_{k>=t} r_k.

    Q_0 is the trajectory's true return.
    """
    states, rewards = replay_rewards(plant, x0, actions)
    return states, return_to_go(rewards)


@dataclass(frozen=True)
class ExpertSolution:
    """What one expert request produced: the dataset trajectory and how it was found."""

    trajectory: Trajectory  # stored states, actions, Q_t (true return-to-go)
    optimization: TrajOptResult
    raw_states: FloatArray  # the plant's [qpos, qvel] as replayed
    kept_warm_start: bool = False  # the warm start's true return beat the optimised one

    @property
    def expert_return(self) -> float:
        return float(self.trajectory.values[0])


VALUE_MODES = ("return-to-go", "window")
DEFAULT_VALUES = "window"  # one value per visited state, as the lqr expert's: what every optimizer expert stores
STOP_MODES = ("iterations", "time")
DEFAULT_STOP = "iterations"  # a request ends by convergence or max_iterations: the same answer on any machine
DEFAULT_TIME_BUDGET_S = 5.0  # stop = "time": wall-clock seconds per request (a task may set its own)
# stop = "iterations": the time budget as a guard, several times the slowest request it can stop that npp-bench
# --only experts measured (a pendulum request's 8 s at a load average of 7; the acrobot's polish is never cut).
DEFAULT_GUARD_S = 60.0
STOP_HELP = (
    "what ends an iLQR expert's request: iterations (convergence or max_iterations: the same answer on any machine; "
    "the default) or time (within the time budget: fewer iterations on a loaded machine, not reproducible)"
)
TIME_BUDGET_HELP = (
    f"seconds per expert request (iLQR experts): a guard under --expert-stop iterations (default {DEFAULT_GUARD_S:g}), "
    f"the budget iLQR works within under time (default {DEFAULT_TIME_BUDGET_S:g}); default: a task file's [expert] "
    "time_budget, else those"
)


def check_stop(stop: str) -> str:
    """What ends a request: ``iterations`` (reproducible) or ``time`` (a wall-clock budget, machine-dependent)."""
    if stop not in STOP_MODES:
        raise ValueError(f"stop must be one of {', '.join(STOP_MODES)}; got {stop!r}")
    return stop


class OptimizingExpert:
    """An expert oracle from a plant, a smooth cost, a warm-start controller and a state map.

    Each request: roll the warm-start controller out from s0 and replay its actions on the plant,
    refine with :class:`ILQR` in what is left of ``time_budget`` seconds (see
    :meth:`optimizer_budget`), then replay the optimised actions on the plant for the task's true
    rewards, keeping the warm start's actions if they score better. Q_0 is the trajectory's H-step
    return in both value modes; they differ for t > 0:

    - ``"return-to-go"``: Q_t = r_t + ... + r_{H-1}. Q then depends on the time left, not only
      on the state: a state held to the end (the pendulum upright) has Q = H - t, so one state
      carries many values and no finite L fits the data.
    - ``"window"``: Q_t = r_t + ... + r_{t+H-1}, the H-step value of s_t, the trajectory
      continued past H by the warm-start controller. This is the stationary convention of the
      lqr expert (V*(s_t) = H - J*(s_t)).

    Stored states are ``represent(raw state)``.

    What ends a request (``stop``): under ``"iterations"`` (the default) iLQR runs to convergence
    or ``max_iterations``, so the same request gives the same answer bit for bit on any machine;
    ``time_budget`` (default :data:`DEFAULT_GUARD_S`) is then only a guard against a runaway
    request. Under ``"time"`` iLQR works within ``time_budget`` (default ``time_stop_budget_s``),
    so a loaded machine answers with fewer iterations. Either way a request the budget stopped is
    counted in ``budget_stops``: its answer depends on the machine's speed.

    The time budget covers the whole request and is wall-clock, so it is met when the machine
    leaves iLQR at least ``min_optimizer_share`` of it; on a slower machine iLQR still gets that
    share and ``min_iterations`` iterations, and the request overruns by them. No timing carries
    over from one request to the next.
    """

    min_optimizer_share = 0.2  # of time_budget: iLQR's at least, whatever the warm start and replays take
    min_iterations = 1  # iLQR iterations the budget cannot cut (convergence and max_iterations can)
    time_stop_budget_s = DEFAULT_TIME_BUDGET_S  # the budget under stop = "time" when none is given

    def __init__(
        self,
        plant: PhysicsPlant,
        cost: StageCost,
        warm_start: Callable[[FloatArray], ArrayLike],
        represent: Callable[[FloatArray], FloatArray],
        *,
        horizon: int,
        time_budget: float | None = None,
        max_iterations: int = 50,
        values: str = DEFAULT_VALUES,
        stop: str = DEFAULT_STOP,
    ) -> None:
        if values not in VALUE_MODES:
            raise ValueError(f"values must be one of {', '.join(VALUE_MODES)}; got {values!r}")
        if isinstance(horizon, bool) or not isinstance(horizon, (int, np.integer)) or horizon < 1:
            raise ValueError(f"horizon must be an integer >= 1, got {horizon!r}")
        self.values = values
        self.horizon = int(horizon)
        self.stop = check_stop(stop)
        if time_budget is None:
            time_budget = self.time_stop_budget_s if stop == "time" else DEFAULT_GUARD_S
        self.time_budget = check_time_budget(time_budget)
        self.max_iterations = int(max_iterations)
        self.plant = plant
        self.cost = cost
        self.optimizer = ILQR(plant, cost)
        self.warm_start = warm_start
        self.represent = represent
        self.max_slope_seen = 0.0
        self.max_transition_norm = 0.0
        self.requests = 0
        self.budget_stops = 0  # requests the time budget stopped (their answers depend on the machine's speed)
        self.task = "mujoco"
        self.reward_lipschitz = math.inf  # a task that knows its reward's slope says so
        self.reward_lipschitz_detail = "not known for this task"
        self.no_lipschitz_bound = ""  # a task whose true values are discontinuous in the state says why

    @property
    def clock(self) -> Callable[[], float]:
        """The clock the request's phases and iLQR's budget are read on (a test may slow it)."""
        return self.optimizer.clock

    @clock.setter
    def clock(self, clock: Callable[[], float]) -> None:
        self.optimizer.clock = clock

    def solve(self, initial_state: ArrayLike, horizon: int | None = None) -> ExpertSolution:
        """One request. The answer is never worse than the warm start under the true reward: when
        the surrogate's optimum replays to a lower H-step return, the warm start's actions are
        kept (with W_x from a backward pass at them) and ``kept_warm_start`` says so.

        The plant is replayed twice: the warm start's H actions (before iLQR, so their time is
        known when iLQR's budget is set), and the optimised actions, in window mode continued by
        the warm-start controller for H - 1 more steps. The first H rewards of that continued
        replay are the H-step return compared with the warm start's (a replay starts from a reset
        plant, so its first H steps do not depend on what follows them).
        """
        x0 = self.plant.check_state(initial_state, "requested state")
        steps = self.horizon if horizon is None or horizon == 0 else int(horizon)
        window = self.values == "window"
        start = self.clock()
        warm = self.warm_actions(x0, steps)
        rolled = self.clock()
        warm_raw, warm_rewards = replay_rewards(self.plant, x0, warm)
        replayed = self.clock()
        result = self.optimizer.solve(
            x0,
            steps,
            time_budget=self.optimizer_budget(rolled - start, replayed - rolled, replayed - start),
            initial_actions=warm,
            max_iterations=self.max_iterations,
            min_iterations=self.min_iterations,
        )
        stopped_by_budget = result.timed_out  # before a kept warm start replaces the result: it decided that too
        extra = steps - 1 if window else 0
        raw, rewards = replay_rewards(self.plant, x0, result.actions, self.warm_start if window else None, extra)
        kept_warm_start = float(warm_rewards.sum()) > float(rewards[:steps].sum())
        if kept_warm_start:
            result = self.optimizer.solve(x0, steps, time_budget=60.0, initial_actions=warm, max_iterations=0)
            if window:
                raw, rewards = replay_rewards(self.plant, x0, result.actions, self.warm_start, extra)
            else:  # result.actions == warm (the rollout clamped them; clamping again changes nothing)
                raw, rewards = warm_raw, warm_rewards
        values = window_values(rewards, steps) if window else return_to_go(rewards)
        self.max_slope_seen = max(self.max_slope_seen, result.max_value_slope)
        self.max_transition_norm = max(self.max_transition_norm, result.max_transition_norm)
        self.requests += 1
        self.budget_stops += stopped_by_budget
        # Q_0 is the replayed H-step return in both value modes: the expert's own return at s0 (oracle mode).
        trajectory = Trajectory(
            self.represent(raw), result.actions.copy(), values, expert_return=float(values[0]), gains=result.gains
        )
        return ExpertSolution(trajectory, result, raw, kept_warm_start)

    def warm_actions(self, x0: FloatArray, steps: int) -> FloatArray:
        """The ``steps`` actions iLQR starts from: ``warm_start`` rolled out from ``x0`` (clamped).

        A subclass that plans its start another way overrides this; ``warm_start`` still continues
        every replay past H (window values), and ``optimizer_budget`` reads this call's seconds as
        the controller's rollout time.
        """
        _, actions = self.optimizer.dynamics.rollout(x0, steps, policy=self.warm_start)
        return actions

    def optimizer_budget(self, rollout_seconds: float, replay_seconds: float, spent: float) -> float:
        """iLQR's seconds: the budget less what this request has spent and its replay still to come.

        The replay to come is predicted from this request's own, at this moment's machine load: the
        optimised actions' replay takes the warm start's (``replay_seconds``, H plant steps); window
        mode's H - 1 continued steps add as much plus the controller, whose time is within the warm
        start's rollout (``rollout_seconds``, controller and model steps). Never below
        ``min_optimizer_share`` of the budget, so a loaded machine gets a shorter optimisation, not
        none. (A kept warm start's backward pass and replay are not predicted: they are rare.)
        """
        to_come = replay_seconds + (replay_seconds + rollout_seconds if self.values == "window" else 0.0)
        return max(self.time_budget - spent - to_come, self.min_optimizer_share * self.time_budget)

    def trajectory(self, initial_state: ArrayLike, horizon: int | None = None) -> Trajectory:
        return self.solve(initial_state, horizon).trajectory

    def slope_floor(self) -> float:
        """max |W_x| over every request so far (the surrogate cost-to-go's slope; see TrajOptResult).

        A floor for L: the optimizer's own value already rises this steeply along its trajectories.
        It is not a bound (a slope seen is never more than the slope there is).
        """
        return self.max_slope_seen

    def value_basis(self) -> ValueBasis:
        """What the stored values are; a tail bound only where they are a function of the state.

        ``window``: Q at a requested s0 is the replayed H-step return of the expert's actions, so a
        claim about the expert's H-step return from s0 needs no tail (0). ``return-to-go``: the
        stored values depend on the time left, so no tail is offered and rollout mode refuses.
        """
        what = (
            f"the {self.task} iLQR expert's own H-step return (H = {self.horizon}): a local optimum of a "
            "smooth surrogate, not V*_H (Appendix B's setting)"
        )
        if self.values == "window":
            return ValueBasis(
                what, lambda s0: 0.0, "Q_0 is the expert's replayed H-step return from s0",
                no_lipschitz_bound=self.no_lipschitz_bound,
            )  # fmt: skip
        return ValueBasis(
            what, None, "return-to-go values depend on the time left, not only on the state",
            no_lipschitz_bound=self.no_lipschitz_bound,
        )  # fmt: skip

    def theorem_34_condition(self, lipschitz: float) -> tuple[bool, str]:
        """Theorem 3.4's condition with L_f = the largest |A_t| seen on the expert's trajectories."""
        if self.requests == 0:
            return False, "Theorem 3.4's condition is unchecked: no expert trajectory yet gives L_f"
        where = f"L_f seen on {self.requests} expert trajectories; L_r {self.reward_lipschitz_detail}"
        return theorem_34_condition(lipschitz, 1.0, self.max_transition_norm, self.reward_lipschitz, where)


def time_trajectories(
    solve: Callable[[FloatArray], object], initial_states: Sequence[ArrayLike] | FloatArray
) -> FloatArray:
    """Seconds per request of ``solve(s0)`` (wall clock, one request at a time), for benchmarks."""
    out = np.empty(len(initial_states))
    for i, s0 in enumerate(initial_states):
        tick = time.perf_counter()
        solve(np.asarray(s0, dtype=np.float64))
        out[i] = time.perf_counter() - tick
    return out
