"""Success criteria: the built-in tasks' on known trajectories, what a run records of them, and a run over an expert
that never succeeds saying so where the user looks (npp-learn's warning before the certificate, and its text)."""

from __future__ import annotations

import dataclasses
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest

from npp_ros.certificate.authoring import MeasuredSuccess
from npp_ros.certificate.certifier import SUCCESS_MARK, Certificate
from npp_ros.cli import learn
from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.run import setup
from npp_ros.run.records import SuccessCounts
from npp_ros.run.request import success_lipschitz_choice
from npp_ros.run.setup import build_config, build_loop
from npp_ros.run.store import RunStore
from npp_ros.tasks.builtin.lqr import LQR_2_1, LQRExpert
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.rollout import rollout
from npp_ros.tasks.success import SuccessCriterion, UprightAngles, WithinBand


# ----------------------------------------------------------------------------- the criteria
def test_a_criterion_looks_at_the_final_states_and_at_all_of_a_shorter_episode() -> None:
    positive = SuccessCriterion("entry 0 at least 0", WithinBand((0,), 0.0, math.inf), steps=3)
    states = np.array([[-1.0], [-1.0], [1.0], [1.0], [1.0]])
    assert positive.met(states)  # the last 3
    assert not positive.met(states[1:4])  # 3 states: all of them
    assert not positive.met(states[3:4] * -1) and not positive.met(np.empty((0, 1)))
    assert positive.window(2) == 2 and positive.window(10) == 3
    share = SuccessCriterion("x", WithinBand((0,), 0.0, 1.0), share=0.1)
    assert (share.window(1000), share.window(200), share.window(5)) == (100, 20, 1)
    assert "over the last 10% of the episode" in share.describe()
    with pytest.raises(ValueError, match="exactly one"):
        SuccessCriterion("x", WithinBand((0,), 0.0, 1.0), steps=3, share=0.1)


@pytest.mark.parametrize(
    ("name", "dt", "steps"),
    [("pendulum_swingup", 0.02, 50), ("cartpole_swingup", 0.01, 100), ("acrobot_swingup", 0.01, 100)],
)
def test_the_swing_ups_look_at_their_last_second(name: str, dt: float, steps: int) -> None:
    task = get_task(name)
    assert task.make_plant(0).dt == pytest.approx(dt)
    assert task.success is not None and task.success.steps == steps and task.success.seconds == 1.0
    assert "over the last" in task.success.describe() and "(1 s)" in task.success.describe()


def held(state: list[float], steps: int = 120) -> np.ndarray:
    return np.tile(np.asarray(state, dtype=np.float64), (steps, 1))


def test_the_pendulum_is_done_upright_and_not_from_a_zero_action_hanging() -> None:
    task = get_task("pendulum_swingup")
    criterion = task.success
    assert criterion is not None
    hanging = rollout(task.make_plant(0), lambda _x: np.zeros(1), np.array([np.pi, 0.0]), 300).states
    assert not criterion.met(hanging)
    assert criterion.met(held([np.radians(7.9), 0.0])) and not criterion.met(held([np.radians(8.1), 0.0]))
    swing = held([0.0, 0.0])
    swing[-50] = [np.radians(9.0), 0.0]  # one state of the last second off
    assert not criterion.met(swing)
    swing = held([0.0, 0.0])
    swing[-51] = [np.radians(9.0), 0.0]  # just before the last second: not looked at
    assert criterion.met(swing)


def test_the_cartpole_counts_its_pole_angle_only() -> None:
    criterion = get_task("cartpole_swingup").success
    assert criterion is not None
    assert criterion.met(held([1.5, np.radians(11.9), 0.5, 0.0]))  # the cart may be anywhere, moving
    assert not criterion.met(held([0.0, np.radians(12.1), 0.0, 0.0]))
    assert not criterion.met(held([0.0, np.pi, 0.0, 0.0]))


def test_the_acrobot_counts_the_lower_links_own_angle() -> None:
    criterion = get_task("acrobot_swingup").success
    assert criterion is not None
    assert criterion.met(held([0.1, -0.1, 0.0, 0.0]))  # upper link 5.7 degrees, lower one upright
    assert not criterion.met(held([0.0, 0.3, 0.0, 0.0]))  # upper link upright, lower one 17 degrees off
    assert criterion.met(held([0.0, 2 * np.pi, 0.0, 0.0]))  # a full turn of the elbow is upright
    assert UprightAngles(((0,), (0, 1)), 8.0)(held([0.0, np.radians(7.0), 0.0, 0.0]))


@pytest.mark.parametrize("name", ["lqr_2_1", "lqr_6_2"])
def test_the_optimal_lqr_expert_succeeds_and_no_control_does_not(name: str) -> None:
    task = get_task(name)
    criterion = task.success
    assert criterion is not None
    expert = task.make_expert(0, 1000)
    plant = task.make_plant(0)
    for episode in range(5):
        s0 = task.initial_state(0, episode)
        assert criterion.met(expert.trajectory(s0).states), episode
        assert not criterion.met(rollout(plant, lambda _x: np.zeros(task.action_dim), s0, 1000).states), episode


# ----------------------------------------------------------------------------- what a run records and says
def never_met() -> SuccessCriterion:
    """A criterion lqr_2_1's expert never meets: a position beyond 5, where its springs never take it."""
    return SuccessCriterion("the first joint beyond 5", WithinBand((0,), 5.0, math.inf), steps=10)


def config(horizon: int = 100, epsilon: float = 1000.0, certify: str = "rollout") -> object:
    lipschitz = LipschitzConstant(263.0, "user", "test")
    return build_config("lqr_2_1", 0, lipschitz, epsilon, horizon=horizon, policy="open-loop", certify=certify)  # type: ignore[arg-type]


def test_every_episode_records_the_expert_and_the_policy_on_the_criterion(tmp_path: Path) -> None:
    expert = LQRExpert("lqr_2_1", 0, horizon=1000)
    loop = build_loop(config(1000, 20.0), expert, store_path=tmp_path / "run.sqlite")
    loop.run(6)
    criterion = get_task("lqr_2_1").success
    assert criterion is not None
    for row in loop.rows:
        if row.oracle_called:
            answer = loop.dataset.trajectory(row.trajectory)
            assert row.expert_success is criterion.met(answer.states) is True
        else:
            assert row.expert_success is None
        assert (row.policy_success is None) == (row.policy_return is None)
    assert loop.rows[0].policy_success is None  # no policy yet
    assert all(row.policy_success is not None for row in loop.rows[1:])
    loop.store.close()
    with RunStore.open(tmp_path / "run.sqlite") as store:
        assert [(r.expert_success, r.policy_success) for r in store.episodes()] == [
            (r.expert_success, r.policy_success) for r in loop.rows
        ]


class SimOnly:
    """A driver like the graph's sim: it returns the policy's return and nothing of its states."""

    def __init__(self) -> None:
        self.plant = LQR_2_1.make_plant(0)

    def run_episode(self, episode: int, initial_state: np.ndarray, policy: object) -> float | None:
        if len(policy.dataset) == 0:  # type: ignore[attr-defined]
            return None
        return rollout(self.plant, policy.act, initial_state, 100).total_return  # type: ignore[attr-defined]


def test_the_graphs_way_judges_the_policy_as_the_in_process_run(tmp_path: Path) -> None:
    """Behind a sim the loop sees no states: it re-runs the policy's rollout on a local plant, with the same rows."""
    expert = LQRExpert("lqr_2_1", 0, horizon=100)
    local = build_loop(config(100, 5.0), expert)
    local.run(12)
    graph_like = build_loop(config(100, 5.0), expert, oracle=expert, driver=SimOnly())
    graph_like.run(12)
    assert [(r.expert_success, r.policy_success) for r in graph_like.rows] == [
        (r.expert_success, r.policy_success) for r in local.rows
    ]
    assert [r.policy_return for r in graph_like.rows] == [r.policy_return for r in local.rows]
    assert any(r.policy_success is not None for r in local.rows)


@pytest.fixture
def failing_expert(monkeypatch: pytest.MonkeyPatch) -> None:
    """lqr_2_1 with a criterion its expert never meets, wherever the run's set-up and npp-learn look it up."""
    task = dataclasses.replace(LQR_2_1, success=never_met())

    def lookup(name: str) -> object:
        return task if name == "lqr_2_1" else get_task(name)

    monkeypatch.setattr(setup, "get_task", lookup)
    monkeypatch.setattr(learn, "get_task", lookup)


def test_a_run_over_an_expert_that_never_succeeds_says_so_before_its_certificate(
    tmp_path: Path, failing_expert: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    both = io.StringIO()  # stdout and stderr in the order a terminal shows them
    monkeypatch.setattr("sys.stdout", both)
    monkeypatch.setattr("sys.stderr", both)
    argv = ["--horizon", "100", "--epsilon", "1000", "--policy", "open-loop", "--evaluate", "0",
            "--run-dir", str(tmp_path)]  # fmt: skip
    assert learn.main(argv) == 0
    out = both.getvalue()
    warning = "npp-learn: WARNING: the expert succeeded on 0 of its 1 answers (0%); success: the first joint beyond 5"
    assert warning in out and "a certificate is relative to its expert" in out
    assert out.index(warning) < out.index("CERTIFICATE (lqr_2_1")
    assert "  success         the first joint beyond 5 over the last 10 steps: the expert succeeded on 0 of 1 " in out
    statement = json.loads((tmp_path / "summary.json").read_text())["certificate"]["statement"]
    said = f"{SUCCESS_MARK}, the first joint beyond 5 over the last 10 steps: the expert succeeded on 0 of 1 answers"
    assert said in statement
    assert "this expert mostly fails the task" in statement
    summary = json.loads((tmp_path / "summary.json").read_text())["success"]
    assert (summary["expert_successes"], summary["expert_answers"]) == (0, 1)
    assert (summary["policy_successes"], summary["policy_checked"]) == (0, 30)


def test_an_expert_that_succeeds_gets_no_warning(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["--epsilon", "1000", "--evaluate", "0", "--run-dir", str(tmp_path)]  # feedback: the optimal law
    assert learn.main(argv) == 0
    captured = capsys.readouterr()
    assert "WARNING" not in captured.err
    assert "the expert succeeded on 1 of 1 answers; the policy on 30 of 30 checked episodes." in captured.out


def test_the_counts_and_the_words() -> None:
    counts = SuccessCounts(0, 201, 187, 201)
    assert counts.expert_fails and "succeeded on 0 of its 201 answers (0%)" in counts.warning("x")[0]
    assert SuccessCounts(101, 201, 0, 0).warning("x") == [] and not SuccessCounts(0, 0, 0, 0).expert_fails
    said = MeasuredSuccess("the pole up", (0, 201), (187, 201)).sentence()
    assert said.startswith(f"{SUCCESS_MARK}, the pole up: the expert succeeded on 0 of 201 answers; the policy on 187")
    assert "not checked in this mode" in MeasuredSuccess("the pole up", (3, 3), None).sentence()
    assert "states no success criterion" in MeasuredSuccess(None).sentence()


def test_a_certificate_from_before_success_was_measured_reads_as_before() -> None:
    expert = LQRExpert("lqr_2_1", 0, horizon=100)
    loop = build_loop(config(100, 1000.0), expert)
    loop.run(100)
    cert = loop.certificate
    assert cert is not None and cert.success.startswith("every joint position within 0.15 of 0")
    old = {**cert.record(), "statement": cert.claim}
    again = Certificate.from_record(old, cert.spec)
    assert again.success == "" and "  success " not in again.summary() and again.claim == cert.claim


def test_a_success_claim_needs_no_l_from_the_user() -> None:
    """The claim rests on no L: a task with no L of its own acts with one measured on the run's first answers
    ('data', a choice) instead of refusing; a task with its own default keeps it."""
    cartpole = get_task("cartpole_swingup")
    with pytest.raises(ValueError, match="no analytic, paper or own L"):
        cartpole.default_lipschitz_choice()
    assert success_lipschitz_choice(cartpole) == "data"
    assert success_lipschitz_choice(get_task("lqr_2_1")) == "analytic"
