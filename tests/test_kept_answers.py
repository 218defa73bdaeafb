"""The expert's held-out answers are kept as they arrive: a check stopped at any moment loses none of them, and a
later check of the same run asks only for the s0 it adds (npp_ros.run.held_out.KeptAnswers). Both commands keep them
so, named by the run's own identity; a file of other answers is refused by name and left untouched."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from npp_ros.run.held_out import KEPT_ANSWERS, KeptAnswers, StoredReturnsError
from npp_ros.tasks.registry import get_task

ARM = Path(__file__).resolve().parents[1] / "examples" / "two_link_arm" / "task.toml"
STATES = np.array([[0.1 * k, -0.2 * k] for k in range(6)])


class Expert:
    """Answers 100 + k for s0 k and counts what it was asked; ``fail_at`` raises as a kill would."""

    def __init__(self, fail_at: int | None = None) -> None:
        self.asked: list[int] = []
        self.fail_at = fail_at

    def __call__(self, k: int) -> tuple[float, bool]:
        if k == self.fail_at:
            raise KeyboardInterrupt
        self.asked.append(k)
        return 100.0 + k, False


def test_a_larger_check_asks_only_for_the_s0_it_adds(tmp_path: Path) -> None:
    kept = KeptAnswers(tmp_path / KEPT_ANSWERS, "run A")
    first = Expert()
    returns, cut, reused = kept.returns(STATES[:3], first)
    assert first.asked == [0, 1, 2] and reused == 0 and cut == 0
    second = Expert()
    more, _, reused = kept.returns(STATES, second)
    assert second.asked == [3, 4, 5] and reused == 3
    np.testing.assert_array_equal(more, 100.0 + np.arange(6))
    np.testing.assert_array_equal(more[:3], returns)


def test_a_stopped_check_loses_no_answer(tmp_path: Path) -> None:
    kept = KeptAnswers(tmp_path / KEPT_ANSWERS, "run A")
    with pytest.raises(KeyboardInterrupt):
        kept.returns(STATES, Expert(fail_at=4))
    again = Expert()
    kept.returns(STATES, again)
    assert again.asked == [4, 5]


def test_a_torn_last_line_is_asked_again_and_the_rest_kept(tmp_path: Path) -> None:
    path = tmp_path / KEPT_ANSWERS
    KeptAnswers(path, "run A").returns(STATES[:4], Expert())
    text = path.read_text()
    path.write_text(text[: len(text) - 9])  # a kill in the middle of s0 3's line
    again = Expert()
    returns, _, reused = KeptAnswers(path, "run A").returns(STATES[:5], again)
    assert again.asked == [3, 4] and reused == 3
    np.testing.assert_array_equal(returns, 100.0 + np.arange(5))
    assert KeptAnswers(path, "run A").returns(STATES[:5], Expert())[2] == 5  # the file reads clean again


def test_answers_of_another_run_are_refused_by_name_and_left_untouched(tmp_path: Path) -> None:
    path = tmp_path / KEPT_ANSWERS
    KeptAnswers(path, "run A").returns(STATES[:3], Expert())
    before = path.read_bytes()
    other = Expert()
    with pytest.raises(StoredReturnsError, match="holds the expert's returns of another run") as refused:
        KeptAnswers(path, "run B").returns(STATES[:3], other)  # another expert setting: neither used nor overwritten
    assert other.asked == [] and path.read_bytes() == before and "\n" not in str(refused.value)
    with pytest.raises(StoredReturnsError, match="left untouched"):
        KeptAnswers(path, "run B").check()
    assert path.read_bytes() == before


def test_an_old_format_file_is_refused_naming_what_it_is_and_left_untouched(tmp_path: Path) -> None:
    """npp-experiment's files before its returns were named by the run: a header dict of its own, lines per chunk.
    Nothing proves them this run's answers, so they are neither read nor overwritten."""
    path = tmp_path / "heldout-expert.jsonl"
    header = {"task": "lqr_2_1", "seed": 0, "horizon": 200, "expert": {"kind": "optimal"}}
    chunk = {"first": 0, "states": STATES[:2].tolist(), "returns": [100.0, 101.0], "budget_stops": 0}
    path.write_text(json.dumps(header) + "\n" + json.dumps(chunk) + "\n")
    before = path.read_bytes()
    asked = Expert()
    with pytest.raises(StoredReturnsError, match=r"earlier per-chunk format.*\(task lqr_2_1, seed 0, horizon 200\)"):
        KeptAnswers(path, "run A").returns(STATES[:2], asked)
    assert asked.asked == [] and path.read_bytes() == before
    path.write_text("not json\n")
    with pytest.raises(StoredReturnsError, match="an unreadable first line"):
        KeptAnswers(path, "run A").check()
    assert path.read_text() == "not json\n"


def test_a_first_write_torn_inside_the_header_is_begun_again(tmp_path: Path) -> None:
    path = tmp_path / KEPT_ANSWERS
    kept = KeptAnswers(path, "run A")
    path.write_text(kept.header[:10])  # a kill in the middle of the first write: nothing answered yet
    asked = Expert()
    kept.returns(STATES[:2], asked)
    assert asked.asked == [0, 1] and path.read_text().splitlines()[0] == kept.header
    assert KeptAnswers(path, "run A").returns(STATES[:2], Expert())[2] == 2


def test_answers_of_other_s0_are_not_used(tmp_path: Path) -> None:
    path = tmp_path / KEPT_ANSWERS
    KeptAnswers(path, "run A").returns(STATES[:3], Expert())
    moved = STATES[:3].copy()
    moved[1, 0] = np.nextafter(moved[1, 0], 1.0)  # s0 1 differs in its last bit
    changed = Expert()
    KeptAnswers(path, "run A").returns(moved, changed)
    assert changed.asked == [1]


def test_budget_stops_are_kept_with_their_answers(tmp_path: Path) -> None:
    path = tmp_path / KEPT_ANSWERS
    _, cut, _ = KeptAnswers(path, "run A").returns(STATES[:3], lambda k: (100.0 + k, k == 0))  # the first cut
    assert cut == 1
    _, cut, reused = KeptAnswers(path, "run A").returns(STATES[:3], Expert())
    assert (cut, reused) == (1, 3)
    rows = [json.loads(line) for line in path.read_text().splitlines()[1:]]
    assert [row["budget_stop"] for row in rows] == [True, False, False]


def test_each_commands_held_out_stream_keeps_its_value_and_draws_through_one_function() -> None:
    """The committed results were made with these streams: npp-learn's, and npp-experiment's next to the one its
    checkpoint evaluations draw from."""
    from npp_ros.experiment.arms import EVALUATION_STREAM, evaluation_states
    from npp_ros.run.held_out import EXPERIMENT_HELD_OUT_STREAM, LEARN_HELD_OUT_STREAM, held_out_states

    assert (LEARN_HELD_OUT_STREAM, EXPERIMENT_HELD_OUT_STREAM, EVALUATION_STREAM) == (1 << 30, (1 << 30) + 1, 1 << 30)
    rng = np.random.default_rng([3, (1 << 30) + 1])
    task = get_task("lqr_2_1")
    drawn = np.array([task.sample_initial_state(rng) for _ in range(4)])
    np.testing.assert_array_equal(held_out_states("lqr_2_1", 3, 4, EXPERIMENT_HELD_OUT_STREAM), drawn)
    learns = held_out_states(task, 3, 4, LEARN_HELD_OUT_STREAM)
    np.testing.assert_array_equal(evaluation_states("lqr_2_1", 3, 4), learns)  # the same stream, drawn the same way


def learn(run_dir: Path, evaluate: int) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "npp_ros.cli.learn", "--task", str(ARM), "--horizon", "20", "--epsilon", "5",
         "--max-episodes", "2", "--evaluate", str(evaluate), "--run-dir", str(run_dir)],
        capture_output=True, text=True,
    )  # fmt: skip


def test_npp_learn_keeps_its_held_out_answers_and_a_larger_check_gives_what_a_fresh_one_does(tmp_path: Path) -> None:
    first = learn(tmp_path / "run", 3)
    assert first.returncode == 1, first.stderr  # two episodes certify nothing
    assert len((tmp_path / "run" / KEPT_ANSWERS).read_text().splitlines()) == 1 + 3
    resumed = learn(tmp_path / "run", 5)
    assert "held-out: 3 of the expert's 5 returns kept from an earlier check of this run" in resumed.stderr
    fresh = learn(tmp_path / "fresh", 5)
    assert "kept from an earlier check" not in fresh.stderr
    summaries = [json.loads((tmp_path / name / "summary.json").read_text())["evaluation"] for name in ("run", "fresh")]
    assert summaries[0] == summaries[1]


def test_npp_learn_stopped_in_its_held_out_check_says_what_is_kept(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Ctrl-C while the expert answers: exit 130 and where the answers are, not a traceback."""
    import npp_ros.cli.learn as learn_cli

    def interrupted(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(learn_cli, "check_policy", interrupted)
    argv = ["--task", str(ARM), "--horizon", "20", "--epsilon", "5", "--max-episodes", "2", "--evaluate", "3"]
    assert learn_cli.main([*argv, "--run-dir", str(tmp_path)]) == 130
    err = capsys.readouterr().err
    assert "interrupted in the held-out check" in err and str(tmp_path / KEPT_ANSWERS) in err


def test_npp_learn_refuses_a_file_of_other_answers_before_its_run_and_leaves_it(tmp_path: Path) -> None:
    """Refused at the start (exit 2, one line), not after the run it would follow; a run with --evaluate 0 needs
    no kept answers and is not stopped by them."""
    path = tmp_path / KEPT_ANSWERS
    path.write_text(json.dumps({"identity": "0" * 64}) + "\n")
    before = path.read_bytes()
    refused = learn(tmp_path, 3)
    assert refused.returncode == 2 and "holds the expert's returns of another run" in refused.stderr
    assert "Traceback" not in refused.stderr and not (tmp_path / "run.sqlite").exists()
    assert path.read_bytes() == before
    assert learn(tmp_path, 0).returncode == 1 and path.read_bytes() == before


def test_both_commands_keep_the_expert_returns_of_the_same_run_under_the_same_identity(tmp_path: Path) -> None:
    """npp-learn's held-out answers and npp-experiment's (asked in chunks, for its evaluations and held-out check)
    of one run are named by that run's identity, as npp-experiment resolves it for the arm and seed."""
    from npp_ros.experiment import run_arm_seed
    from npp_ros.experiment.arms import Arm, ExperimentSettings, arm_request
    from npp_ros.experiment.expert_requests import EVALUATION_FILE
    from npp_ros.run.held_out import answers_identity
    from npp_ros.run.request import resolve_run

    arm = Arm("lqr_2_1", "optimal", "analytic", "oracle", "sequential")  # checked against the expert: answers kept
    settings = ExperimentSettings(max_episodes={"lqr_2_1": 2}, horizon=20, evaluations=3, held_out=3, checkpoints=(2,))
    run_arm_seed(arm, 0, settings, tmp_path / "experiment")
    experiment_dir = tmp_path / "experiment" / "runs" / f"{arm.name}-seed0"
    argv = ["--task", "lqr_2_1", "--seed", "0", "--lipschitz", "analytic", "--certify", "oracle", "--rule",
            "sequential", "--policy", arm.policy, "--horizon", "20", "--max-episodes", "2", "--evaluate", "3",
            "--run-dir", str(tmp_path / "learn")]  # fmt: skip
    learned = subprocess.run([sys.executable, "-m", "npp_ros.cli.learn", *argv], capture_output=True, text=True)
    assert learned.returncode == 1, learned.stderr
    headers = {name: path.read_text().splitlines()[0]
               for name, path in [("learn", tmp_path / "learn" / KEPT_ANSWERS),
                                  ("experiment", experiment_dir / EVALUATION_FILE)]}  # fmt: skip
    run = resolve_run(arm_request(arm, 0, settings), kind=arm.expert, control_weight=settings.control_weight)
    assert headers["learn"] == headers["experiment"] == KeptAnswers(Path(), answers_identity(run.config)).header
