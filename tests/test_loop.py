"""Algorithm 1 end to end on lqr_2_1, in process: certification, persistence, resume."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from npp_ros.certificate.certifier import Certificate, CertificationStatus
from npp_ros.policy.lipschitz import LipschitzWarning
from npp_ros.run.loop import Observer
from npp_ros.run.records import EpisodeRow, RunFileError
from npp_ros.run.setup import build_config, build_loop, lipschitz_checks, resolve_lipschitz
from npp_ros.run.store import RunStore
from npp_ros.tasks.builtin.lqr import LQRExpert

# Episodes of 300 steps: lqr_2_1 seed 0 certifies after some 370 episodes, as it does at the task's 1000 steps
# (about 420), in a quarter of the time.
HORIZON = 300


@pytest.fixture(scope="module")
def expert() -> LQRExpert:
    return LQRExpert("lqr_2_1", seed=0, horizon=HORIZON)


class Recorder(Observer):
    def __init__(self) -> None:
        self.rows: list[EpisodeRow] = []
        self.certificates: list[Certificate] = []

    def on_episode(self, row: EpisodeRow, status: CertificationStatus) -> None:
        self.rows.append(row)

    def on_certificate(self, certificate: Certificate) -> None:
        self.certificates.append(certificate)


@pytest.fixture(scope="module")
def certified_run(tmp_path_factory, expert: LQRExpert):
    path = tmp_path_factory.mktemp("run") / "run.sqlite"
    config = build_config("lqr_2_1", 0, resolve_lipschitz("lqr_2_1", "analytic", expert), 50.0, horizon=HORIZON)
    recorder = Recorder()
    loop = build_loop(config, expert, store_path=path, observers=[recorder])
    result = loop.run(max_episodes=1000)
    loop.store.close()
    return config, path, loop, result, recorder


def test_certifies_lqr_2_1_with_a_valid_lipschitz_constant(certified_run) -> None:
    config, _, loop, result, recorder = certified_run
    cert = result.certificate
    assert cert is not None and recorder.certificates == [cert]
    assert cert.spec == config.spec and cert.spec.lipschitz.source == "lqr-analytic"
    # The default: the rollout check under the sequentially valid rule; test k needs ln(1/delta_k) / (1 - p).
    assert (cert.spec.certify, cert.spec.rule, cert.proven) == ("rollout", "sequential", True)
    assert cert.window == cert.required == config.spec.streak_required(cert.test)
    assert cert.delta_spent == pytest.approx(0.1 / (cert.test * (cert.test + 1)))
    assert cert.episodes == result.episodes == len(recorder.rows)
    assert cert.oracle_calls == sum(r.oracle_called for r in result.rows) == loop.dataset.num_trajectories
    assert cert.dataset_size == HORIZON * cert.oracle_calls == HORIZON * cert.policy_trajectories
    assert all(not r.oracle_called for r in result.rows[-cert.window :])
    # The oracle is called exactly when the check fails, and every check saw the policy's own return.
    assert all(r.oracle_called == (r.checked_gap > 50.0) for r in result.rows)
    assert all(r.policy_return is not None for r in result.rows[1:])
    # The check is never below the surrogate bound's own quantity V_ub + tail - V^pi for this policy.
    assert all(r.checked_gap >= r.v_ub - r.policy_return for r in result.rows[1:])
    assert any("Riccati" in a for a in cert.assumptions) and "V*_H" in cert.value


def test_every_oracle_call_is_stored_with_its_episode(certified_run) -> None:
    _, path, loop, result, _ = certified_run
    with RunStore.open(path) as store:
        stored = store.load_dataset()
        rows = store.episodes()
        assert store.certificate()["episodes"] == result.episodes
    np.testing.assert_array_equal(stored.states, loop.dataset.states)
    assert rows == result.rows


def test_resume_after_interruption_gives_identical_numbers(tmp_path: Path, certified_run, expert) -> None:
    config, _, _, full, _ = certified_run
    path = tmp_path / "run.sqlite"
    first = build_loop(config, expert, store_path=path)
    first.run(max_episodes=60)
    first.store.close()
    resumed = build_loop(config, expert, store_path=path)
    assert resumed.next_episode == 60
    result = resumed.run(max_episodes=1000)
    resumed.store.close()
    strip = [(r.initial_state, r.gap, r.checked_gap, r.oracle_called, r.dataset_size) for r in result.rows]
    assert strip == [(r.initial_state, r.gap, r.checked_gap, r.oracle_called, r.dataset_size) for r in full.rows]
    assert result.certificate == full.certificate


def test_resuming_a_certified_run_reports_its_certificate_without_new_episodes(certified_run, expert) -> None:
    config, path, _, full, _ = certified_run
    again = build_loop(config, expert, store_path=path)
    assert again.certificate == full.certificate
    assert again.run(max_episodes=5000).episodes == full.episodes
    again.store.close()


def test_resume_with_other_settings_is_refused_and_the_file_is_untouched(certified_run, expert) -> None:
    config, path, _, _, _ = certified_run
    before = path.read_bytes()
    other = build_config("lqr_2_1", 0, config.spec.lipschitz, 40.0, horizon=HORIZON)
    with pytest.raises(RunFileError, match=r"epsilon: file has 50.0, this run asks for 40.0"):
        build_loop(other, expert, store_path=path)
    assert path.read_bytes() == before


def test_paper_lipschitz_is_flagged(expert_2_1: LQRExpert) -> None:
    config = build_config("lqr_2_1", 0, resolve_lipschitz("lqr_2_1", "paper", expert_2_1), 50.0)
    assert config.spec.lipschitz.value == 50.0 and config.spec.lipschitz.source == "paper"
    loop = build_loop(config, expert_2_1)
    loop.run(max_episodes=30)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        checks = lipschitz_checks(loop, expert_2_1)
    assert not all(c.ok for c in checks)
    assert any(issubclass(w.category, LipschitzWarning) and "not a guarantee" in str(w.message) for w in caught)


def test_oracle_returning_bad_data_fails_loudly_and_stores_nothing(tmp_path: Path, expert_2_1: LQRExpert) -> None:
    class BrokenExpert:
        def trajectory(self, s0):
            t = expert_2_1.trajectory(s0, horizon=5)
            t.values[2] = np.nan
            return t

    config = build_config("lqr_2_1", 0, resolve_lipschitz("lqr_2_1", "analytic", expert_2_1), 50.0)
    loop = build_loop(config, expert_2_1, store_path=tmp_path / "run.sqlite")
    loop.oracle = BrokenExpert()
    with pytest.raises(ValueError, match=r"values\[2\] is nan"):
        loop.run_episode()
    assert loop.store.num_trajectories() == 0 and loop.store.episodes() == []
