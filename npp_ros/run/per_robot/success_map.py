"""Where in a set of robots the policy and its expert fail: their success per bin of each uncertain parameter.

A certificate over a set is an average over (s0, theta): it allows a policy that never succeeds on a corner of the
set. This table shows where that corner is, from draws already judged on the task's success criterion (a run's
episode log: the policy's checks and the expert's answers, each on its episode's robot; or the expert alone, before
a run, :mod:`npp_ros.run.per_robot.expert_map`). Each drawn parameter's range is split into equal bins, the delay
into its values, and every bin counts the successes of each and how many were judged there.

Parameters that enter the same term of the equation of motion move the motion together: with the mass of one body
only scaled (the pendulum), dividing its equation by that body's inertia leaves gravity's term as it is, so its
motion changes with gear/mass and damping/mass only, and those ratios are tabled too (exact where the joint has no
armature, which the mass does not scale). With several bodies (the cart-pole: cart and pole drawn apart) no ratio of
two scales fixes the motion, and none is tabled.

What the table does not say: a run's policy changes as its data grow, so its column counts the checks of every policy
the run held, not of the certified one; and a bin's share is a share of few draws (its count is beside it).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from npp_ros.tasks.uncertainty import Robot, UncertaintySet

DEFAULT_BINS = 4
RATIO_NUMERATORS = ("gear", "damping", "frictionloss")  # the scales a body's inertia divides (see the module text)
DELAY = "delay"


@dataclass(frozen=True)
class Tally:
    """Successes of the ones judged (a draw not judged, None in the log, is not counted)."""

    succeeded: int = 0
    judged: int = 0

    @property
    def rate(self) -> float:
        return self.succeeded / self.judged if self.judged else math.nan

    def add(self, outcome: bool | None) -> Tally:
        return self if outcome is None else Tally(self.succeeded + int(outcome), self.judged + 1)

    def text(self) -> str:
        if not self.judged:
            return "-"
        return f"{self.succeeded}/{self.judged} {self.rate:4.0%}"


@dataclass(frozen=True)
class Axis:
    """One direction the set is split along: a parameter of one element ("mass[pole]"), a ratio of two
    ("gear[torque]/mass[pole]") or the delay; ``edges`` are the bins' bounds (the delay: one bin per value)."""

    name: str
    edges: tuple[float, ...]
    ratio: bool = False

    @property
    def discrete(self) -> bool:
        return self.name == DELAY

    @property
    def bins(self) -> int:
        return len(self.edges) if self.discrete else len(self.edges) - 1

    def bin_of(self, value: float) -> int:
        if self.discrete:
            return round(value)
        inside = int(np.searchsorted(self.edges, value, side="right")) - 1
        return min(max(inside, 0), len(self.edges) - 2)  # the top edge (and rounding past an end) is the end bin

    def labels(self) -> list[str]:
        if self.discrete:
            return [f"{int(v)}" for v in self.edges]
        return [f"x[{lo:.3g}, {hi:.3g}{']' if k == len(self.edges) - 2 else ')'}"
                for k, (lo, hi) in enumerate(zip(self.edges[:-1], self.edges[1:], strict=True))]  # fmt: skip


@dataclass(frozen=True)
class AxisTable:
    """One axis's bins, each with the policy's and the expert's tally."""

    axis: Axis
    policy: tuple[Tally, ...]
    expert: tuple[Tally, ...]


@dataclass(frozen=True)
class SuccessMap:
    """The per-parameter table of one set's draws: what it was made of (``source``), its axes, the totals, and
    every draw's values (for the figure's scatter)."""

    source: str
    robots: str  # the set in words
    tables: tuple[AxisTable, ...]
    policy: Tally
    expert: Tally
    ratios_note: str
    points: tuple[tuple[dict[str, float], bool | None, bool | None], ...] = field(default=(), repr=False)

    def table(self) -> str:
        """The table for people: one row per bin, the policy's share in its checks and the expert's in its answers."""
        show_policy = self.policy.judged > 0
        header = (
            f"{'axis':<28} {'bin':<18} " + (f"{'policy (checks)':<20} " if show_policy else "") + "expert (answers)"
        )
        lines = [
            f"Where in the set the policy and the expert fail: {self.source}",
            f"  set: {self.robots}",
            "  total: "
            + (f"policy {self.policy.text()} of its checks; " if show_policy else "")
            + f"expert {self.expert.text()} of its answers",
            "",
            header,
            "-" * len(header),
        ]
        for part in self.tables:
            for k, label in enumerate(part.axis.labels()):
                name = part.axis.name if k == 0 else ""
                row = f"{name:<28} {label:<18} " + (f"{part.policy[k].text():<20} " if show_policy else "")
                lines.append(row + part.expert[k].text())
        lines += ["", self.ratios_note]
        worst = self.worst()
        if worst:
            lines.append(worst)
        return "\n".join(lines)

    def worst(self, least: int = 10) -> str:
        """The bin where the policy (else the expert) did worst among bins with at least ``least`` judged ("" where
        none did worse than the total)."""
        who = "policy" if self.policy.judged else "expert"
        found = [
            (getattr(part, who)[k].rate, part.axis.name, label, getattr(part, who)[k])
            for part in self.tables
            for k, label in enumerate(part.axis.labels())
            if getattr(part, who)[k].judged >= least
        ]
        total = getattr(self, who)
        if not found or min(item[0] for item in found) >= total.rate:
            return ""  # no bin below the total: nowhere worse to point at
        _, name, label, tally = min(found, key=lambda item: item[0])
        return f"  worst bin of the {who} (at least {least} judged): {name} {label}, {tally.text()}"

    def record(self) -> dict[str, Any]:
        """The map as plain values (JSON): each axis's bins with their counts."""
        return {
            "source": self.source,
            "robots": self.robots,
            "policy": [self.policy.succeeded, self.policy.judged],
            "expert": [self.expert.succeeded, self.expert.judged],
            "ratios": self.ratios_note,
            "axes": [
                {
                    "axis": part.axis.name,
                    "ratio": part.axis.ratio,
                    "bins": [
                        {"bin": label, "policy": [p.succeeded, p.judged], "expert": [e.succeeded, e.judged]}
                        for label, p, e in zip(part.axis.labels(), part.policy, part.expert, strict=True)
                    ],
                }
                for part in self.tables
            ],
        }


def robot_values(robot: Robot) -> dict[str, float]:
    """A robot's factor per element ("mass[pole]": 1.13) and its delay."""
    values = {f"{parameter}[{name}]": float(factor) for parameter, name, factor in robot.scales}
    values[DELAY] = float(robot.action_delay)
    return values


def ratio_pairs(robots: UncertaintySet, bodies: Sequence[str] | None = None) -> tuple[list[tuple[str, str]], str]:
    """The ratios worth tabling (numerator, denominator) and why: see the module text. ``bodies``: every body of
    the model (the world left out); a set that scales one body of several tables no ratio."""
    masses = [(s, name) for s in robots.scales if s.parameter == "mass" for name in s.names]
    if len(masses) != 1 or (bodies is not None and list(bodies) != [masses[0][1]]):
        many = len(masses) > 1 or (bodies is not None and len(bodies) > 1)
        why = "several bodies, drawn apart" if many else "no mass drawn"
        return [], f"  ratios: none tabled ({why}: no ratio of two scales fixes the motion)"
    if any(s.parameter == "armature" for s in robots.scales):
        return [], "  ratios: none tabled (the armature adds inertia the mass does not scale)"
    body = f"mass[{masses[0][1]}]"
    pairs = [(f"{s.parameter}[{name}]", body) for s in robots.scales if s.parameter in RATIO_NUMERATORS
             for name in s.names]  # fmt: skip
    if not pairs:
        return [], "  ratios: none tabled (only the mass is drawn)"
    names = ", ".join(f"{a}/{b}" for a, b in pairs)
    return pairs, (
        f"  ratios: one body ({masses[0][1]}) is scaled; dividing its equation of motion by its mass scale leaves "
        f"gravity's term as it is, so the motion changes with {names} (and the delay) only"
    )


def axes_of(robots: UncertaintySet, bins: int = DEFAULT_BINS, bodies: Sequence[str] | None = None) -> list[Axis]:
    """The axes of a set: each drawn element's range in ``bins`` equal bins, the identifiable ratios, the delay."""
    if bins < 1:
        raise ValueError(f"bins must be >= 1, got {bins}")
    ranges = {f"{s.parameter}[{name}]": (s.low, s.high) for s in robots.scales for name in s.names}
    axes = [Axis(key, tuple(np.linspace(lo, hi, bins + 1))) for key, (lo, hi) in ranges.items()]
    for top, bottom in ratio_pairs(robots, bodies)[0]:
        lo, hi = ranges[top][0] / ranges[bottom][1], ranges[top][1] / ranges[bottom][0]
        axes.append(Axis(f"{top}/{bottom}", tuple(np.linspace(lo, hi, bins + 1)), ratio=True))
    if robots.action_delay:
        axes.append(Axis(DELAY, tuple(float(d) for d in range(robots.action_delay + 1))))
    return axes


def value_on(axis: Axis, values: dict[str, float]) -> float:
    if axis.ratio:
        top, bottom = axis.name.split("/")
        return values[top] / values[bottom]
    return values[axis.name]


def success_map(
    robots: UncertaintySet,
    draws: Iterable[tuple[Robot, bool | None, bool | None]],
    source: str,
    *,
    bins: int = DEFAULT_BINS,
    bodies: Sequence[str] | None = None,
) -> SuccessMap:
    """The table of ``draws``, each (its robot, the policy's success, the expert's; None: not judged)."""
    axes = axes_of(robots, bins, bodies)
    policy = {axis.name: [Tally()] * axis.bins for axis in axes}
    expert = {axis.name: [Tally()] * axis.bins for axis in axes}
    total_policy, total_expert = Tally(), Tally()
    points = []
    for robot, policy_met, expert_met in draws:
        values = robot_values(robot)
        points.append((values, policy_met, expert_met))
        total_policy, total_expert = total_policy.add(policy_met), total_expert.add(expert_met)
        for axis in axes:
            k = axis.bin_of(value_on(axis, values))
            policy[axis.name][k] = policy[axis.name][k].add(policy_met)
            expert[axis.name][k] = expert[axis.name][k].add(expert_met)
    tables = tuple(AxisTable(axis, tuple(policy[axis.name]), tuple(expert[axis.name])) for axis in axes)
    return SuccessMap(
        source, robots.describe(), tables, total_policy, total_expert, ratio_pairs(robots, bodies)[1], tuple(points)
    )


def model_bodies(task: Any, seed: int) -> tuple[str, ...] | None:
    """The bodies of the task's model (None where its plant is no MuJoCo model)."""
    from npp_ros.tasks.uncertainty import model_elements, supports_robots

    plant = task.make_plant(seed)
    return model_elements(plant.physics.model)["body"] if supports_robots(plant) else None


def run_success_map(
    robots: UncertaintySet | None,
    episodes: Sequence[Any],
    source: str,
    *,
    bins: int = DEFAULT_BINS,
    bodies: Sequence[str] | None = None,
) -> SuccessMap | None:
    """The map of a run's episode log (rows with ``robot``, ``policy_success`` and ``expert_success``); None for a
    run on the exact model, which has one robot and nothing to split."""
    if robots is None or robots.empty:
        return None
    draws = [(Robot.from_record(row.robot), row.policy_success, row.expert_success) for row in episodes if row.robot]
    return success_map(robots, draws, source, bins=bins, bodies=bodies)
