"""The paper's Section 5 experiments (and Appendix B with a detuned expert), run in process.

May import: npp_ros.policy, npp_ros.certificate, npp_ros.trajopt, npp_ros.tasks, npp_ros.run.

One *arm* is a task, the expert that supplies data (optimal LQR or a detuned one), a choice
of L (the paper's, or one that bounds the expert's value slope) and what certifies (the paper's
surrogate gap and one-shot rule, or a sound mode under the sequential rule). Each (arm, seed)
runs the same :class:`~npp_ros.run.loop.NPPLoop` as the supervisor node, stored in its own ``run.sqlite``, and is
evaluated at checkpoints on a fixed set of N initial states s0 ~ rho: the policy's return, the
data expert's and the optimal controller's returns from the same s0, and V_lb(s0). Everything is
rebuilt from the files, so a resumed or repeated run gives the same numbers. Every certificate is
also checked on HELD_OUT fresh s0 (a stream of its own): the fraction whose gap, for the value the
certificate speaks of, is within epsilon, and a one-sided binomial test of its claim. That check, its draws and
the expert's kept answers are npp-learn's too (:mod:`npp_ros.run.held_out`); what is here is npp-experiment's own.

Modules, one concern each: ``arms`` (what is run), ``runs`` (running and resuming one arm and
seed), ``evaluation`` (the checkpoint evaluations, and the held-out check of an arm's certificate),
``expert_requests`` (the expert's returns asked in chunks over Dask) and ``report`` (the results table). Figures
are in :mod:`npp_ros.experiment.plots`.
"""

from npp_ros.experiment.arms import (
    DEFAULT_CHECKPOINTS,
    DETUNED_CONTROL_WEIGHT,
    EXPERTS,
    LIPSCHITZ_SETTINGS,
    Arm,
    ExperimentSettings,
    default_arms,
)
from npp_ros.experiment.evaluation import EvaluationRow, HeldOutCheck, check_certificate, read_evaluations
from npp_ros.experiment.report import ResultRow, result_row, verdict, write_results
from npp_ros.experiment.runs import RunRecord, run_arm_seed

__all__ = [
    "DEFAULT_CHECKPOINTS",
    "DETUNED_CONTROL_WEIGHT",
    "EXPERTS",
    "LIPSCHITZ_SETTINGS",
    "Arm",
    "EvaluationRow",
    "ExperimentSettings",
    "HeldOutCheck",
    "ResultRow",
    "RunRecord",
    "check_certificate",
    "default_arms",
    "read_evaluations",
    "result_row",
    "run_arm_seed",
    "verdict",
    "write_results",
]
