from __future__ import annotations

import math

import pytest

from npp_ros.certification import CertificationSpec, Certifier


def spec(condition: str = "i", **kw) -> CertificationSpec:
    base = {"epsilon": 50.0, "p": 0.9, "delta": 0.1, "lipschitz": 10.0, "diameter": 2.0}
    base.update(kw)
    return CertificationSpec(condition, **base)


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
        status = cert.observe(10.0, oracle_called=False)
    assert (status.quiet_episodes, status.required, status.certified) == (23, 24, False)
    status = cert.observe(80.0, oracle_called=True)
    assert status.quiet_episodes == 0 and not status.certified
    for _ in range(24):
        status = cert.observe(10.0, oracle_called=False)
    assert status.certified and status.window == 24


def test_condition_ii_hoeffding_window() -> None:
    s = spec("ii", lipschitz=1.0, diameter=1.0, epsilon=1.0, delta=0.1)
    # mean gap 0.5: n >= 2 * 1 * 1 * ln(10) / 0.25 = 18.42 -> 19 episodes
    assert s.hoeffding_required(0.5) == pytest.approx(2 * math.log(10) / 0.25)
    cert = Certifier(s)
    for k in range(18):
        status = cert.observe(0.5, oracle_called=(k == 0))
        assert not status.certified
    status = cert.observe(0.5, oracle_called=False)
    assert status.certified and status.window == 19 and status.required == 19
    assert status.mean_gap == pytest.approx(0.5)


def test_condition_ii_ignores_windows_whose_mean_exceeds_epsilon() -> None:
    cert = Certifier(spec("ii", lipschitz=1.0, diameter=1.0, epsilon=1.0))
    status = cert.observe(math.inf, oracle_called=True)
    assert not status.certified and status.required == 0
    for _ in range(40):
        status = cert.observe(0.1, oracle_called=False)
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


def test_statement_names_the_guarantee_and_its_assumption() -> None:
    text = spec().statement(24)
    assert "0.9" in text and "<= 50" in text and "10-Lipschitz" in text and "24" in text
