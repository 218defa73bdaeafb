"""Counts and seeds on the command line: a bad value is refused by argparse, naming the option, before any work."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from npp_ros.cli import experiment, learn

LEARN = [sys.executable, "-m", "npp_ros.cli.learn"]
EXPERIMENT = [sys.executable, "-m", "npp_ros.cli.experiment"]


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--evaluate", "-3"], "argument --evaluate: must be an integer >= 0, got '-3'"),
        (["--max-episodes", "0"], "argument --max-episodes: must be an integer >= 1, got '0'"),
        (["--horizon", "0"], "argument --horizon: must be an integer >= 1, got '0'"),
        (["--seed", "-1"], "argument --seed: must be an integer >= 0, got '-1'"),
        (["--max-episodes", "ten"], "argument --max-episodes: must be an integer >= 1, got 'ten'"),
    ],
)
def test_npp_learn_refuses_bad_counts(argv: list[str], message: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        learn.parser().parse_args(argv)
    assert exit_.value.code == 2
    assert capsys.readouterr().err.strip().endswith(f"npp-learn: error: {message}")


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--seeds", "0", "-1"], "argument --seeds: must be an integer >= 0, got '-1'"),
        (["--max-episodes", "0"], "argument --max-episodes: must be an integer >= 1, got '0'"),
        (["--evaluate", "0"], "argument --evaluate: must be an integer >= 1, got '0'"),
        (["--jobs", "0"], "argument --jobs: must be an integer >= 1, got '0'"),
        (["--horizon", "-5"], "argument --horizon: must be an integer >= 1, got '-5'"),
        (
            ["--checkpoints", "10,0,30"],
            "argument --checkpoints: must be integers >= 1 separated by commas, got '10,0,30'",
        ),
    ],
)
def test_npp_experiment_refuses_bad_counts(argv: list[str], message: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        experiment.parser().parse_args(argv)
    assert exit_.value.code == 2
    assert capsys.readouterr().err.strip().endswith(f"npp-experiment: error: {message}")


def test_good_values_still_parse() -> None:
    args = learn.parser().parse_args(["--evaluate", "0", "--max-episodes", "1", "--seed", "0"])
    assert (args.evaluate, args.max_episodes, args.seed) == (0, 1, 0)
    args = experiment.parser().parse_args(["--seeds", "0", "7", "--checkpoints", "10,20"])
    assert args.seeds == [0, 7] and args.checkpoints == (10, 20)


def test_as_users_typed_them_nothing_is_written(tmp_path: Path) -> None:
    """The commands as users ran them: one line on stderr, exit code 2, no results.md, no run folder."""
    run = subprocess.run([*EXPERIMENT, "--seeds", "-1", "--out", str(tmp_path / "out")], capture_output=True, text=True)
    assert run.returncode == 2
    assert run.stderr.splitlines()[-1] == "npp-experiment: error: argument --seeds: must be an integer >= 0, got '-1'"
    assert not (tmp_path / "out").exists()
    for option, value in (("--evaluate", "-3"), ("--max-episodes", "0")):
        run = subprocess.run(
            [*LEARN, "--run-dir", str(tmp_path / "run"), option, value], capture_output=True, text=True
        )
        assert run.returncode == 2 and f"npp-learn: error: argument {option}: must be an integer" in run.stderr
    assert not (tmp_path / "run").exists()
