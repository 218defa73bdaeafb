"""The mixture rule's statistic, its thresholds, its futility line and its states, without a plant."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate, stats

from npp_ros.certificate.certifier import Certificate, CertificationSpec, Certifier
from npp_ros.certificate.mixture import (
    SCREEN_PASSES,
    VERIFICATION_BUDGET,
    MixtureCertifier,
    certifier_for,
    checks_to_certify,
    futility_failures,
    log_mixture,
)
from npp_ros.policy.lipschitz import LipschitzConstant

P, DELTA = 0.9, 0.1


def spec(**kw: object) -> CertificationSpec:
    base: dict[str, object] = {"condition": "i", "rule": "mixture", "certify": "rollout"}
    base.update(kw)
    return CertificationSpec(epsilon=50.0, p=P, delta=DELTA, lipschitz=LipschitzConstant(1.0, "user"), **base)  # type: ignore[arg-type]


def integral_mixture(checks: int, failures: int, p: float) -> float:
    """M(n, F) by its definition: the likelihood ratio averaged over Beta(1/2, 1/2) restricted to [p, 1]."""
    passes = checks - failures

    def weighted_ratio(theta: float) -> float:
        return stats.beta.pdf(theta, 0.5, 0.5) * (theta / p) ** passes * ((1 - theta) / (1 - p)) ** failures

    mass = stats.beta.sf(p, 0.5, 0.5)
    value, error = integrate.quad(weighted_ratio, p, 1.0, epsabs=0, epsrel=1e-11, limit=200)
    assert error <= 1e-9 * max(value, 1e-300)
    return value / mass


@pytest.mark.parametrize(
    ("checks", "failures", "p"),
    [(0, 0, 0.9), (1, 0, 0.9), (1, 1, 0.9), (5, 2, 0.9), (20, 0, 0.9), (36, 0, 0.9), (64, 1, 0.9), (30, 3, 0.8),
     (12, 1, 0.5)],
)  # fmt: skip
def test_closed_form_matches_the_integral_it_stands_for(checks: int, failures: int, p: float) -> None:
    assert math.exp(log_mixture(checks, failures, p)) == pytest.approx(integral_mixture(checks, failures, p), rel=1e-8)


def test_no_checks_is_no_evidence_and_a_pass_raises_m_by_less_than_1_over_p() -> None:
    assert log_mixture(0, 0, P) == pytest.approx(0.0, abs=1e-12)
    for failures in (0, 1, 5):
        for checks in range(failures, failures + 50):
            step = log_mixture(checks + 1, failures, P) - log_mixture(checks, failures, P)
            assert 0 < step <= -math.log(P) + 1e-12
    with pytest.raises(ValueError, match="failures <= checks"):
        log_mixture(3, 4, P)


def test_thresholds_are_the_smallest_certifying_counts() -> None:
    # The first verification (delta_1 = 0.05): 36 passes without failure, 64 with one, 744 with 50.
    assert [checks_to_certify(f, P, 0.05) for f in (0, 1, 2, 3, 5, 10, 20, 50)] == [36, 64, 86, 105, 140, 218, 359, 744]
    for v in (1, 2, 10, 30):
        delta_v = DELTA / (v * (v + 1))
        for failures in (0, 1, 7, 40):
            n = checks_to_certify(failures, P, delta_v)
            assert log_mixture(n, failures, P) >= math.log(1 / delta_v) > log_mixture(n - 1, failures, P)


def test_futility_line() -> None:
    # F >= 1 + 0.05 n + 2 sqrt(0.0475 n) at p = 0.9: the failures say q < 0.95.
    assert [math.ceil(futility_failures(n, P)) for n in (20, 50, 100, 200, 400, 800)] == [4, 7, 11, 18, 30, 54]
    assert futility_failures(100, 0.8) == pytest.approx(1 + 0.1 * 100 + 2 * math.sqrt(0.9 * 0.1 * 100))


def test_ville_bound_holds_exactly_for_a_policy_at_p() -> None:
    """Exact distribution of (n, F) for one verification at q = p, watched after every check with no
    futility stop: the chance of ever certifying within the budget stays below delta_v."""
    for v in (1, 3):
        delta_v = DELTA / (v * (v + 1))
        crossing: dict[int, list[int]] = {}  # n -> the failure counts that certify at the n-th check
        for failures in range(VERIFICATION_BUDGET + 1):
            n = checks_to_certify(failures, P, delta_v)
            if n > VERIFICATION_BUDGET:
                break
            crossing.setdefault(n, []).append(failures)
        alive = np.zeros(VERIFICATION_BUDGET + 1)
        alive[0] = 1.0  # P(F = f and not certified yet)
        certified = 0.0
        for n in range(1, VERIFICATION_BUDGET + 1):
            alive[1 : n + 1] = alive[1 : n + 1] * P + alive[:n] * (1 - P)
            alive[0] *= P
            at = crossing.get(n, [])
            certified += float(alive[at].sum())
            alive[at] = 0.0
        assert 0.5 * delta_v < certified <= delta_v  # nearly attained: the threshold cannot be lowered much


def feed(certifier: MixtureCertifier, outcomes: str) -> None:
    """'.' a passed check, 'x' a failed one."""
    for outcome in outcomes:
        certifier.observe(0.0 if outcome == "." else math.inf, failed=outcome == "x")


def test_a_screen_of_20_passes_in_a_row_starts_a_verification_that_does_not_count_them() -> None:
    certifier = MixtureCertifier(spec())
    feed(certifier, "x" + "." * 19 + "x")
    status = certifier.status()
    assert (status.stage, status.quiet_episodes, status.required, status.frozen) == ("screen", 0, 20, False)
    assert status.test_delta == 0.0 and not status.certified  # no delta spent while learning
    feed(certifier, "." * SCREEN_PASSES)
    status = certifier.status()
    assert (status.stage, status.test, status.window, status.failures, status.frozen) == ("verification", 1, 0, 0, True)
    assert status.test_delta == pytest.approx(0.05) and status.required == 36


def test_a_verification_certifies_at_its_threshold_despite_failures() -> None:
    certifier = MixtureCertifier(spec())
    feed(certifier, "." * SCREEN_PASSES + "x" + "." * 62)
    status = certifier.status()
    assert (status.window, status.failures, status.required, status.certified) == (63, 1, 64, False)
    status = certifier.observe(0.0, failed=False)
    assert status.certified and status.frozen and (status.window, status.failures) == (64, 1)
    assert status.log_mixture == pytest.approx(log_mixture(64, 1, P)) and status.log_mixture >= math.log(20)
    with pytest.raises(RuntimeError, match="certified"):
        certifier.observe(0.0, failed=False)


def test_preview_changes_nothing() -> None:
    certifier = MixtureCertifier(spec())
    feed(certifier, "." * 30)
    before = (certifier.streak, certifier.verification, certifier.checks, certifier.failures)
    assert certifier.preview(math.inf, failed=True).failures == 1
    assert (certifier.streak, certifier.verification, certifier.checks, certifier.failures) == before


def test_failures_on_the_futility_line_end_the_verification_and_the_next_one_spends_less() -> None:
    certifier = MixtureCertifier(spec())
    feed(certifier, "." * SCREEN_PASSES + "x")
    assert certifier.status().stage == "verification"  # F = 1 < 1 + 0.05 + 2 sqrt(0.0475) = 1.49
    feed(certifier, "x")  # F = 2 >= 1 + 0.1 + 2 sqrt(0.095) = 1.72
    assert certifier.ended == "futility" and certifier.checks == 2 and certifier.failures == 2
    status = certifier.status()
    assert (status.stage, status.quiet_episodes, status.frozen) == ("screen", 0, False)
    feed(certifier, "." * SCREEN_PASSES)
    status = certifier.status()
    assert status.test == 2 and status.test_delta == pytest.approx(DELTA / 6) and status.required == 48


def test_a_verification_gives_up_at_its_budget() -> None:
    # At p = 0.9 the futility line ends a verification before 3,000 checks unless delta_v is tiny.
    verification = 10**8
    failures = math.ceil(futility_failures(VERIFICATION_BUDGET, P)) - 1
    assert checks_to_certify(failures, P, DELTA / (verification * (verification + 1))) > VERIFICATION_BUDGET
    certifier = MixtureCertifier(
        spec(), verification=verification, verifying=True, checks=VERIFICATION_BUDGET - 1, failures=failures
    )
    status = certifier.observe(0.0, failed=False)
    assert certifier.ended == "budget" and status.stage == "screen" and not status.frozen and not status.certified


def test_the_rule_is_chosen_by_the_spec_and_refuses_condition_ii() -> None:
    assert isinstance(certifier_for(spec()), MixtureCertifier)
    assert isinstance(certifier_for(spec(rule="sequential")), Certifier)
    with pytest.raises(ValueError, match="its own certifier"):
        Certifier(spec())
    with pytest.raises(ValueError, match="mixture rule tests condition"):
        spec(condition="ii", diameter=1.0, certify="surrogate")


def test_a_certificate_record_from_before_the_mixture_rule_still_reads() -> None:
    old = {
        "task": "lqr_2_1", "episodes": 229, "oracle_calls": 32, "dataset_size": 32000, "policy_trajectories": 32,
        "window": 93, "required": 93, "test": 32, "delta_spent": 9.47e-05, "value": "V*_H", "statement": "...",
        "proven": True, "assumptions": ["a"],
    }  # fmt: skip
    certificate = Certificate.from_record(old, spec(rule="sequential"))
    assert (certificate.failures, certificate.mixture, certificate.window) == (0, None, 93)
    with pytest.raises(KeyError):
        Certificate.from_record({k: v for k, v in old.items() if k != "window"}, spec(rule="sequential"))
