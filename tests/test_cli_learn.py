"""npp-learn as a user runs it: a real process, its output and its run folder."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest

LEARN = [sys.executable, "-m", "npp_ros.cli.learn"]


def test_help_explains_the_options() -> None:
    out = subprocess.run([*LEARN, "--help"], capture_output=True, text=True, check=True).stdout
    for option in ("--task", "--lipschitz", "--epsilon", "--certify", "--rule", "--condition", "--run-dir"):
        assert option in out
    assert "not a bound on these tasks" in out  # the paper's L is named for what it is


@pytest.mark.long
def test_runs_to_a_certificate_and_leaves_a_run_folder(tmp_path: Path) -> None:
    run = subprocess.run([*LEARN, "--run-dir", str(tmp_path), "--evaluate", "3"], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert "CERTIFICATE (lqr_2_1, condition (i), certify=rollout, rule=sequential)" in run.stdout
    assert "(lqr-analytic, margin 1e-06)" in run.stdout and "proven          yes" in run.stdout
    assert "test " in run.stdout and "spent delta" in run.stdout and "assumptions" in run.stdout
    assert "episode" in run.stderr and "oracle calls" in run.stderr  # live progress
    summary = json.loads((tmp_path / "summary.json").read_text())
    cert = summary["certificate"]
    assert cert["oracle_calls"] == summary["oracle_calls"] and cert["dataset_size"] == 1000 * cert["oracle_calls"]
    assert all(check["ok"] for check in summary["lipschitz_checks"])
    assert summary["evaluation"]["lower_bound_violations"] == 0
    with (tmp_path / "episodes.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == cert["episodes"]
    # Started again: resumes, runs no new episode, prints the same certificate.
    again = subprocess.run([*LEARN, "--run-dir", str(tmp_path), "--evaluate", "0"], capture_output=True, text=True)
    assert again.returncode == 0 and f"episodes        {cert['episodes']}" in again.stdout
    assert "resuming" in again.stderr


def test_bad_settings_get_a_clear_error(tmp_path: Path) -> None:
    run = subprocess.run([*LEARN, "--run-dir", str(tmp_path), "--p", "1.5"], capture_output=True, text=True)
    assert run.returncode == 2 and "p must lie in (0, 1), got 1.5" in run.stderr
    run = subprocess.run([*LEARN, "--run-dir", str(tmp_path), "--lipschitz", "-3"], capture_output=True, text=True)
    assert run.returncode == 2 and "Lipschitz constant must be finite and > 0" in run.stderr
    run = subprocess.run([*LEARN, "--task", "lqr_9_9"], capture_output=True, text=True)
    assert run.returncode == 2 and "argument --task: unknown task 'lqr_9_9'; known tasks: " in run.stderr
