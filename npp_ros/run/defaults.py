"""Every run setting's default, declared once.

The run request (request.py) takes its fields' defaults from here, and so do the parts below or beside it that
a caller may use without a request: build_config, the run's config (RunConfig) and npp-experiment's settings. A
setting whose default is the task's (horizon, epsilon, L, certify, rule, the expert's options) has none here:
None in the request means "the task's", decided by the task alone. Defaults with a home of their own are used
from it: the policy kind (npp_ros.policy.feedback.DEFAULT_POLICY), the expert's model on a set of robots
(npp_ros.run.nominal_plan.DEFAULT_EXPERT_MODEL), the episode length of a task that names none
(npp_ros.tasks.task.DEFAULT_HORIZON). npp-experiment's arms follow the paper instead where the paper decided
(its checked quantity, stopping rule and open-loop policy, named as the paper's in npp_ros.experiment.arms).
"""

from __future__ import annotations

TASK = "lqr_2_1"  # the task a request names when it names none (the paper's first system)
SEED = 0
CONDITION = "i"  # Theorem 4.1's condition: a share p of initial states within epsilon
P = 0.9
DELTA = 0.1
GAMMA = 1.0  # undiscounted H-step values
EXPLORE = 0.0  # no exploration beyond the checks
UNCERTAINTY = 0.0  # the exact model, no set of robots
POLICY_LIPSCHITZ = "claim"  # the policy acts by the claim's L
MAX_EPISODES = 1000
