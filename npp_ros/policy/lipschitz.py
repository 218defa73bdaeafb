"""The Lipschitz constant L, where it came from, and checks that it is not too small.

Every guarantee of NPP (Theorems 3.4, 4.1, Proposition 3.7) assumes V* is L-Lipschitz on the
states the run compares. With an L below the true slope, V_lb is not a lower bound and a
certificate is not a guarantee, so a run always carries its L with its provenance and warns
when it can see that L is too small.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from npp_ros.policy.dataset import Dataset, FloatArray

# data: fixed from a run's first expert answers; selected: a policy's own L (npp_ros.run.policy_lipschitz)
SOURCES = ("user", "paper", "lqr-analytic", "data", "selected")


class LipschitzWarning(UserWarning):
    """The L in use is below a slope the run can compute or estimate."""


@dataclass(frozen=True)
class LipschitzConstant:
    """L with its provenance, so a certificate can say which L it rests on."""

    value: float
    source: str
    detail: str = ""
    margin: float = 0.0  # relative margin already included in value (value = computed sup x (1 + margin))

    def __post_init__(self) -> None:
        if not np.isfinite(self.value) or self.value <= 0:
            raise ValueError(f"the Lipschitz constant must be finite and > 0, got {self.value!r}")
        if self.source not in SOURCES:
            raise ValueError(f"unknown Lipschitz source {self.source!r}; known: {', '.join(SOURCES)}")

    def describe(self) -> str:
        text = f"L = {self.value:.6g} ({self.source})"
        return f"{text}: {self.detail}" if self.detail else text


@dataclass(frozen=True)
class LipschitzCheck:
    """A slope the run could compute or estimate, compared with the L in use."""

    slope: float
    source: str
    lipschitz: float

    @property
    def ok(self) -> bool:
        return self.lipschitz >= self.slope

    def message(self) -> str:
        if self.ok:
            return f"L = {self.lipschitz:.6g} covers the {self.source} slope {self.slope:.6g}"
        return (
            f"L = {self.lipschitz:.6g} is below the {self.source} slope {self.slope:.6g}: "
            "V_lb is not a lower bound there and the certificate is not a guarantee"
        )


def check_lipschitz(lipschitz: float, slope: float, source: str, *, warn: bool = True) -> LipschitzCheck:
    check = LipschitzCheck(float(slope), source, float(lipschitz))
    if warn and not check.ok:
        warnings.warn(check.message(), LipschitzWarning, stacklevel=2)
    return check


def _pair_slopes(states: FloatArray, values: FloatArray, a: np.ndarray, b: np.ndarray) -> FloatArray:
    dist = np.sqrt(((states[a] - states[b]) ** 2).sum(axis=1))
    keep = dist > 1e-12
    return np.abs(values[a][keep] - values[b][keep]) / dist[keep]


def estimate_global(dataset: Dataset, *, max_points: int = 2000, seed: int = 0) -> float:
    """Largest observed slope |Q_i - Q_j| / |s_i - s_j| over a global sample of pairs.

    All pairs among up to ``max_points`` random points, plus consecutive pairs along every
    trajectory (the short pairs that see local slope). A data-based estimate can only
    under-estimate the true constant: use it to detect a too-small L, not to prove one.
    """
    n = len(dataset)
    if n < 2:
        raise ValueError("estimating L needs at least two data points")
    states, values = dataset.states, dataset.values
    rng = np.random.default_rng(seed)
    pick = np.sort(rng.choice(n, size=min(n, max_points), replace=False))
    a, b = np.triu_indices(len(pick), k=1)
    slopes = [_pair_slopes(states, values, pick[a], pick[b])]
    offsets = np.asarray(dataset.trajectory_offsets)
    starts = np.arange(n - 1)
    same_traj = np.searchsorted(offsets, starts, side="right") == np.searchsorted(offsets, starts + 1, side="right")
    slopes.append(_pair_slopes(states, values, starts[same_traj], starts[same_traj] + 1))
    return float(max(float(s.max(initial=0.0)) for s in slopes))


@dataclass(frozen=True)
class PairSlope:
    """The steepest slope between stored points at least ``floor`` apart, and the pair that shows it.

    Points are named (trajectory, step); ``pairs`` is how many pairs were compared, ``points`` how many points."""

    slope: float
    value_change: float
    distance: float
    first: tuple[int, int]
    second: tuple[int, int]
    floor: float
    pairs: int
    points: int

    def describe(self) -> str:
        (i, t), (j, u) = self.first, self.second
        return (
            f"{self.slope:.6g} = |dQ| {self.value_change:.4g} / |ds| {self.distance:.4g}, answer {i + 1} step {t} "
            f"against answer {j + 1} step {u}, over {self.pairs} pairs of {self.points} points at least "
            f"{self.floor:.3g} apart"
        )


def steepest_pair(
    dataset: Dataset,
    *,
    steps: int | None = None,
    floor_share: float,
    max_points: int = 2000,
    seed: int = 0,
) -> PairSlope | None:
    """The steepest |Q_i - Q_j| / |s_i - s_j| over pairs of points at least a floor apart (None: no such pair).

    ``steps``: only each trajectory's first ``steps`` points (None: all). The floor is ``floor_share`` x the
    median distance between the pairs compared: two states far closer than the data's own spacing say nothing
    about a slope a policy meets, and their quotient is any number (two upright states 1e-10 apart whose values
    differ by 1 give 1e10). All pairs among up to ``max_points`` points, drawn at random (seeded) beyond that.
    """
    bounds = np.asarray(dataset.trajectory_offsets)  # each trajectory's start, then the total size
    owner = np.repeat(np.arange(len(bounds) - 1), np.diff(bounds))
    step = np.arange(len(dataset)) - bounds[owner]
    keep = np.flatnonzero(step < steps) if steps is not None else np.arange(len(dataset))
    if len(keep) > max_points:
        keep = np.sort(np.random.default_rng(seed).choice(keep, size=max_points, replace=False))
    if len(keep) < 2:
        return None
    a, b = np.triu_indices(len(keep), k=1)
    a, b = keep[a], keep[b]
    states, values = dataset.states, dataset.values
    dist = np.sqrt(((states[a] - states[b]) ** 2).sum(axis=1))
    floor = float(floor_share * np.median(dist))
    apart = dist >= floor if floor > 0 else dist > 0
    if not apart.any():
        return None
    a, b, dist = a[apart], b[apart], dist[apart]
    change = np.abs(values[a] - values[b])
    best = int(np.argmax(change / dist))
    return PairSlope(
        slope=float(change[best] / dist[best]), value_change=float(change[best]), distance=float(dist[best]),
        first=(int(owner[a[best]]), int(step[a[best]])), second=(int(owner[b[best]]), int(step[b[best]])),
        floor=floor, pairs=len(a), points=len(keep),
    )  # fmt: skip
