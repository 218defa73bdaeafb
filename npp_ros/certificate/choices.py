"""Run choices given as text or numbers (a node parameter, a command-line option), parsed once.

ROS parameters and command-line options arrive as plain values; these functions turn them into what
the core runs on, or raise a ValueError that names the choice, so every front end refuses a bad value
with the same words before anything starts.
"""

from __future__ import annotations

from npp_ros.policy.lipschitz import LipschitzConstant

# The named L choices, resolved once the plant is known (npp_ros.run.setup): 'analytic' (a bound the expert
# computes), 'paper' (the paper's value) and 'data' (fixed from the run's first expert answers, see DATA_RULE).
LIPSCHITZ_CHOICES = ("analytic", "paper", "data")
DATA_ANSWERS = 3  # 'data': the expert's answers from the s0 of episodes 0 .. DATA_ANSWERS - 1 ...
DATA_FACTOR = 2.0  # ... and L = this x the steepest value slope they show
# Window values Q_t = r_t + ... + r_{t+H-1} take their last t rewards past the horizon, from the continuation
# (zero torque for a task file): the rule uses the steps whose values lie at least this share within the horizon,
DATA_WITHIN = 0.75  # t <= (1 - DATA_WITHIN) H; a chaotic fall after H must not set the policy's L ...
DATA_PAIR_FLOOR = 0.01  # ... and pairs at least this x the median distance between the pairs compared apart
DATA_RULE = (
    f"{DATA_FACTOR:g} x the steepest value slope seen on the expert's answers from the s0 of the run's first "
    f"{DATA_ANSWERS} episodes (the stored values' slope between points at least {DATA_PAIR_FLOOR:g} x the median "
    f"pair distance apart, on steps whose values lie at least {DATA_WITHIN:g} within the horizon; and the iLQR "
    "expert's own |W_x|), fixed when the run begins and kept in its run file"
)
LIPSCHITZ_HELP = (
    "'analytic' (a bound on the expert's value slope, lqr only: the guarantee holds), 'paper' (the paper's "
    f"value, not a bound on these tasks), 'data' (L = {DATA_RULE}; a choice, not a bound) or a number (a user's L, "
    "in return per unit of state distance)"
)
LIPSCHITZ_FLAG = "pass --lipschitz (a node: the supervisor's lipschitz parameter)"
EPSILON_FLAG = "pass --epsilon (a node: the supervisor's epsilon parameter)"


def parse_lipschitz(choice: str | float) -> str | LipschitzConstant:
    """A named choice as it is; a number as a user's L (finite and > 0), else a ValueError."""
    if choice in LIPSCHITZ_CHOICES:
        return str(choice)
    try:
        value = float(choice)
    except ValueError:
        named = ", ".join(LIPSCHITZ_CHOICES)
        raise ValueError(f"lipschitz must be {named} or a finite number > 0, got {choice!r}") from None
    return LipschitzConstant(value, "user", "given as a run setting")  # refuses a number that is no L, saying why


def check_gamma(gamma: float) -> float:
    """The discount: in (0, 1], 1 for undiscounted H-step values."""
    if not 0 < gamma <= 1:
        raise ValueError(f"gamma must lie in (0, 1], got {gamma!r}")
    return float(gamma)
