"""Writing a certificate: which value it speaks of, whether it is proven, and every assumption it rests on.

The loop decides *when* a run certifies (the stopping rule); what the certificate then says depends
only on the spec, the expert's value basis and the run's counts, so it is written here, beside the
spec and the certificate it fills in.

A certificate is relative to its expert, so its statement also says how often the expert did the task on its
own answers and the policy on its checked rollouts, by the task's success criterion (:class:`MeasuredSuccess`),
or that the task states none and nothing was measured.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from npp_ros.certificate.certifier import (
    L_FREE,
    SUCCESS_MARK,
    Certificate,
    CertificationSpec,
    CertificationStatus,
    assumption_list,
)
from npp_ros.certificate.values import ValueBasis

LOW_EXPERT_SUCCESS = 0.5  # below this share of successful answers the statement says the expert fails the task


@dataclass(frozen=True)
class MeasuredSuccess:
    """What a run measured of the task's success criterion, for the certificate's words.

    ``criterion`` is the criterion in words (None: the task states none); ``expert`` is (answers that succeeded,
    answers judged); ``policy`` is (rollouts that succeeded, checked episodes), None when the check measures no
    rollout of the policy (surrogate).
    """

    criterion: str | None
    expert: tuple[int, int] = (0, 0)
    policy: tuple[int, int] | None = (0, 0)
    relative: bool = True  # the claim is relative to the expert (False: the success claim, which needs none)

    def sentence(self) -> str:
        """One sentence, starting with SUCCESS_MARK, that the statement ends with."""
        if self.criterion is None:
            return (
                f"{SUCCESS_MARK}: not measured; the task states no success criterion, so this certificate does not "
                "say whether the expert, or the policy, does the task."
            )
        done, answers = self.expert
        said = f"the expert succeeded on {done} of {answers} answers"
        if self.policy is None:
            said += "; the policy's rollouts are not checked in this mode"
        else:
            said += f"; the policy on {self.policy[0]} of {self.policy[1]} checked episodes"
        sentence = f"{SUCCESS_MARK}, {self.criterion}: {said}."
        if not self.relative:
            sentence += (
                " The claim needs no expert: it was asked only after a failed check, so its answers are from the"
                " hardest starts."
            )
        elif answers and done / answers < LOW_EXPERT_SUCCESS:
            sentence += (
                " A certificate is relative to its expert, and this expert mostly fails the task: a claim about the"
                " policy against it does not say the policy does the task."
            )
        return sentence


@dataclass(frozen=True)
class RobotClaim:
    """What a run whose plant is a robot says of it in its certificate (npp_ros.run.on_robot).

    ``robot``: the robot in words (its description's fingerprint, the model its expert planned on); ``starts``: where
    its episodes started, in words; the counts are of the robot's own episodes: the checks counted, the expert plans
    it ran, those a fault cut short (stored, not counted), its clock's seconds over all, and late commands.
    """

    robot: str
    starts: str
    checks: int
    answers: int
    faults: int
    robot_time: float
    late_commands: int
    prior: str = ""  # the trajectories it started with from another run, in words ("": none)

    def sentence(self) -> str:
        started = f" The policy's data began with {self.prior}; those are data, never checks." if self.prior else ""
        return (
            f"The robot: {self.robot}. Every check is one of this robot's own episodes from its reset ({self.starts}), "
            f"judged on the states it measured: {self.checks} checks and {self.answers} expert plans run on it, "
            f"{self.robot_time:.1f} s of robot time; {self.faults} episodes a fault cut short are stored and not "
            f"counted; {self.late_commands} commands arrived after their control period. Nothing is claimed for "
            "another robot, or for this one after it changes." + started
        )


ON_ROBOT_DRAW = "s0~this robot's resets"  # what a claim on the robot itself is a probability over


def on_robot_assumptions() -> tuple[str, ...]:
    """What a success claim on the robot itself rests on: no model of the robot, no deterministic plant."""
    return (
        "each check is one episode of the robot itself from its reset, and success is judged on the states the robot "
        "measured (its sensors as they read), not on a model",
        "the robot's starts are independent draws from one distribution (its reset, asked for an s0 drawn from rho "
        "with the run's seed and the episode's index; the measured start is what counts), independent of the run so "
        "far: a reset that drifts with wear or with the last episode breaks this, and is NOT checked",
        "the robot is the same robot at every episode (its description's fingerprint is checked at the run's start)",
        "the claim is over the episodes no fault cut short: a cut episode is stored and marked, never counted, so a "
        "fault that comes with failing (a limit tripped on a bad swing) is a failure the claim does not see",
        "no Lipschitz constant, no expert value and no model of the robot are needed: the claim is about success "
        "alone, and says nothing of optimality",
    )


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
    success: MeasuredSuccess | None = None,
    robots: str = "",
    reference: str = "",
    robot: RobotClaim | None = None,
    policy_lipschitz: float | None = None,
) -> Certificate:
    """The certificate a run issues when ``status`` certifies, about the policy on its first trajectories;
    ``success``: what the run measured of the task's success criterion (None: the task states none); ``robots``:
    the set of robots each episode drew from, in words ("": the exact model); ``reference``: what V^E is then (the
    expert planning on each robot, unless it says otherwise); ``robot``: a run whose plant is the robot itself,
    whose claim is over that robot's starts and rests on no model (success claims only); ``policy_lipschitz``: the L
    the certified policy chooses by when the run chose its own (None: the claim's)."""
    measured = success if success is not None else MeasuredSuccess(None)
    certify = spec.certify
    if certify == "success":
        value = measured.criterion or "the task's success criterion"
    elif certify == "oracle":
        value = f"the expert's own H-step return V^E_H (H = {horizon}), as the oracle reports it"
    elif certify == "rollout" and basis is not None:
        value = basis.value
    else:
        value = "V*, the value function the expert's stored values describe"
    statement = over_robots(
        spec.statement(status.window, value, policy_trajectories, status.test, status.failures, status.log_mixture),
        robots,
        reference,
    )
    listed = assumptions(spec, basis) + robot_assumptions(spec, robots)
    if robot is not None:
        if certify != "success":
            raise ValueError("a run on the robot itself certifies the success claim only")
        statement = statement.replace("_(s0~rho)[", f"_({ON_ROBOT_DRAW})[") + " " + robot.sentence()
        listed = assumption_list([*on_robot_assumptions(), *spec_rule_assumptions(spec)])
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
        statement=statement + " " + measured.sentence(),
        proven=is_proven(spec, basis) and not (robots and spec.certify == "surrogate"),
        assumptions=listed,
        failures=status.failures,
        mixture=math.exp(status.log_mixture) if status.log_mixture is not None else None,
        policy_lipschitz=policy_lipschitz,
    )


ROBOT_DRAW = "(s0, theta)~rho x Theta"  # what a claim under model uncertainty is a probability over


PRIVILEGED_REFERENCE = "V^E is the expert planning on each episode's robot (which the policy does not know)"


def over_robots(statement: str, robots: str, reference: str = "") -> str:
    """A claim over the exact model made a claim over the set of robots: the probability is over (s0, theta), and
    V^E is what ``reference`` says (default: the expert planning on each robot)."""
    if not robots:
        return statement
    claim = statement.replace("_(s0~rho)[", f"_({ROBOT_DRAW})[")
    return (
        f"{claim} Theta, the robots this covers: {robots}; {reference or PRIVILEGED_REFERENCE}. Nothing is claimed "
        "for a robot outside Theta."
    )


def robot_assumptions(spec: CertificationSpec, robots: str) -> tuple[str, ...]:
    """What a claim under model uncertainty adds to its assumptions ("" robots: nothing)."""
    if not robots:
        return ()
    items = [
        "each episode's robot theta is an independent draw from Theta (from the run's seed and the episode only), "
        "independent of s0 and of the run so far",
        "the robot is one of Theta: the plant's model with those parameters, delay and noise; nothing else differs",
    ]
    if spec.certify not in L_FREE:
        items.append(
            "L bounds the slope of the value for every robot in Theta, and V_ub from data of one robot bounds "
            "another's value: NOT checked, so a certificate under uncertainty that rests on L is not proven"
        )
    return tuple(items)


def no_lipschitz_bound(basis: ValueBasis | None) -> str:
    """Why no L bounds the stored values, where the expert knows it ("" otherwise)."""
    return basis.no_lipschitz_bound if basis is not None else ""


def is_proven(spec: CertificationSpec, basis: ValueBasis | None) -> bool:
    """Whether the claim follows from its assumptions, rather than resting on a test or an L that cannot hold."""
    if spec.rule == "paper":
        return False
    if spec.certify not in L_FREE and no_lipschitz_bound(basis):
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
    if spec.certify == "success":
        items = ["the success criterion is judged on the true states of the policy's own rollout from s0", *common,
                 "no Lipschitz constant and no expert value is needed: the claim is about success alone, and says "
                 "nothing of optimality"]  # fmt: skip
    elif spec.certify == "rollout":
        assert basis is not None
        items = [lipschitz, "the expert's stored values equal its value function at the data points",
                 basis.tail_detail, *common]  # fmt: skip
    elif spec.certify == "oracle":
        items = ["the expert's reported return at s0 is the return of the trajectory it gives", *common,
                 "no Lipschitz constant is needed; the claim is relative to the expert's own return"]  # fmt: skip
    elif spec.policy in ("feedback", "path"):
        items = [lipschitz, f"Theorem 3.4 (V_lb <= V^pi) for the {spec.policy} policy, so that the surrogate gap "
                 "bounds the true gap: NOT checked; its argument holds for stored actions replayed open loop, and for "
                 "a feedback law it would need L (1 - gamma L_g) >= L_rg, with L_g and L_rg the slopes in the state of "
                 "the closed-loop step and reward at every data point",
                 "initial states are independent draws from rho"]  # fmt: skip
    else:
        items = [lipschitz, "Theorem 3.4 (V_lb <= V^pi), so that the surrogate gap bounds the true gap",
                 basis.theorem_34 if basis is not None and basis.theorem_34 else
                 "Theorem 3.4's condition was not checked for this plant",
                 "initial states are independent draws from rho"]  # fmt: skip
    return assumption_list([*items, *spec_rule_assumptions(spec)])


def spec_rule_assumptions(spec: CertificationSpec) -> list[str]:
    """What the stopping rule adds to any claim's assumptions."""
    items = []
    if spec.rule == "mixture":
        items.append(
            "the policy stayed frozen during its verification: the trajectories the verification asked for "
            "joined it only afterwards, and its checks counted in the order the episodes ran"
        )
    if spec.rule == "paper":
        items.append("the paper's one-shot test, though it is checked after every episode (not sequentially valid)")
    return items
