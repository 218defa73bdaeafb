"""How an expert's stored values relate to the value a certificate speaks of.

The data store stationary values V(s) (for the lqr tasks H - J*(s)); a policy's rollout measures
an H-step return. A certificate must compare like with like, so each expert states which value
its claims are about and bounds the difference at s0: tail(s0) >= V_H(s0) - V(s0). The rollout
certification mode checks V_ub(s0) + tail(s0) - R^pi(s0), a proven upper bound on
V_H(s0) - R^pi(s0) when L bounds the slope of V.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from npp_ros.policy.dataset import FloatArray


@dataclass(frozen=True)
class ValueBasis:
    """``tail`` is None when the expert's values give no upper bound on V_H (rollout mode refuses)."""

    value: str
    tail: Callable[[FloatArray], float] | None
    tail_detail: str
    theorem_34_holds: bool = False  # Theorem 3.4's condition, checked for the plant and L (surrogate mode)
    theorem_34: str = ""
    no_lipschitz_bound: str = ""  # why no finite L bounds these values, where the expert knows it ("": no such reason)


def theorem_34_condition(
    lipschitz: float, gamma: float, transition_lipschitz: float, reward_lipschitz: float, where: str
) -> tuple[bool, str]:
    """Theorem 3.4's sufficient condition L (1 - gamma L_f) >= L_r, and what it says in words.

    L_f bounds |f(s, a) - f(s', a)| / |s - s'| and L_r bounds |r(s, a) - r(s', a)| / |s - s'| on
    ``where``; with them T^pi V_lb - V_lb >= (L - L_r - gamma L L_f) |s - s_i| >= 0, so V_lb <= V^pi.
    """
    contraction = gamma * transition_lipschitz
    if contraction >= 1:
        return False, (
            f"Theorem 3.4 (V_lb <= V^pi) needs L (1 - gamma L_f) >= L_r; here gamma L_f = {gamma:g} x "
            f"{transition_lipschitz:.6g} = {contraction:.6g} >= 1, so no L satisfies it and the surrogate gap "
            "is not a proven bound on the true gap"
        )
    needed = reward_lipschitz / (1 - contraction)
    holds = lipschitz >= needed
    return holds, (
        f"Theorem 3.4 (V_lb <= V^pi) needs L >= L_r / (1 - gamma L_f) = {reward_lipschitz:.6g} / "
        f"{1 - contraction:.6g} = {needed:.6g} ({where}); L = {lipschitz:.6g} {'meets' if holds else 'misses'} it"
        + ("" if holds else ", so the surrogate gap is not a proven bound on the true gap")
        + "; the last point of each truncated trajectory has no successor in the data and is not covered"
    )
