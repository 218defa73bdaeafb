"""Run choices given as text or numbers (a node parameter, a command-line option), parsed once.

ROS parameters and command-line options arrive as plain values; these functions turn them into what
the core runs on, or raise a ValueError that names the choice, so every front end refuses a bad value
with the same words before anything starts.
"""

from __future__ import annotations

from npp_ros.policy.lipschitz import LipschitzConstant

LIPSCHITZ_CHOICES = ("analytic", "paper")  # the named L choices, resolved once the plant is known (npp_ros.run.setup)


def parse_lipschitz(choice: str | float) -> str | LipschitzConstant:
    """'analytic' or 'paper' as they are; a number as a user's L (finite and > 0), else a ValueError."""
    if choice in LIPSCHITZ_CHOICES:
        return str(choice)
    try:
        return LipschitzConstant(float(choice), "user", "given as a run setting")
    except ValueError:
        named = ", ".join(LIPSCHITZ_CHOICES)
        raise ValueError(f"lipschitz must be {named} or a finite number > 0, got {choice!r}") from None


def check_gamma(gamma: float) -> float:
    """The discount: in (0, 1], 1 for undiscounted H-step values."""
    if not 0 < gamma <= 1:
        raise ValueError(f"gamma must lie in (0, 1], got {gamma!r}")
    return float(gamma)
