"""The policy as one object: how it acts, its L, and the task's control space, which together make it over data.

A run's policy crosses processes (the supervisor to the policy node), is read back from run files (npp-deploy,
``read_run``) and is rebuilt in process (checks, evaluations); each place must act as the run certified. So what
decides it is one value, :class:`PolicySpec`, built from a run's spec in one place (npp_ros.run.loop.make_policy)
and sent whole (npp_ros_graph.transport.convert), and the policy over any data is ``spec.build(data)``.
"""

from __future__ import annotations

from dataclasses import dataclass

from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import Dataset
from npp_ros.policy.feedback import ControlSpace, PolicyKind, check_policy_kind
from npp_ros.policy.lipschitz import LipschitzConstant


@dataclass(frozen=True)
class PolicySpec:
    """What decides how a run's policy acts over its data.

    ``kind``: open-loop (the paper's stored actions), feedback (the expert's gains at the chosen point) or path
    (following the chosen trajectory); ``lipschitz``: the L of its V_lb; ``control``: the task's angles, actuator
    range and invariant entries (the open-loop policy uses only the invariant entries, in its distance).
    """

    kind: PolicyKind
    lipschitz: LipschitzConstant
    control: ControlSpace

    def __post_init__(self) -> None:
        check_policy_kind(self.kind)

    def build(self, data: Dataset) -> NonparametricPolicy:
        """The policy over ``data``: the greedy choice on V_lb with this L, acting as ``kind`` says."""
        return NonparametricPolicy(data, self.lipschitz.value, control=self.control, kind=self.kind)

    def describe(self) -> str:
        return f"{self.kind} policy, L = {self.lipschitz.value:g} ({self.lipschitz.source})"
