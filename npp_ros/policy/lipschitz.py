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

SOURCES = ("user", "paper", "lqr-analytic", "data")  # data: fixed from a run's first expert answers


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
