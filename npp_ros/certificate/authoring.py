"""Writing a certificate: which value it speaks of, whether it is proven, and every assumption it rests on.

The loop decides *when* a run certifies (the stopping rule); what the certificate then says depends
only on the spec, the expert's value basis and the run's counts, so it is written here, beside the
spec and the certificate it fills in.
"""

from __future__ import annotations

import math

from npp_ros.certificate.certifier import Certificate, CertificationSpec, CertificationStatus, assumption_list
from npp_ros.certificate.values import ValueBasis


def author_certificate(
    spec: CertificationSpec,
    basis: ValueBasis | None,
    status: CertificationStatus,
    *,
    task: str,
    horizon: int,
    episodes: int,
    oracle_calls: int,
    dataset_size: int,
    policy_trajectories: int,
) -> Certificate:
    """The certificate a run issues when ``status`` certifies, about the policy on its first trajectories."""
    certify = spec.certify
    if certify == "oracle":
        value = f"the expert's own H-step return V^E_H (H = {horizon}), as the oracle reports it"
    elif certify == "rollout" and basis is not None:
        value = basis.value
    else:
        value = "V*, the value function the expert's stored values describe"
    return Certificate(
        task=task,
        spec=spec,
        episodes=episodes,
        oracle_calls=oracle_calls,
        dataset_size=dataset_size,
        policy_trajectories=policy_trajectories,
        window=status.window,
        required=status.required,
        test=status.test,
        delta_spent=status.test_delta,
        value=value,
        statement=spec.statement(
            status.window, value, policy_trajectories, status.test, status.failures, status.log_mixture
        ),
        proven=is_proven(spec, basis),
        assumptions=assumptions(spec, basis),
        failures=status.failures,
        mixture=math.exp(status.log_mixture) if status.log_mixture is not None else None,
    )


def no_lipschitz_bound(basis: ValueBasis | None) -> str:
    """Why no L bounds the stored values, where the expert knows it ("" otherwise)."""
    return basis.no_lipschitz_bound if basis is not None else ""


def is_proven(spec: CertificationSpec, basis: ValueBasis | None) -> bool:
    """Whether the claim follows from its assumptions, rather than resting on a test or an L that cannot hold."""
    if spec.rule == "paper":
        return False
    if spec.certify != "oracle" and no_lipschitz_bound(basis):
        return False  # the claim rests on an L that cannot exist for these values
    if spec.certify == "surrogate":
        # Theorem 3.4's argument (and the condition the basis checks) is about stored actions replayed open loop.
        return bool(basis is not None and basis.theorem_34_holds and spec.policy == "open-loop")
    return True


def assumptions(spec: CertificationSpec, basis: ValueBasis | None) -> tuple[str, ...]:
    """Every assumption the claim rests on, in the words a certificate prints."""
    lipschitz = (
        f"L = {spec.lipschitz.value:.6g} ({spec.lipschitz.source}) bounds the slope of the stored value function "
        f"on every segment between an initial state and a data point"
    )
    if no_bound := no_lipschitz_bound(basis):
        lipschitz += f": it does NOT hold here, {no_bound}"
    common = [
        "initial states are independent draws from rho, independent of the run so far",
        "the plant is deterministic, so one rollout's return is the policy's value at s0",
    ]
    if spec.certify == "rollout":
        assert basis is not None
        items = [lipschitz, "the expert's stored values equal its value function at the data points",
                 basis.tail_detail, *common]  # fmt: skip
    elif spec.certify == "oracle":
        items = ["the expert's reported return at s0 is the return of the trajectory it gives", *common,
                 "no Lipschitz constant is needed; the claim is relative to the expert's own return"]  # fmt: skip
    elif spec.policy == "feedback":
        items = [lipschitz, "Theorem 3.4 (V_lb <= V^pi) for the feedback policy, so that the surrogate gap bounds "
                 "the true gap: NOT checked; its argument holds for stored actions replayed open loop, and for a "
                 "feedback law it would need L (1 - gamma L_g) >= L_rg, with L_g and L_rg the slopes in the state of "
                 "the closed-loop step and reward at every data point",
                 "initial states are independent draws from rho"]  # fmt: skip
    else:
        items = [lipschitz, "Theorem 3.4 (V_lb <= V^pi), so that the surrogate gap bounds the true gap",
                 basis.theorem_34 if basis is not None and basis.theorem_34 else
                 "Theorem 3.4's condition was not checked for this plant",
                 "initial states are independent draws from rho"]  # fmt: skip
    if spec.rule == "mixture":
        items.append(
            "the policy stayed frozen during its verification: the trajectories the verification asked for "
            "joined it only afterwards, and its checks counted in the order the episodes ran"
        )
    if spec.rule == "paper":
        items.append("the paper's one-shot test, though it is checked after every episode (not sequentially valid)")
    return assumption_list(items)
