"""The expert's held-out answers are kept as they arrive: a check stopped at any moment loses none of them, and a
later check of the same run asks only for the s0 it adds (npp_ros.run.evaluation.KeptAnswers)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from npp_ros.run.evaluation import KEPT_ANSWERS, KeptAnswers

ARM = Path(__file__).resolve().parents[1] / "examples" / "two_link_arm" / "task.toml"
STATES = np.array([[0.1 * k, -0.2 * k] for k in range(6)])


class Expert:
    """Answers 100 + k for s0 k and counts what it was asked; ``fail_at`` raises as a kill would."""

    def __init__(self, fail_at: int | None = None) -> None:
        self.asked: list[int] = []
        self.fail_at = fail_at

    def __call__(self, k: int) -> float:
        if k == self.fail_at:
            raise KeyboardInterrupt
        self.asked.append(k)
        return 100.0 + k


def test_a_larger_check_asks_only_for_the_s0_it_adds(tmp_path: Path) -> None:
    kept = KeptAnswers(tmp_path / KEPT_ANSWERS, "run A")
    first = Expert()
    returns, cut, reused = kept.returns(STATES[:3], first, lambda: 0)
    assert first.asked == [0, 1, 2] and reused == 0 and cut == 0
    second = Expert()
    more, _, reused = kept.returns(STATES, second, lambda: 0)
    assert second.asked == [3, 4, 5] and reused == 3
    np.testing.assert_array_equal(more, 100.0 + np.arange(6))
    np.testing.assert_array_equal(more[:3], returns)


def test_a_stopped_check_loses_no_answer(tmp_path: Path) -> None:
    kept = KeptAnswers(tmp_path / KEPT_ANSWERS, "run A")
    with pytest.raises(KeyboardInterrupt):
        kept.returns(STATES, Expert(fail_at=4), lambda: 0)
    again = Expert()
    kept.returns(STATES, again, lambda: 0)
    assert again.asked == [4, 5]


def test_a_torn_last_line_is_asked_again_and_the_rest_kept(tmp_path: Path) -> None:
    path = tmp_path / KEPT_ANSWERS
    KeptAnswers(path, "run A").returns(STATES[:4], Expert(), lambda: 0)
    text = path.read_text()
    path.write_text(text[: len(text) - 9])  # a kill in the middle of s0 3's line
    again = Expert()
    returns, _, reused = KeptAnswers(path, "run A").returns(STATES[:5], again, lambda: 0)
    assert again.asked == [3, 4] and reused == 3
    np.testing.assert_array_equal(returns, 100.0 + np.arange(5))
    assert KeptAnswers(path, "run A").returns(STATES[:5], Expert(), lambda: 0)[2] == 5  # the file reads clean again


def test_answers_of_other_settings_or_other_s0_are_not_used(tmp_path: Path) -> None:
    path = tmp_path / KEPT_ANSWERS
    KeptAnswers(path, "run A").returns(STATES[:3], Expert(), lambda: 0)
    other = Expert()
    KeptAnswers(path, "run B").returns(STATES[:3], other, lambda: 0)  # another expert setting: asked afresh
    assert other.asked == [0, 1, 2]
    moved = STATES[:3].copy()
    moved[1, 0] = np.nextafter(moved[1, 0], 1.0)  # s0 1 differs in its last bit
    changed = Expert()
    KeptAnswers(path, "run B").returns(moved, changed, lambda: 0)
    assert changed.asked == [1]


def test_budget_stops_are_kept_with_their_answers(tmp_path: Path) -> None:
    stops = iter([0, 1, 1, 1, 1, 1])  # the expert's count before and after each of three answers: the first cut
    path = tmp_path / KEPT_ANSWERS
    _, cut, _ = KeptAnswers(path, "run A").returns(STATES[:3], Expert(), lambda: next(stops))
    assert cut == 1
    _, cut, reused = KeptAnswers(path, "run A").returns(STATES[:3], Expert(), lambda: 0)
    assert (cut, reused) == (1, 3)
    rows = [json.loads(line) for line in path.read_text().splitlines()[1:]]
    assert [row["budget_stop"] for row in rows] == [True, False, False]


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
