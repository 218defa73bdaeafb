"""When Algorithm 1 may stop, and what it then certifies.

What each episode checks (``certify``), per episode at its initial state s0:

- ``rollout`` (default): V_ub(s0) + tail(s0) - R^pi(s0), with R^pi the return of the policy's own
  H-step rollout from s0 and tail(s0) the expert's bound on how far the H-step value exceeds the
  stationary value its data describe. An upper bound on V_H(s0) - R^pi_H(s0) whenever L bounds
  the slope of the stored value function; needs no Theorem 3.4.
- ``oracle``: V^E(s0) - R^pi(s0), V^E(s0) the expert's own H-step return from s0 (one oracle call
  per checked episode). Needs no Lipschitz constant; the claim is relative to the expert.
- ``surrogate``: the paper's V_ub(s0) - V_lb(s0). An upper bound on the true gap only where
  Theorem 3.4 holds, which a valid L does not ensure (tests/test_soundness.py builds a counterexample).

When to stop (``rule``):

- ``sequential`` (default but in oracle mode). Each time the policy changes a new test starts; test k (k = 1, 2, ...)
  may spend delta_k = delta / (k (k + 1)), and sum_k delta_k = delta. Condition (i): test k
  certifies after n_k >= ln(1/delta_k) / (1 - p) passed checks in a row. Proof sketch: during a
  test the policy is frozen and every s0 is a fresh draw from rho, independent of the past; if the
  policy's true success rate q is below p, each check passes with probability at most q (a passed
  check implies a true gap <= epsilon), so the test passes with probability at most
  p^(n_k) <= exp(-(1 - p) n_k) <= delta_k, whatever happened before it. A union bound over the
  tests gives a false certificate with probability at most delta, however many tests the run makes
  and whenever it stops. Condition (ii) (surrogate only) looks again after every check of a test,
  so the n-th look of test k spends delta_k / (n (n + 1)).
- ``mixture`` (an option): screen a policy with 20 passes in a row, then verify
  it with a mixture likelihood-ratio test that tolerates failures (npp_ros/mixture.py, with its
  proof sketch).
- ``paper``: Theorem 4.1 as the paper uses it: n >= ln(1/delta) / (1 - p) quiet episodes,
  checked after every episode, and for (ii) the best window over all episodes. Kept to reproduce
  the paper; repeated looks make its error rate exceed delta (see the note above).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import MISSING, dataclass, field, fields, replace
from typing import Any, Literal, get_args

import numpy as np

from npp_ros.policy.feedback import PAPER_POLICY, POLICY_KINDS, PolicyKind
from npp_ros.policy.lipschitz import LipschitzConstant

Condition = Literal["i", "ii"]
CheckedQuantity = Literal["rollout", "oracle", "surrogate", "success"]
StoppingRule = Literal["sequential", "mixture", "paper"]
CONDITIONS: tuple[str, ...] = get_args(Condition)
# The rule a run uses unless it names one, per checked quantity, as measured on real runs (docs, "Which rule
# is the default"): the mixture rule needs fewer checks for a simulated policy that stays frozen below
# 0.98, but on the pendulum swing-up (oracle) and lqr_2_1 (rollout) it needed more episodes than the
# streak, whose failures keep teaching the policy while a verification holds its data back.
DEFAULT_RULES: dict[str, StoppingRule] = {
    "rollout": "sequential", "oracle": "sequential", "surrogate": "sequential", "success": "sequential"
}  # fmt: skip
CERTIFY_MODES: tuple[str, ...] = get_args(CheckedQuantity)
L_FREE = ("oracle", "success")  # the checked quantities whose claim rests on no Lipschitz constant
STOPPING_RULES: tuple[str, ...] = get_args(StoppingRule)

# The statement ends with what the run measured of the task's success (authoring.MeasuredSuccess), from here on.
SUCCESS_MARK = "Success as the task defines it"

QUANTITY = {
    "rollout": "V_ub(s0) + tail(s0) - R^pi(s0)",
    "oracle": "V^E(s0) - R^pi(s0)",
    "surrogate": "V_ub(s0) - V_lb(s0)",
    "success": "the task's success criterion on the policy's own rollout from s0",
}
SUCCESS_CHECK = {True: 0.0, False: 1.0}  # certify=success: the checked quantity is 1 - [the rollout succeeded]
SUCCESS_EPSILON = 1.0  # the spec's epsilon of a success claim on a task that has none: no gap is bounded, never read


def check_spec_choices(
    condition: str,
    p: float,
    delta: float,
    policy: str | None,
    *,
    epsilon: float | None,
    certify: str | None,
    rule: str | None,
) -> None:
    """Refuse, with one line naming the field, what a CertificationSpec may not hold (its constructor checks its
    fields here). None is a value the task decides (epsilon, certify, rule, policy): it is checked when the spec is
    built, so a node can check its parameters here before it knows the task, with the same code and no stand-ins."""
    if policy is not None and policy not in POLICY_KINDS:
        raise ValueError(f"policy must be one of {', '.join(POLICY_KINDS)}, got {policy!r}")
    if condition not in CONDITIONS:
        raise ValueError(f"condition must be 'i' or 'ii', got {condition!r}")
    if certify is not None and certify not in CERTIFY_MODES:
        raise ValueError(f"certify must be one of {', '.join(CERTIFY_MODES)}, got {certify!r}")
    if rule is not None and rule not in STOPPING_RULES:
        raise ValueError(f"rule must be one of {', '.join(STOPPING_RULES)}, got {rule!r}")
    if epsilon is not None and not (math.isfinite(epsilon) and epsilon > 0):
        raise ValueError(f"epsilon must be finite and > 0, got {epsilon!r}")
    if not 0 < p < 1:
        raise ValueError(f"p must lie in (0, 1), got {p!r}")
    if not 0 < delta < 1:
        raise ValueError(f"delta must lie in (0, 1), got {delta!r}")
    if condition == "ii" and rule == "mixture":
        raise ValueError("the mixture rule tests condition (i): it counts passed and failed checks")
    if condition == "ii" and certify is not None and certify != "surrogate":
        raise ValueError(
            f"condition (ii) cannot certify with certify={certify}: Hoeffding's bound needs a checked "
            "quantity of known range, and a policy's return has none (a bad policy can lose without limit); "
            "use condition (i), or certify=surrogate (range 2 L diam(S0))"
        )


@dataclass(frozen=True)
class CertificationSpec:
    """What the run must certify, about which policy, and the L it rests on.

    ``diameter`` is diam(S0), needed by condition (ii) only. ``policy`` is how the certified policy acts at its
    chosen data point (npp_ros.policy.feedback): the paper's open-loop action, the expert's feedback law, or that law
    along the stored trajectory it follows (npp_ros.policy.path).
    """

    condition: Condition
    epsilon: float
    p: float
    delta: float
    lipschitz: LipschitzConstant
    diameter: float | None = None
    certify: CheckedQuantity = "rollout"
    rule: StoppingRule = "sequential"
    policy: PolicyKind = PAPER_POLICY

    def __post_init__(self) -> None:
        check_spec_choices(
            self.condition, self.p, self.delta, self.policy, epsilon=self.epsilon, certify=self.certify, rule=self.rule
        )
        if self.condition == "ii" and (self.diameter is None or not self.diameter > 0):
            raise ValueError("condition (ii) needs diam(S0) > 0")

    def passes(self, checked: float | None) -> bool:
        """Whether one check passed: the checked quantity is known and at most epsilon (inf and NaN fail); for the
        success claim, the rollout met the criterion (SUCCESS_CHECK: 0), whatever epsilon."""
        if self.certify == "success":
            return checked == SUCCESS_CHECK[True]
        return checked is not None and checked <= self.epsilon

    # ------------------------------------------------------------------ the tests' budgets
    def test_delta(self, test: int) -> float:
        """The confidence test ``test`` (1-based) may spend."""
        if self.rule == "paper":
            return self.delta
        k = max(int(test), 1)
        return self.delta / (k * (k + 1))

    def streak_required(self, test: int) -> int:
        """Condition (i): the smallest integer n >= ln(1/delta_k) / (1 - p) for test k."""
        return math.ceil(math.log(1.0 / self.test_delta(test)) / (1.0 - self.p) - 1e-12)

    def quiet_episodes_required(self) -> int:
        """Condition (i) of the paper's one-shot test: n >= ln(1/delta) / (1 - p)."""
        return math.ceil(math.log(1.0 / self.delta) / (1.0 - self.p) - 1e-12)

    def hoeffding_required(self, mean_gap: float, delta: float | None = None) -> float:
        """Condition (ii): episodes needed for a window whose mean gap is ``mean_gap``."""
        margin = self.epsilon - mean_gap
        if margin <= 0:
            return math.inf
        assert self.diameter is not None
        spend = self.delta if delta is None else delta
        return 2 * self.lipschitz.value**2 * self.diameter**2 * math.log(1 / spend) / margin**2

    def statement(
        self, episodes_used: int, value: str, policy_trajectories: int, test: int, failures: int = 0,
        log_mixture: float | None = None,
    ) -> str:  # fmt: skip
        """The claim in words: about which value, for which policy, at which confidence."""
        acts = "its stored actions, open loop" if self.policy == "open-loop" else "its experts' feedback gains"
        policy = f"the greedy policy over the first {policy_trajectories} expert trajectories, acting with {acts}"
        if self.policy == "path":
            policy = (
                f"the path-following policy over the first {policy_trajectories} expert trajectories, which follows "
                "the stored trajectory it chose on V_lb step by step with its expert's feedback gains while the "
                "state stays near it, and chooses again on V_lb when it leaves"
            )
        gap = "V^E(s0) - R^pi(s0)" if self.certify == "oracle" else "V(s0) - R^pi(s0)"
        confidence = f"With probability at least {1 - self.delta:.4g}"
        how = f"test {test} of a sequentially valid rule" if self.rule == "sequential" else "the paper's one-shot rule"
        if self.certify == "success":  # ``value`` is the criterion in words
            return (
                f"{confidence}, P_(s0~rho)[the policy's rollout from s0 meets the task's success criterion] >= "
                f"{self.p:.4g} for {policy}, the criterion being {value} ("
                + (f"{episodes_used} checks with {failures} failed, verification {test} of the mixture rule"
                   if self.rule == "mixture" else f"{episodes_used} successful rollouts in a row, {how}")
                + "). It claims nothing about how well the policy does beside that criterion, nor about any "
                "expert's return."
            )  # fmt: skip
        if self.rule == "mixture":
            mixture = math.exp(log_mixture) if log_mixture is not None else math.nan
            return (
                f"{confidence}, P_(s0~rho)[{gap} <= {self.epsilon:.6g}] >= {self.p:.4g} for {policy}, where V is "
                f"{value} and R^pi the policy's own return over the same horizon ({episodes_used} checks of "
                f"{QUANTITY[self.certify]} with {failures} failed, verification {test} of the mixture rule: "
                f"M = {mixture:.4g} >= 1/delta_v = {1 / self.test_delta(test):.4g})."
            )
        if self.condition == "i":
            return (
                f"{confidence}, P_(s0~rho)[{gap} <= {self.epsilon:.6g}] >= {self.p:.4g} for {policy}, where V is "
                f"{value} and R^pi the policy's own return over the same horizon ({episodes_used} passed checks "
                f"of {QUANTITY[self.certify]} in a row, {how})."
            )
        return (
            f"{confidence}, E_(s0~rho)[{gap}] <= {self.epsilon:.6g} for {policy}, where V is {value} (mean of "
            f"{QUANTITY[self.certify]} over {episodes_used} episodes, {how}, diam(S0) = {self.diameter:.6g})."
        )

    def record(self) -> dict[str, Any]:
        """The spec as run files and messages name it: L by value and source; diam(S0) is the task's."""
        named = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("lipschitz", "diameter")}
        return {**named, "lipschitz": self.lipschitz.value, "lipschitz_source": self.lipschitz.source}


@dataclass(frozen=True)
class CertificationStatus:
    """Where the run stands.

    ``window`` is the streak of passed checks (i) or the window length (ii); ``required`` what the
    current test needs of it; ``test`` the current test (0 before the first policy exists) and
    ``test_delta`` the confidence it may spend. ``frozen``: the policy under test must stay as it is
    (trajectories are stored but held back). The mixture rule (mixture.py) fills ``stage``
    ("screen" or "verification"); in a verification ``window`` counts its checks, ``failures`` the
    failed ones, and ``log_mixture`` is ln M.

    ``episodes_to_certify`` is the fewest further episodes after which the rule could certify: every
    further check passing, which no failure can shorten (a failure starts a test that needs more).
    It is a lower bound, so a run with fewer episodes left cannot certify (``reachable_within``);
    None where the rule cannot tell (condition (ii): its need moves with the mean gap).
    """

    certified: bool
    window: int
    required: int
    quiet_episodes: int
    mean_gap: float | None = None
    test: int = 0
    test_delta: float = 0.0
    frozen: bool = False
    stage: str = ""
    failures: int = 0
    log_mixture: float | None = None
    episodes_to_certify: int | None = None

    def reachable_within(self, episodes_left: int) -> bool | None:
        """Whether a certificate may still come within ``episodes_left`` more episodes (None: cannot tell)."""
        if self.certified:
            return True
        return None if self.episodes_to_certify is None else self.episodes_to_certify <= episodes_left


@dataclass
class Certifier:
    """Feeds on one (checked gap, failed) pair per episode, in order.

    ``failed`` means the check did not pass and the policy changes (new data): the current test
    ends and the next one starts. Under the paper's rule ``failed`` is "the oracle was called".
    """

    spec: CertificationSpec
    gaps: list[float] = field(default_factory=list)
    quiet_episodes: int = 0
    tests: int = 0
    test_gaps: list[float] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.spec.rule == "mixture":
            raise ValueError("the mixture rule has its own certifier (npp_ros.mixture.certifier_for)")

    def observe(self, gap: float, failed: bool) -> CertificationStatus:
        self.gaps.append(float(gap))
        if failed:
            self.quiet_episodes = 0
            self.tests += 1
            self.test_gaps = []
        else:
            self.quiet_episodes += 1
            self.test_gaps.append(float(gap))
        return self.status()

    def preview(self, gap: float, failed: bool) -> CertificationStatus:
        """The status ``observe`` would return, without changing this certifier."""
        probe = Certifier(self.spec, list(self.gaps), self.quiet_episodes, self.tests, list(self.test_gaps))
        return probe.observe(gap, failed)

    def status(self) -> CertificationStatus:
        spec, test = self.spec, self.tests
        test_delta = spec.test_delta(test) if test else 0.0
        if spec.condition == "i":
            required = spec.streak_required(test) if spec.rule == "sequential" else spec.quiet_episodes_required()
            # Before any episode (test 0) the first check has no policy and fails; then test 1's streak.
            at_best = 1 + required if test == 0 else max(required - self.quiet_episodes, 0)
            return CertificationStatus(
                certified=test > 0 and self.quiet_episodes >= required,
                window=self.quiet_episodes,
                required=required,
                quiet_episodes=self.quiet_episodes,
                test=test,
                test_delta=test_delta,
                frozen=self.quiet_episodes > 0,
                episodes_to_certify=at_best,
            )
        if spec.rule == "sequential":
            return replace(self._hoeffding_within_test(test, test_delta), frozen=self.quiet_episodes > 0)
        return replace(self._hoeffding_best_window(test, test_delta), frozen=self.quiet_episodes > 0)

    def _hoeffding_within_test(self, test: int, test_delta: float) -> CertificationStatus:
        """All checks of the current test form the window; the n-th look spends delta_k / (n (n + 1))."""
        n = len(self.test_gaps)
        if n == 0 or test == 0:
            return CertificationStatus(False, 0, 0, self.quiet_episodes, None, test, test_delta)
        mean = float(np.mean(self.test_gaps))
        need = self.spec.hoeffding_required(mean, test_delta / (n * (n + 1)))
        required = math.ceil(need) if math.isfinite(need) else 0
        return CertificationStatus(n >= need, n, required, self.quiet_episodes, mean, test, test_delta)

    def _hoeffding_best_window(self, test: int, test_delta: float) -> CertificationStatus:
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
            test=test,
            test_delta=test_delta,
        )


@dataclass(frozen=True)
class Certificate:
    """The run's certificate: what it certifies (``spec``, for ``task``), what the run found, what it rests on."""

    task: str
    spec: CertificationSpec
    episodes: int
    oracle_calls: int
    dataset_size: int
    policy_trajectories: int
    window: int
    required: int
    test: int
    delta_spent: float
    value: str
    statement: str
    proven: bool
    assumptions: tuple[str, ...]
    failures: int = 0  # the mixture rule: failed checks of the certifying verification (window = its checks)
    mixture: float | None = None  # the mixture rule: M at certification (at least 1 / delta_spent)
    # The L the certified policy chooses its data point by, where the run chose it from its data
    # (npp_ros.run.policy_lipschitz); None: the claim's own L.
    policy_lipschitz: float | None = None

    def _lipschitz_lines(self) -> list[str]:
        """The L a claim rests on, and the one the policy chooses its data point by, where they are not one."""
        spec, lipschitz = self.spec, self.spec.lipschitz
        chosen = "" if self.policy_lipschitz is None else f"{self.policy_lipschitz:.6g} (chosen from the run's data)"
        picks = "it only picks the data point the policy follows"
        if spec.certify in L_FREE:
            own = chosen or f"{lipschitz.value:.6g} ({lipschitz.source})"
            return [f"  policy's L      {own}: {picks}; the claim rests on no L"]
        used = f"  L used          {lipschitz.value:.6g} ({lipschitz.source}, margin {lipschitz.margin:g})"
        return [used, *([f"  policy's L      {chosen}: {picks}"] if chosen else [])]

    def summary(self, label: str = "") -> str:
        """The certificate for people; ``label`` names the task (a task file's ``name`` key), and the task's
        identity (a task file's path and hash) then follows on a line of its own."""
        spec = self.spec
        proof = "yes" if self.proven else "NO: it rests on a step that does not hold here (see assumptions)"
        lines = [
            f"CERTIFICATE ({label or self.task}, condition ({spec.condition}), certify={spec.certify}, "
            f"rule={spec.rule})",
            *([f"  task            {self.task}"] if label and label != self.task else []),
            f"  episodes        {self.episodes}",
            f"  oracle calls    {self.oracle_calls}",
            f"  policy          {'path-following' if spec.policy == 'path' else 'greedy'} over "
            f"{self.policy_trajectories} trajectories ({self.dataset_size} triplets)",
            *self._lipschitz_lines(),
            f"  epsilon, p, delta  {spec.epsilon:g}, {spec.p:g}, {spec.delta:g}"
            if spec.certify != "success"
            else f"  p, delta        {spec.p:g}, {spec.delta:g} (no epsilon: the claim bounds no gap)",
            f"  checked         {QUANTITY[spec.certify]}",
            f"  value           {self.value}",
            f"  test            {self.test}, spent delta {self.delta_spent:.4g}",
            f"  window          {self.window} episodes (required {self.required})"
            if spec.rule != "mixture"
            else f"  verification    {self.window} checks, {self.failures} failed (required {self.required} at that "
            f"count), M = {self.mixture:.4g} >= 1/delta_v = {1 / self.delta_spent:.4g}",
            f"  proven          {proof}",
            f"  statement       {self.claim}",
        ]
        if self.success:
            lines.append(f"  success         {self.success}")
        lines.append("  assumptions")
        lines += [f"    - {text}" for text in self.assumptions]
        return "\n".join(lines)

    @property
    def claim(self) -> str:
        """The statement's claim, without what it says of the task's success."""
        return self.statement.partition(f" {SUCCESS_MARK}")[0]

    @property
    def success(self) -> str:
        """What the statement says of the task's success: how often the expert and the policy met the task's
        criterion, or that the task states none ("" in certificates from before success was measured)."""
        _, mark, rest = self.statement.partition(f" {SUCCESS_MARK}")
        return rest.removeprefix(",").removeprefix(":").strip() if mark else ""

    def record(self) -> dict[str, Any]:
        """One flat record of plain values: what the run file stores and the message carries."""
        found = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "spec"}
        spec = self.spec
        certified = {**spec.record(), "lipschitz_margin": spec.lipschitz.margin, "quantity": QUANTITY[spec.certify]}
        return {**found, **certified, "assumptions": list(self.assumptions)}

    @classmethod
    def from_record(cls, record: Mapping[str, Any], spec: CertificationSpec) -> Certificate:
        """Rebuild from a stored record, for the run ``spec`` describes (a resume has checked they agree).

        Records from before the mixture rule lack its fields and keep their defaults."""
        stored = [f.name for f in fields(cls) if f.name != "spec" and (f.name in record or f.default is MISSING)]
        found = {name: record[name] for name in stored}
        return cls(spec=spec, **{**found, "assumptions": tuple(found["assumptions"])})


def false_certificate_rate(
    spec: CertificationSpec, q: float, repetitions: int, seed: int, episodes: int = 1000
) -> float:
    """How often a rule certifies policies that each pass a check with probability q (< p: falsely).

    Every failed check replaces the policy by another one with the same q, as new data does in a
    run; the first episode has no policy. Condition (i) only.
    """
    rng = np.random.default_rng(seed)
    false = 0
    for _ in range(repetitions):
        certifier = Certifier(spec)
        certifier.observe(math.inf, failed=True)
        for passed in rng.random(episodes) < q:
            if certifier.observe(0.0 if passed else math.inf, failed=not passed).certified:
                false += 1
                break
    return false / repetitions


def assumption_list(items: Sequence[str | None]) -> tuple[str, ...]:
    return tuple(item for item in items if item)
