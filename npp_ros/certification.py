"""Theorem 4.1: when Algorithm 1 may stop, and what it then certifies.

(i)  no new data for n >= ln(1/delta) / (1 - p) consecutive episodes
     => w.p. >= 1 - delta, P_{s~rho}[V*(s) - V^pi(s) <= epsilon] >= p.
(ii) mean surrogate gap over the last n episodes, mean_n < epsilon, and
     n >= 2 L^2 diam(S0)^2 ln(1/delta) / (epsilon - mean_n)^2
     => w.p. >= 1 - delta, E_{s~rho}[V*(s) - V^pi(s)] <= epsilon.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

Condition = Literal["i", "ii"]


@dataclass(frozen=True)
class CertificationSpec:
    """What the run must certify. ``diameter`` is diam(S0), needed by condition (ii) only."""

    condition: Condition
    epsilon: float
    p: float
    delta: float
    lipschitz: float
    diameter: float | None = None

    def __post_init__(self) -> None:
        if self.condition not in ("i", "ii"):
            raise ValueError(f"condition must be 'i' or 'ii', got {self.condition!r}")
        if not (math.isfinite(self.epsilon) and self.epsilon > 0):
            raise ValueError(f"epsilon must be finite and > 0, got {self.epsilon!r}")
        if not 0 < self.p < 1:
            raise ValueError(f"p must lie in (0, 1), got {self.p!r}")
        if not 0 < self.delta < 1:
            raise ValueError(f"delta must lie in (0, 1), got {self.delta!r}")
        if not (math.isfinite(self.lipschitz) and self.lipschitz > 0):
            raise ValueError(f"the Lipschitz constant must be finite and > 0, got {self.lipschitz!r}")
        if self.condition == "ii" and (self.diameter is None or not self.diameter > 0):
            raise ValueError("condition (ii) needs diam(S0) > 0")

    def quiet_episodes_required(self) -> int:
        """Condition (i): the smallest integer n >= ln(1/delta) / (1 - p)."""
        return math.ceil(math.log(1.0 / self.delta) / (1.0 - self.p) - 1e-12)

    def hoeffding_required(self, mean_gap: float) -> float:
        """Condition (ii): episodes needed for a window whose mean gap is ``mean_gap``."""
        margin = self.epsilon - mean_gap
        if margin <= 0:
            return math.inf
        assert self.diameter is not None
        return 2 * self.lipschitz**2 * self.diameter**2 * math.log(1 / self.delta) / margin**2

    def statement(self, episodes_used: int) -> str:
        base = f"V* is {self.lipschitz:.6g}-Lipschitz on the states compared"
        if self.condition == "i":
            return (
                f"With probability at least {1 - self.delta:.4g}, P_(s~rho)[V*(s) - V^pi(s) <= {self.epsilon:.6g}]"
                f" >= {self.p:.4g} (Theorem 4.1 (i), {episodes_used} consecutive episodes without new data;"
                f" assumes {base})."
            )
        return (
            f"With probability at least {1 - self.delta:.4g}, E_(s~rho)[V*(s) - V^pi(s)] <= {self.epsilon:.6g}"
            f" (Theorem 4.1 (ii), mean surrogate gap over the last {episodes_used} episodes;"
            f" assumes {base}, diam(S0) = {self.diameter:.6g})."
        )


@dataclass(frozen=True)
class CertificationStatus:
    """Where the run stands. ``window`` is the quiet streak (i) or the best window length (ii)."""

    certified: bool
    window: int
    required: int
    quiet_episodes: int
    mean_gap: float | None = None


@dataclass
class Certifier:
    """Feeds on one (gap, oracle_called) pair per episode, in order."""

    spec: CertificationSpec
    gaps: list[float] = field(default_factory=list)
    quiet_episodes: int = 0

    def observe(self, gap: float, oracle_called: bool) -> CertificationStatus:
        self.gaps.append(float(gap))
        self.quiet_episodes = 0 if oracle_called else self.quiet_episodes + 1
        return self.status()

    def status(self) -> CertificationStatus:
        if self.spec.condition == "i":
            required = self.spec.quiet_episodes_required()
            return CertificationStatus(
                certified=self.quiet_episodes >= required,
                window=self.quiet_episodes,
                required=required,
                quiet_episodes=self.quiet_episodes,
            )
        return self._hoeffding_status()

    def _hoeffding_status(self) -> CertificationStatus:
        if not self.gaps:
            return CertificationStatus(False, 0, 0, 0)
        recent_first = np.asarray(self.gaps[::-1])
        windows = np.arange(1, len(recent_first) + 1)
        with np.errstate(invalid="ignore"):
            means = np.cumsum(recent_first) / windows  # inf gaps give inf means
        need = np.array([self.spec.hoeffding_required(m) for m in means])
        shortfall = need - windows
        best = int(np.argmin(shortfall))
        # required = 0 means no window yet has a mean gap below epsilon.
        required = math.ceil(need[best]) if math.isfinite(need[best]) else 0
        return CertificationStatus(
            certified=bool(shortfall[best] <= 0),
            window=int(windows[best]),
            required=required,
            quiet_episodes=self.quiet_episodes,
            mean_gap=float(means[best]),
        )


@dataclass(frozen=True)
class Certificate:
    """The run's certificate, with everything needed to judge it."""

    task: str
    condition: Condition
    epsilon: float
    p: float
    delta: float
    lipschitz: float
    lipschitz_source: str
    episodes: int
    oracle_calls: int
    dataset_size: int
    window: int
    required: int
    statement: str

    def summary(self) -> str:
        lines = [
            f"CERTIFICATE ({self.task}, Theorem 4.1 ({self.condition}))",
            f"  episodes        {self.episodes}",
            f"  oracle calls    {self.oracle_calls}",
            f"  dataset size    {self.dataset_size} triplets",
            f"  L used          {self.lipschitz:.6g} (source: {self.lipschitz_source})",
            f"  epsilon, p, delta  {self.epsilon:g}, {self.p:g}, {self.delta:g}",
            f"  window          {self.window} episodes (required {self.required})",
            f"  statement       {self.statement}",
        ]
        return "\n".join(lines)
