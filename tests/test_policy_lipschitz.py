"""The policy's own L, chosen from the run's data (policy_lipschitz select): made at each doubling of the policy's
data, the same when the run is resumed or derived again, kept in the run file under its seal, named by the
certificate, acted by wherever the run's policy is rebuilt, and refused where the claim would not hold for it."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np
import pytest
from deploy_runs import EPSILON, HORIZON, SEED, TASK, stored_run

from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import Dataset, Trajectory
from npp_ros.run.loop import RunConfig
from npp_ros.run.policy_lipschitz import LADDER, HeldOutStart, choice_point, choose_lipschitz
from npp_ros.run.read import read_run
from npp_ros.run.records import RunFileError
from npp_ros.run.rederive import rederive
from npp_ros.run.request import RunRequest
from npp_ros.run.seal import write_seal
from npp_ros.run.setup import build_config, build_loop, resolve_lipschitz
from npp_ros.run.store import RunStore
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.success import SuccessCriterion

EPISODES = 40
FIRST_CHOICE = "trajectories = (SELECT MIN(trajectories) FROM lipschitz_choices)"  # the run's first choice


def select_config(policy_lipschitz: str = "select") -> tuple[RunConfig, object]:
    """lqr_2_1 at H = 100, oracle checks, the paper's open-loop policy (its checks fail now and then, so the data
    grows past a few choice points within tens of episodes)."""
    expert = get_task(TASK).make_expert(SEED, HORIZON)
    lipschitz = resolve_lipschitz(TASK, "analytic", expert)
    config = build_config(
        TASK, SEED, lipschitz, EPSILON, horizon=HORIZON, certify="oracle", policy="open-loop",
        policy_lipschitz=policy_lipschitz,
    )  # fmt: skip
    return config, expert


@pytest.fixture(scope="module")
def selected(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("select") / "run"
    config, expert = select_config()
    stored_run(config, expert, folder, EPISODES)  # type: ignore[arg-type]
    return folder


def test_choice_points_are_the_doublings_from_four() -> None:
    assert [choice_point(n) for n in (0, 1, 3, 4, 5, 7, 8, 15, 16, 33)] == [0, 0, 0, 4, 4, 4, 8, 8, 16, 32]


def test_a_run_chooses_where_its_policy_grows_keeps_it_sealed_and_its_policy_acts_by_it(selected: Path) -> None:
    run = read_run(selected)
    trajectories = run.dataset.num_trajectories
    assert trajectories >= 4, "the run must reach a choice point for this test to say anything"
    assert run.lipschitz_choices, "the policy's data passed a choice point"
    claim = run.spec.lipschitz.value
    for point, choice in run.lipschitz_choices.items():
        assert choice_point(point) == point and choice.trajectories == point  # a doubling from 4
        assert [score.lipschitz for score in choice.scores] == pytest.approx([claim * f for f in LADDER])
        assert choice.value in [score.lipschitz for score in choice.scores]
        assert 0 < choice.starts <= 32
    last = max(point for point in run.lipschitz_choices if point <= choice_point(trajectories))
    assert run.policy.lipschitz == run.lipschitz_choices[last].value
    assert run.spec.lipschitz.value == claim  # the claim's L stays the claim's
    assert not run.seal.mismatches


def test_a_resumed_run_chooses_as_one_that_ran_through(selected: Path, tmp_path: Path) -> None:
    config, expert = select_config()
    stored_run(config, expert, tmp_path / "r", 13)  # type: ignore[arg-type]
    stored_run(config, expert, tmp_path / "r", EPISODES)  # type: ignore[arg-type]
    resumed, through = read_run(tmp_path / "r"), read_run(selected)
    assert [row.checked_gap for row in resumed.episodes] == [row.checked_gap for row in through.episodes]
    assert {k: c.value for k, c in resumed.lipschitz_choices.items()} == {
        k: c.value for k, c in through.lipschitz_choices.items()
    }


def test_a_run_derived_again_chooses_the_same_and_a_resealed_choice_is_named(selected: Path, tmp_path: Path) -> None:
    assert rederive(read_run(selected)).agrees
    edited = tmp_path / "edited"
    edited.mkdir()
    (edited / "run.sqlite").write_bytes((selected / "run.sqlite").read_bytes())
    with sqlite3.connect(edited / "run.sqlite") as conn:
        conn.execute(f"UPDATE lipschitz_choices SET value = value * 7 WHERE {FIRST_CHOICE}")
        write_seal(conn)  # anyone with this code can reseal: the derivation still tells
    found = rederive(read_run(edited))
    assert not found.agrees
    assert "the policy's L chosen at" in found.differences[0]


def test_an_unsealed_edit_of_a_choice_is_refused_naming_it(selected: Path, tmp_path: Path) -> None:
    copy = tmp_path / "run.sqlite"
    copy.write_bytes((selected / "run.sqlite").read_bytes())
    with sqlite3.connect(copy) as conn:
        conn.execute(f"UPDATE lipschitz_choices SET value = 1.0 WHERE {FIRST_CHOICE}")
    with pytest.raises(RunFileError, match=r"lipschitz_choices\.value"):
        read_run(copy)


def test_a_resume_asking_for_the_claims_l_is_refused_naming_the_setting(selected: Path, tmp_path: Path) -> None:
    copy = tmp_path / "r"
    copy.mkdir()
    (copy / "run.sqlite").write_bytes((selected / "run.sqlite").read_bytes())
    config, expert = select_config("claim")
    with pytest.raises(RunFileError, match=r"policy_lipschitz: file has 'select', this run asks for 'claim'"):
        build_loop(config, expert, store_path=copy / "run.sqlite")  # type: ignore[arg-type]


def test_a_file_from_before_the_choice_reads_as_acting_by_the_claims_l(tmp_path: Path) -> None:
    config, expert = select_config("claim")
    stored_run(config, expert, tmp_path / "old", 20)  # type: ignore[arg-type]
    with sqlite3.connect(tmp_path / "old" / "run.sqlite") as conn:
        conn.execute("DELETE FROM meta WHERE key = 'policy_lipschitz'")
        write_seal(conn)
    with RunStore.open(tmp_path / "old" / "run.sqlite") as store:
        assert store.metadata.policy_lipschitz == "claim"
    run = read_run(tmp_path / "old")
    assert run.policy.lipschitz == run.spec.lipschitz.value and not run.lipschitz_choices


def test_a_surrogate_claim_refuses_a_selected_l_at_the_request() -> None:
    with pytest.raises(ValueError, match="surrogate claim's V_ub - V_lb speaks of the policy greedy on the claim"):
        RunRequest(task=TASK, certify="surrogate", policy_lipschitz="select")
    with pytest.raises(ValueError, match="policy_lipschitz must be one of claim, select"):
        RunRequest(task=TASK, policy_lipschitz="nearest")


def test_the_certificate_names_the_policys_l_where_the_run_chose_it(tmp_path: Path) -> None:
    config, expert = select_config()
    result = stored_run(config, expert, tmp_path / "c", 300)  # type: ignore[arg-type]
    assert result.certificate is not None
    run = read_run(tmp_path / "c")
    point = choice_point(result.certificate.policy_trajectories)
    if point:
        assert result.certificate.policy_lipschitz == run.lipschitz_choices[point].value
        assert "policy's L" in result.certificate.summary()
    else:
        assert result.certificate.policy_lipschitz is None
    assert run.policy.lipschitz == (result.certificate.policy_lipschitz or run.spec.lipschitz.value)


def test_the_choice_moves_off_the_claims_l_on_more_successes_only() -> None:
    """Most successes wins; a tie keeps the claim's L whatever the returns say; without a criterion, return decides.
    The rollouts here are a rule of the candidate's L (the policy's own), so each outcome is known in advance."""
    data = Dataset(1, 1)
    for k in range(4):
        data.append(Trajectory(np.array([[float(k)]]), np.array([[0.0]]), np.array([1.0])))
    starts = [HeldOutStart(np.array([0.5 + k]), None, (k,)) for k in range(3)]
    criterion = SuccessCriterion("the state ends above 0", lambda states: bool(states[-1, 0] > 0), steps=1)

    def build(data: Dataset, lipschitz: float) -> NonparametricPolicy:
        return NonparametricPolicy(data, lipschitz)

    def chooser(met: dict[float, bool], returns: dict[float, float]):  # outcome per factor of the claim's L
        def run(state, policy, robot):
            factor = round(policy.lipschitz / 2.0, 6)
            return np.array([[1.0 if met[factor] else -1.0]]), returns[factor]

        return run

    flat = {f: 1.0 for f in LADDER}
    higher = {f: 1.0 + f for f in LADDER}  # a larger L always returns a little more
    everyone = {f: True for f in LADDER}
    assert choose_lipschitz(data, starts, 2.0, build, chooser(everyone, higher), criterion).value == 2.0  # tie: claim
    only_big = {f: f >= 100 for f in LADDER}
    assert choose_lipschitz(data, starts, 2.0, build, chooser(only_big, flat), criterion).value == 200.0
    assert choose_lipschitz(data, starts, 2.0, build, chooser(everyone, higher), None).value == 2.0 * LADDER[-1]
