from __future__ import annotations

import math

import pytest

from npp_ros.certificate.certifier import CertificationSpec, Certifier
from npp_ros.policy.lipschitz import LipschitzConstant


def spec(condition: str = "i", **kw) -> CertificationSpec:
    """The paper's setting (surrogate gap, one-shot rule) unless a test asks for another."""
    base = {"epsilon": 50.0, "p": 0.9, "delta": 0.1, "lipschitz": 10.0, "diameter": 2.0}
    base.update({"certify": "surrogate", "rule": "paper"})
    base.update(kw)
    return CertificationSpec(condition, **{**base, "lipschitz": LipschitzConstant(base["lipschitz"], "user")})


def test_condition_i_needs_24_quiet_episodes_for_p_09_delta_01() -> None:
    assert spec().quiet_episodes_required() == 24  # ln(10) / 0.1 = 23.03


@pytest.mark.parametrize(("p", "delta"), [(0.5, 0.5), (0.95, 0.05), (0.99, 0.01), (0.8, 0.2)])
def test_condition_i_is_the_smallest_integer_at_least_the_bound(p: float, delta: float) -> None:
    n = spec(p=p, delta=delta).quiet_episodes_required()
    bound = math.log(1 / delta) / (1 - p)
    assert n >= bound - 1e-9 and n - 1 < bound


def test_streak_counts_consecutive_quiet_episodes_and_resets_on_new_data() -> None:
    cert = Certifier(spec())
    for _ in range(23):
        status = cert.observe(10.0, failed=False)
    assert (status.quiet_episodes, status.required, status.certified) == (23, 24, False)
    status = cert.observe(80.0, failed=True)
    assert status.quiet_episodes == 0 and not status.certified
    for _ in range(24):
        status = cert.observe(10.0, failed=False)
    assert status.certified and status.window == 24


def test_condition_ii_hoeffding_window() -> None:
    s = spec("ii", lipschitz=1.0, diameter=1.0, epsilon=1.0, delta=0.1)
    # mean gap 0.5: n >= 2 * 1 * 1 * ln(10) / 0.25 = 18.42 -> 19 episodes
    assert s.hoeffding_required(0.5) == pytest.approx(2 * math.log(10) / 0.25)
    cert = Certifier(s)
    for k in range(18):
        status = cert.observe(0.5, failed=(k == 0))
        assert not status.certified
    status = cert.observe(0.5, failed=False)
    assert status.certified and status.window == 19 and status.required == 19
    assert status.mean_gap == pytest.approx(0.5)


def test_condition_ii_ignores_windows_whose_mean_exceeds_epsilon() -> None:
    cert = Certifier(spec("ii", lipschitz=1.0, diameter=1.0, epsilon=1.0))
    status = cert.observe(math.inf, failed=True)
    assert not status.certified and status.required == 0
    for _ in range(40):
        status = cert.observe(0.1, failed=False)
    assert status.certified and status.window <= 40


@pytest.mark.parametrize(
    ("kw", "message"),
    [
        ({"p": 1.0}, "p must lie in"),
        ({"delta": 0.0}, "delta must lie in"),
        ({"epsilon": -1.0}, "epsilon"),
        ({"lipschitz": 0.0}, "Lipschitz"),
        ({"lipschitz": math.nan}, "Lipschitz"),
    ],
)
def test_invalid_specs_are_refused(kw, message) -> None:
    with pytest.raises(ValueError, match=message):
        spec(**kw)


def test_condition_ii_needs_a_diameter() -> None:
    with pytest.raises(ValueError, match="diam"):
        spec("ii", diameter=None)


def test_statement_names_the_guarantee_the_policy_and_the_rule() -> None:
    text = spec().statement(24, "V*", 7, 3)
    assert "0.9" in text and "<= 50" in text and "24" in text and "first 7 expert trajectories" in text
    assert "one-shot" in text
    sequential = spec(certify="rollout", rule="sequential").statement(93, "V*_H", 32, 32)
    assert "test 32 of a sequentially valid rule" in sequential and "V_ub(s0) + tail(s0) - R^pi(s0)" in sequential


def test_sequential_rule_spends_delta_over_tests_and_the_streak_grows() -> None:
    s = spec(certify="rollout", rule="sequential")
    spent = [s.test_delta(k) for k in range(1, 100_000)]
    assert sum(spent) < s.delta and sum(spent) == pytest.approx(s.delta, rel=1e-4)
    assert s.streak_required(1) == math.ceil(math.log(2 / 0.1) / 0.1)  # delta_1 = delta / 2: 30
    needs = [s.streak_required(k) for k in range(1, 200)]
    assert needs == sorted(needs) and needs[0] == 30
    for k in (1, 7, 50):
        n = s.streak_required(k)
        assert 0.9**n <= s.test_delta(k) < 0.9 ** (n - 12)  # e^{-(1-p) n} <= delta_k, and n is not wasteful


def test_sequential_streak_belongs_to_one_policy() -> None:
    cert = Certifier(spec(certify="rollout", rule="sequential"))
    status = cert.observe(math.inf, failed=True)  # episode 0: no policy; the first test starts
    assert (status.test, status.required, status.certified) == (1, 30, False)
    for _ in range(29):
        status = cert.observe(10.0, failed=False)
    assert (status.quiet_episodes, status.certified) == (29, False)
    status = cert.observe(80.0, failed=True)  # a failed check changes the policy: test 2, longer streak
    assert (status.test, status.quiet_episodes, status.required) == (2, 0, 41)
    for _ in range(41):
        status = cert.observe(10.0, failed=False)
    assert status.certified and status.test == 2 and status.test_delta == pytest.approx(0.1 / 6)


@pytest.mark.parametrize("certify", ["rollout", "oracle"])
def test_condition_ii_is_refused_where_hoeffding_has_no_range(certify: str) -> None:
    with pytest.raises(ValueError, match="known range"):
        spec("ii", certify=certify, rule="sequential")


def test_sequential_condition_ii_spends_per_look() -> None:
    s = spec("ii", lipschitz=1.0, diameter=1.0, epsilon=1.0, delta=0.1, rule="sequential")
    cert = Certifier(s)
    cert.observe(math.inf, failed=True)
    for n in range(1, 400):
        status = cert.observe(0.5, failed=False)
        need = 2 * math.log(n * (n + 1) / (s.delta / 2)) / 0.25
        assert status.certified == (n >= need)
        if status.certified:
            break
    assert status.certified and status.window > 19  # the paper's one-shot window would be 19


def test_unknown_mode_and_rule_are_refused() -> None:
    with pytest.raises(ValueError, match="certify must be one of rollout, oracle, surrogate"):
        spec(certify="vibes")
    with pytest.raises(ValueError, match="rule must be one of sequential, mixture, paper"):
        spec(rule="sometimes")
