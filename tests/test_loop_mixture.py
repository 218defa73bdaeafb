"""Algorithm 1 on lqr_2_1 under the mixture rule, in process: certificate, held-back data, resume."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from npp_ros.certificate.mixture import SCREEN_PASSES, checks_to_certify, log_mixture
from npp_ros.run.records import EpisodeRow, RunFileError
from npp_ros.run.setup import build_config, build_loop, resolve_lipschitz
from npp_ros.run.store import RunStore
from npp_ros.tasks.builtin.lqr import LQRExpert

HORIZON = 200  # short episodes keep the run to seconds; with them seed 0 needs two verifications


@pytest.fixture(scope="module")
def expert() -> LQRExpert:
    return LQRExpert("lqr_2_1", 0, horizon=HORIZON)


def config(expert: LQRExpert, certify: str = "rollout", rule: str = "mixture"):
    lipschitz = resolve_lipschitz("lqr_2_1", "analytic", expert)
    return build_config("lqr_2_1", 0, lipschitz, 50.0, horizon=HORIZON, certify=certify, rule=rule)  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def certified_run(tmp_path_factory, expert: LQRExpert):
    path = tmp_path_factory.mktemp("mixture") / "run.sqlite"
    loop = build_loop(config(expert), expert, store_path=path)
    result = loop.run(max_episodes=2000)
    loop.store.close()
    return path, loop, result


def test_the_loop_certifies_lqr_2_1_with_the_mixture_rule(certified_run) -> None:
    path, loop, result = certified_run
    cert = result.certificate
    assert cert is not None and cert.proven and cert.spec.rule == "mixture"
    v, n, failures = cert.test, cert.window, cert.failures
    assert cert.delta_spent == pytest.approx(0.1 / (v * (v + 1)))
    assert n == cert.required == checks_to_certify(failures, 0.9, cert.delta_spent)
    assert cert.mixture == pytest.approx(math.exp(log_mixture(n, failures, 0.9)))
    assert cert.mixture >= 1 / cert.delta_spent
    assert f"{failures} failed, verification {v} of the mixture rule" in cert.statement
    # The verification's checks are the last n episodes, after a screen of 20 passes in a row.
    verification = result.rows[-n:]
    assert all(r.test == v for r in verification) and sum(not r.checked_gap <= 50.0 for r in verification) == failures
    screen = result.rows[-n - SCREEN_PASSES : -n]
    assert all(r.checked_gap <= 50.0 and not r.oracle_called for r in screen)
    # Every failed check asked the expert at once and was stored; those of the verification were held
    # back from the policy it certifies.
    assert all(r.oracle_called == (not r.checked_gap <= 50.0) for r in result.rows)
    assert cert.oracle_calls == loop.dataset.num_trajectories == cert.policy_trajectories + failures
    assert all(r.dataset_size == cert.dataset_size for r in verification)
    with RunStore.open(path) as store:
        assert store.certificate() == cert.record()
        assert store.num_trajectories() == cert.oracle_calls
    record = cert.record()
    assert (record["rule"], record["test"], record["window"], record["failures"]) == ("mixture", v, n, failures)


def test_a_verification_that_gives_up_lets_its_held_data_join(certified_run) -> None:
    _, _, result = certified_run
    assert result.certificate is not None and result.certificate.test >= 2  # verification 1 gave up
    # A row reports the rule's state after its episode: verification 1 starts with the screen's last
    # pass (window 0) and its rows say test 1 until the check that ends it.
    first = [r for r in result.rows if r.test == 1]
    assert first[0].window == 0 and [r.window for r in first] == list(range(len(first)))
    ending = result.rows[first[-1].episode + 1]
    assert ending.test == 0 and ending.oracle_called  # the futility line is crossed by a failure
    held = [r for r in (*first, ending) if r.oracle_called]
    assert all(r.dataset_size == first[0].dataset_size for r in first)  # the policy's data stayed as they were
    assert ending.dataset_size == first[0].dataset_size + HORIZON * len(held)  # then every held trajectory joined


def test_resume_in_the_middle_of_a_verification_gives_the_uninterrupted_run(
    tmp_path: Path, certified_run, expert: LQRExpert
) -> None:
    _, full_loop, full = certified_run
    cert = full.certificate
    assert cert is not None and cert.failures >= 1
    last_failure = max(r.episode for r in full.rows[-cert.window :] if r.oracle_called)
    stop = last_failure + 3  # a held failure and two more checks into the verification
    path = tmp_path / "run.sqlite"
    first = build_loop(config(expert), expert, store_path=path)
    first.run(max_episodes=stop)
    held, policy_size = first.held_back, first.policy_data.num_trajectories
    assert held >= 1
    first.store.close()

    resumed = build_loop(config(expert), expert, store_path=path)
    assert resumed.next_episode == stop
    assert (resumed.held_back, resumed.policy_data.num_trajectories) == (held, policy_size)
    result = resumed.run(max_episodes=2000)
    resumed.store.close()

    def decisions(rows: list[EpisodeRow]) -> list[tuple[object, ...]]:
        return [(r.initial_state, r.checked_gap, r.oracle_called, r.dataset_size, r.test, r.window) for r in rows]

    assert decisions(result.rows) == decisions(full.rows)
    assert result.certificate == cert
    np.testing.assert_array_equal(resumed.dataset.states, full_loop.dataset.states)


def test_resume_under_another_rule_is_refused(certified_run, expert: LQRExpert) -> None:
    path, _, _ = certified_run
    before = path.read_bytes()
    with pytest.raises(RunFileError, match=r"rule: file has 'mixture', this run asks for 'sequential'"):
        build_loop(config(expert, rule="sequential"), expert, store_path=path)
    assert path.read_bytes() == before


def test_oracle_mode_holds_back_the_screen_and_the_verification(expert: LQRExpert) -> None:
    loop = build_loop(config(expert, certify="oracle"), expert)
    result = loop.run(max_episodes=2000)
    cert = result.certificate
    assert cert is not None and cert.spec.certify == "oracle"
    # Every episode asked the expert; the certified policy holds none of the screen's or the verification's.
    assert cert.oracle_calls == result.episodes == loop.dataset.num_trajectories
    assert cert.policy_trajectories <= result.episodes - SCREEN_PASSES - cert.window
    assert loop.held_back == 0  # after the certificate everything joined
