"""The ``mixture`` stopping rule: screen a policy, then verify it with a failure-tolerant test.

Under the ``sequential`` rule one failed check ends a test, the policy changes and the next test
pays a smaller delta_k, so a policy whose success rate q is in (p, 0.95] is rarely certified and
every test spends delta on a policy that is still learning. The mixture rule spends delta only on
policies that already look good, and a failure no longer throws a test away:

1. **Learning.** As under the streak rule: a failed check's trajectory joins the policy at once
   (in oracle mode the trajectories of passed checks are held back while the streak lasts). No
   delta is spent, and no policy of this phase is ever certified.
2. **Screen.** When the current policy has passed ``SCREEN_PASSES`` (20) checks in a row it is
   frozen and verification v (v = 1, 2, ...) starts with delta_v = delta / (v (v + 1)). The
   screen's own checks do not count in the verification.
3. **Verification.** Every check's trajectory (failures included; in oracle mode all of them) is
   asked for and stored at once, but joins the policy only when the verification ends. After its
   n-th check with F failures (S = n - F passes) the verification
   - certifies the frozen policy when log M(n, F) >= ln(1 / delta_v);
   - gives up when F >= 1 + (1 - q_f) n + 2 sqrt(q_f (1 - q_f) n), q_f = (1 + p) / 2 (the
     failures say q is below q_f, 0.95 at p = 0.9), or when n reaches ``VERIFICATION_BUDGET``;
     the held trajectories then join, and learning resumes;
   - goes on otherwise.

M is the average of the likelihood ratios of q = theta against q = p over a Jeffreys prior
Beta(1/2, 1/2) truncated to [p, 1], in closed form (B the beta function, P(Beta(a, b) >= p) the
upper tail of the regularized incomplete beta function):

    M(n, F) = B(S + 1/2, F + 1/2) P(Beta(S + 1/2, F + 1/2) >= p)
              / [B(1/2, 1/2) P(Beta(1/2, 1/2) >= p) p^S (1 - p)^F]

**Why it is valid (proof sketch).** Each episode's s0 is drawn from rho independently of the run
so far, and the policy of a verification is fixed before any of its s0 is drawn. Let X_i = 1 when
check i passes; a pass implies a true gap <= epsilon, so for a frozen policy whose share of s0
within epsilon is q, P(X_i = 1 | past) <= q. For theta in [p, 1] the factor
f_theta(x) = (theta / p)^x ((1 - theta) / (1 - p))^(1 - x) equals 1 + lambda (x - p) with
lambda >= 0, so when q <= p, E[f_theta(X_i) | past] <= 1: the product of the f_theta over a
verification's checks is a nonnegative supermartingale starting at 1, and so is M, its average
over a prior fixed before the run. Ville's inequality gives P(M ever reaches 1 / delta_v) <=
delta_v, whatever stopping rule is applied meanwhile: looking after every check, giving up for
futility or budget, a shutdown and a resume cost nothing, and failures are tolerated. Giving up
only removes chances to certify, so it can never make a false certificate more likely.
Verifications start at stopping times (the screen lies in the past and its checks are not
counted) and each uses only its own later checks, so each is bounded by its delta_v; learning
policies are never certified; a union bound over verifications gives a false certificate with
probability at most sum_v delta_v = delta. The screen length, the futility line and the budget
are efficiency choices and cannot break this; the prior and the delta_v schedule are fixed here,
before any run.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import special

from npp_ros.certificate.certifier import CertificationSpec, CertificationStatus, Certifier

SCREEN_PASSES = 20  # a policy's passes in a row before a verification may spend delta on it
VERIFICATION_BUDGET = 3000  # checks after which a verification gives up
PRIOR = (0.5, 0.5)  # Jeffreys Beta(1/2, 1/2), truncated to [p, 1]
RULE_DETAIL = (
    f"screen of {SCREEN_PASSES} passes in a row, then a mixture likelihood-ratio test over a Jeffreys prior "
    "Beta(1/2, 1/2) on [p, 1], certifying when M >= 1 / delta_v with delta_v = delta / (v (v + 1)); "
    f"a verification gives up when its failures show q < (1 + p) / 2 or after {VERIFICATION_BUDGET} checks"
)


def _log_upper_tail(a: float, b: float, p: float) -> float:
    """ln P(Beta(a, b) >= p); -inf where the tail underflows (M is then far below any threshold)."""
    tail = float(special.betaincc(a, b, p))
    return math.log(tail) if tail > 0 else -math.inf


@functools.lru_cache(maxsize=1 << 16)
def log_mixture(checks: int, failures: int, p: float) -> float:
    """ln M(n, F): the Jeffreys mixture of likelihood ratios after n checks with F failures."""
    if not 0 <= failures <= checks:
        raise ValueError(f"need 0 <= failures <= checks, got {failures} of {checks}")
    passes = checks - failures
    a, b = PRIOR
    numerator = special.betaln(passes + a, failures + b) + _log_upper_tail(passes + a, failures + b, p)
    prior_mass = special.betaln(a, b) + _log_upper_tail(a, b, p)
    return float(numerator - prior_mass - passes * math.log(p) - failures * math.log1p(-p))


@functools.lru_cache(maxsize=1 << 14)
def checks_to_certify(failures: int, p: float, delta_v: float) -> int:
    """The smallest n at which a verification with F failures certifies (M grows with every pass)."""
    threshold = math.log(1.0 / delta_v)
    low, high = failures, max(failures, 1)
    while log_mixture(high, failures, p) < threshold:
        low, high = high, 2 * high
    while high - low > 1:  # log M(low) < threshold <= log M(high), or low = high = failures
        middle = (low + high) // 2
        low, high = (middle, high) if log_mixture(middle, failures, p) < threshold else (low, middle)
    return high if log_mixture(low, failures, p) < threshold else low


def futility_failures(checks: int, p: float) -> float:
    """Failures at which a verification of n checks gives up: q looks below q_f = (1 + p) / 2."""
    target = (1.0 + p) / 2.0
    return 1.0 + (1.0 - target) * checks + 2.0 * math.sqrt(target * (1.0 - target) * checks)


@dataclass
class MixtureCertifier:
    """The mixture rule's state: a screen streak while learning, then (n, F) of verification v.

    Feeds on one (checked gap, failed) pair per episode, in the order the episodes ran, like
    ``Certifier``; ``failed`` means the check did not pass. Whether the failure changes the policy
    is this rule's decision, which ``status().frozen`` reports.
    """

    spec: CertificationSpec
    streak: int = 0  # learning: passes in a row of the current policy
    verification: int = 0  # verifications started so far (the current one's v while verifying)
    verifying: bool = False
    checks: int = 0  # the current (or last) verification's n ...
    failures: int = 0  # ... and F
    certified: bool = False
    ended: str = ""  # why the last verification gave up: "futility", "budget" or "" (it has not)

    def __post_init__(self) -> None:
        if self.spec.rule != "mixture" or self.spec.condition != "i":
            raise ValueError("the mixture certifier runs the mixture rule on condition (i)")

    def step(self, failed: bool) -> None:
        """One check of the policy in use; the status follows from the new state."""
        if self.certified:
            raise RuntimeError("the run is certified: no check comes after the certificate")
        if not self.verifying:
            self.streak = 0 if failed else self.streak + 1
            if self.streak >= SCREEN_PASSES:
                self.verification += 1
                self.verifying, self.checks, self.failures, self.ended = True, 0, 0, ""
            return
        self.checks += 1
        self.failures += int(failed)
        p, delta_v = self.spec.p, self.spec.test_delta(self.verification)
        if self.checks >= checks_to_certify(self.failures, p, delta_v):
            self.certified = True
        elif self.failures >= futility_failures(self.checks, p) or self.checks >= VERIFICATION_BUDGET:
            self.ended = "futility" if self.checks < VERIFICATION_BUDGET else "budget"
            self.verifying, self.streak = False, 0

    def observe(self, gap: float, failed: bool) -> CertificationStatus:
        self.step(failed)
        return self.status()

    def preview(self, gap: float, failed: bool) -> CertificationStatus:
        """The status ``observe`` would return, without changing this certifier."""
        probe = MixtureCertifier(
            self.spec, self.streak, self.verification, self.verifying, self.checks, self.failures,
            self.certified, self.ended,
        )  # fmt: skip
        return probe.observe(gap, failed)

    @property
    def frozen(self) -> bool:
        """The policy must stay as it is: a verification runs, or a screen streak holds (oracle mode)."""
        return self.verifying or self.certified or self.streak > 0

    def episodes_to_certify(self) -> int:
        """The fewest further checks after which this rule could certify (a lower bound, see CertificationStatus).

        Screening: the screen's passes still missing, then the next verification's checks with no failure.
        Verifying: the fewer of this verification's checks still needed with no more failures, and giving it
        up (at least one more failure), a new screen and the next verification with no failure."""
        p, spec = self.spec.p, self.spec
        if self.certified:
            return 0
        if not self.verifying:
            return SCREEN_PASSES - self.streak + checks_to_certify(0, p, spec.test_delta(self.verification + 1))
        here = checks_to_certify(self.failures, p, spec.test_delta(self.verification)) - self.checks
        if here > VERIFICATION_BUDGET - self.checks:
            here = math.inf  # beyond the budget: this verification gives up first
        again = 1 + SCREEN_PASSES + checks_to_certify(0, p, spec.test_delta(self.verification + 1))
        return int(min(here, again))

    def status(self) -> CertificationStatus:
        if self.verifying or self.certified:
            v, n, f = self.verification, self.checks, self.failures
            delta_v = self.spec.test_delta(v)
            return CertificationStatus(
                certified=self.certified,
                window=n,
                required=checks_to_certify(f, self.spec.p, delta_v),
                quiet_episodes=n,
                test=v,
                test_delta=delta_v,
                frozen=True,
                stage="verification",
                failures=f,
                log_mixture=log_mixture(n, f, self.spec.p),
                episodes_to_certify=self.episodes_to_certify(),
            )
        return CertificationStatus(
            certified=False,
            window=self.streak,
            required=SCREEN_PASSES,
            quiet_episodes=self.streak,
            frozen=self.streak > 0,
            stage="screen",
            episodes_to_certify=self.episodes_to_certify(),
        )


def certifier_for(spec: CertificationSpec, *, with_policy: bool = False) -> Certifier | MixtureCertifier:
    """The certifier of the spec's stopping rule; ``with_policy``: the run starts with data (another run's), so its
    first check is already a test of a policy (the first test, spending delta_1), not the check no policy can pass."""
    if spec.rule == "mixture":
        return MixtureCertifier(spec)
    return Certifier(spec, tests=1 if with_policy else 0)


# ---------------------------------------------------------------------- the rules, simulated
SuccessRate = Callable[[int], float]  # a policy's true success rate, by the trajectories it holds


@dataclass(frozen=True)
class SimulatedRun:
    """One simulated run: how long it took, and whether and what it certified."""

    checks: int  # episodes (checks) until the certificate or the budget
    expert_calls: int  # trajectories asked for: failed checks, or every check in oracle mode
    failures: int
    certified: bool
    certified_rate: float  # the certified policy's true success rate (nan without a certificate)


def simulate_run(
    spec: CertificationSpec,
    success_rate: SuccessRate,
    rng: np.random.Generator,
    max_checks: int,
    every_check_asks: bool = False,
) -> SimulatedRun:
    """A run of the spec's rule on policies that pass a check with the success rate of their data.

    The first episode has no policy (a failed check), as in a run. A failed check's trajectory (and
    in oracle mode, ``every_check_asks``, every check's) is stored, and joins the policy whenever
    the rule no longer holds it frozen; the policy's success rate is ``success_rate(joined)``.
    The simulation feeds the certifier the checks' outcomes only: no plant, no expert.
    """
    certifier = certifier_for(spec)
    joined = stored = failures = 0
    for episode in range(max_checks):
        rate = success_rate(joined) if episode else 0.0
        failed = not rng.random() < rate
        failures += failed
        stored += failed or every_check_asks
        if isinstance(certifier, MixtureCertifier):  # the same decisions as observe(), without a status each time
            certifier.step(failed)
            certified, frozen = certifier.certified, certifier.frozen
        else:
            status = certifier.observe(math.inf if failed else 0.0, failed)
            certified, frozen = status.certified, status.frozen
        if certified:
            return SimulatedRun(episode + 1, stored, failures, True, rate)
        if not frozen:
            joined = stored
    return SimulatedRun(max_checks, stored, failures, False, math.nan)


def false_certificate_rate(
    spec: CertificationSpec, q: float, repetitions: int, seed: int, episodes: int = 1000
) -> float:
    """How often the rule certifies policies that each pass a check with probability q (<= p: falsely).

    Every policy has the same q, so every certificate is false when q <= p; condition (i) only.
    """
    rng = np.random.default_rng(seed)
    runs = [simulate_run(spec, lambda joined: q, rng, episodes) for _ in range(repetitions)]
    return sum(run.certified for run in runs) / repetitions
