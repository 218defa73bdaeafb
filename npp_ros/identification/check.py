"""The check before a robot moves: the certified policy simulated at the identified robot, with a lower bound.

A certificate over a set of robots is an average over the set; the robot at hand is one of them (or beside them),
and may sit where the policy does worse than the average. Once the robot is identified (npp_ros.identification.fit),
the certified policy is rolled out at each point of the identified region (the estimate and the corners of the
combinations' intervals) from the same ``n`` s0 ~ rho, and each point's successes give a one-sided Clopper-Pearson
lower bound on that robot's success probability. Each point is bounded at level delta_g / (number of points), so
with probability at least 1 - delta_g every bound holds at once, and so does the worst one, whichever point it is.
The robot may move when the worst bound reaches ``p``.

What it does not cover: robots of the region between its points (a success rate need not be monotone in the
parameters; the corners and the estimate are a sample of the region, not a bound over it), and a model error the
set's parameters cannot express. The rollouts are those of npp_ros.tasks.rollout.rollout (the robot's model, its
delay and its noise by RobotEffects, the success criterion on the true states), run in lockstep over the s0 of one
robot with batched policy queries, which gives the same numbers as one at a time (tests/test_identification.py)
several times faster than npp_ros.run.evaluation's one-robot-per-rollout path.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from npp_ros.identification.fit import Identification
from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import FloatArray
from npp_ros.run.read import Run
from npp_ros.tasks.registry import Plant
from npp_ros.tasks.success import SuccessCriterion
from npp_ros.tasks.uncertainty import Robot, RobotEffects, as_robot

CHECK_S0_STREAM = (1 << 30) + 7  # the s0 stream of these checks: apart from a run's own s0 and its held-out ones


def clopper_pearson_lower(successes: int, trials: int, delta: float) -> float:
    """The one-sided lower confidence bound on a success probability at level ``delta``: P(p < bound) <= delta."""
    if not 0 <= successes <= trials or trials < 1 or not 0 < delta < 1:
        raise ValueError(f"need 0 <= successes <= trials, trials >= 1, 0 < delta < 1; got {successes}, {trials}, "
                         f"{delta}")  # fmt: skip
    if successes == 0:
        return 0.0
    from scipy import stats  # on first use, not at every importer's start

    return float(stats.beta.ppf(delta, successes, trials - successes + 1))


@dataclass(frozen=True)
class PointCheck:
    """The certified policy at one robot: its successes of ``trials`` and the lower bound on its success."""

    robot: Robot
    successes: int
    trials: int
    lower: float

    def record(self) -> dict[str, Any]:
        return {"robot": self.robot.describe(), "successes": self.successes, "trials": self.trials,
                "lower": self.lower}  # fmt: skip


@dataclass(frozen=True)
class MoveCheck:
    """The check before the robot moves: every point's result, the worst, and the verdict against ``p``."""

    points: tuple[PointCheck, ...]
    p: float
    delta_g: float
    accepted: bool
    wall_time: float

    @property
    def worst(self) -> PointCheck:
        return min(self.points, key=lambda point: point.lower)

    def summary(self) -> str:
        worst = self.worst
        verdict = "may move" if self.accepted else "must not move"
        lines = [
            f"the robot {verdict}: the certified policy's success at the worst of {len(self.points)} points is at "
            f"least {worst.lower:.3f} with confidence {1 - self.delta_g:g} (threshold {self.p:g}; "
            f"{worst.successes}/{worst.trials} at {worst.robot.describe()})"
        ]
        for pt in self.points:
            lines.append(f"  {pt.successes:>5}/{pt.trials:<5} lower {pt.lower:.3f}  {pt.robot.describe()}")
        return "\n".join(lines)

    def record(self) -> dict[str, Any]:
        return {"accepted": self.accepted, "p": self.p, "delta_g": self.delta_g, "worst": self.worst.record(),
                "points": [pt.record() for pt in self.points], "wall_time": self.wall_time}  # fmt: skip


def successes_at(
    plant: Plant,
    policy: NonparametricPolicy,
    criterion: SuccessCriterion,
    robot: Robot,
    states: FloatArray,
    horizon: int,
) -> FloatArray:
    """Whether the policy's rollout from each s0 on ``robot`` met ``criterion``: every s0 at once, each rollout on a
    clone of the plant made into the robot, reading its own noise (noise seed k for s0 k) through its own delay."""
    count = len(states)
    effects = [RobotEffects(Robot(robot.scales, robot.action_delay, robot.state_noise, k), plant.action_dim)
               for k in range(count)]  # fmt: skip
    trajectories = np.empty((count, horizon, plant.state_dim))
    act = policy.controller()
    with as_robot(plant, robot):
        plants = [plant.clone() for _ in range(count)]
        x = np.array([p.reset(s0) for p, s0 in zip(plants, states, strict=True)])
        for t in range(horizon):
            read = np.array([e.observe(row) for e, row in zip(effects, x, strict=True)])
            u = np.asarray(act(read), dtype=np.float64).reshape(count, plant.action_dim)
            trajectories[:, t] = x
            for k, p in enumerate(plants):
                p.step(effects[k].command(u[k]))
                x[k] = p.state()
    return np.array([criterion.met(trajectory) for trajectory in trajectories])


def check_initial_states(run: Run, n: int, seed: int = 0) -> FloatArray:
    """The ``n`` s0 ~ rho every point is checked from (the same ones at each, so the points compare fairly)."""
    rng = np.random.default_rng([int(run.metadata.seed), CHECK_S0_STREAM, int(seed)])
    return np.array([run.task.sample_initial_state(rng) for _ in range(n)])


def check_before_move(
    run: Run,
    region: Identification | Sequence[Robot],
    *,
    n: int = 200,
    p: float | None = None,
    delta_g: float = 0.05,
    seed: int = 0,
    progress: Callable[[int, int], None] | None = None,
) -> MoveCheck:
    """The certified policy of ``run`` (npp_ros.read_run) at each robot of ``region`` (an identification's
    :meth:`~Identification.region`, or robots given) from ``n`` s0 ~ rho: may the robot move? ``p``: the
    threshold (default: the run's own p); ``delta_g``: the level shared by the points."""
    started = time.perf_counter()
    criterion = run.task.success
    if criterion is None:
        raise ValueError(f"{run.task.name} states no success criterion: there is nothing to check a robot against")
    robots = region.region() if isinstance(region, Identification) else list(region)
    if not robots or n < 1 or not 0 < delta_g < 1:
        raise ValueError("a check needs at least one robot, n >= 1 and 0 < delta_g < 1")
    threshold = float(run.spec.p if p is None else p)
    policy = run.policy
    plant = run.task.make_plant(int(run.metadata.seed))
    states = check_initial_states(run, n, seed)
    horizon = int(run.metadata.horizon)
    level = delta_g / len(robots)
    points = []
    for index, robot in enumerate(robots):
        met = successes_at(plant, policy, criterion, robot, states, horizon)
        succeeded = int(met.sum())
        points.append(PointCheck(robot, succeeded, n, clopper_pearson_lower(succeeded, n, level)))
        if progress is not None:
            progress(index + 1, len(robots))
    worst = min(pt.lower for pt in points)
    return MoveCheck(tuple(points), threshold, delta_g, worst >= threshold, time.perf_counter() - started)
