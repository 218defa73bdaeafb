"""No committed file under results/ or docs/, nor the README, names an absolute path of the machine that made it.

A committed results file must be readable and rerunnable on any machine: a run folder named as
``/tmp/robust7/runs/...`` or ``/work/main/results/...`` says nothing to a reader of another checkout, and a
command holding it does not run there. Run folders and task files are named relative to the repository or to
the results folder instead. Fast: only ``git ls-files`` and a regex over each tracked text file.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SCANNED = ("results", "docs", "README.md")
BINARY = {".png", ".jpg", ".jpeg", ".gif", ".svg", ".pdf", ".sqlite", ".db", ".mcap", ".stl", ".obj", ".npz", ".npy"}
# An absolute path starts a word: not inside a URL or a relative path (https://host/tmp/, runs/work/, a/home/b).
MACHINE_PATH = re.compile(
    r"(?<![\w.~/\\$})%-])"
    r"(?:/tmp/|/var/(?:tmp|folders)/|/private/var/|/work/|/root/|/home/\w|/Users/\w|/mnt/[a-z]/)"
    r"|file:/"
    r"|(?<![\w\\])[A-Za-z]:\\{1,2}\w"
)


def machine_paths(text: str) -> list[str]:
    """Each absolute machine path that begins in ``text`` (as the regex sees it; empty when there is none)."""
    return [match.group(0) for match in MACHINE_PATH.finditer(text)]


def tracked_files() -> list[Path]:
    """The tracked text files under results/ and docs/ and the README (skips when there is no git checkout)."""
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    listed = subprocess.run(["git", "ls-files", "-z", "--", *SCANNED], cwd=REPO, capture_output=True, text=True)
    if listed.returncode != 0:
        pytest.skip(f"not a git checkout: {listed.stderr.strip()}")
    paths = [REPO / name for name in listed.stdout.split("\0") if name]
    return [path for path in paths if path.suffix.lower() not in BINARY and path.is_file()]


@pytest.mark.parametrize(
    "planted",
    ["/tmp/x/run.sqlite", "see /work/main/results", "`--run-dir /home/alice/runs`", "file:///tmp/a", "C:\\Users\\me"],
)
def test_a_machine_path_is_found(planted: str) -> None:
    assert machine_paths(planted)


@pytest.mark.parametrize(
    "legitimate",
    [
        "https://github.com/org/repo/tree/main/tmp/work/x",
        "the topics /joint_states and /robot_description",
        "npp_interfaces/srv/ResetRobot, ~/reset",
        "#!/usr/bin/env bash; source /opt/ros/jazzy/setup.bash",
        "npp-trial runs/x-seed1 --out results/deploy/trial --logs runs/tmp/work/logs",
        "d=$(mktemp -d) && python3 -m venv $d/v",
    ],
)
def test_legitimate_text_is_not_flagged(legitimate: str) -> None:
    assert machine_paths(legitimate) == []


def test_committed_files_hold_no_machine_path() -> None:
    found = []
    for path in tracked_files():
        if b"\0" in (raw := path.read_bytes()):
            continue  # binary under an unlisted suffix
        for number, line in enumerate(raw.decode(errors="ignore").splitlines(), 1):
            found += [f"{path.relative_to(REPO)}:{number}: {hit}" for hit in machine_paths(line)]
    assert not found, "absolute paths of the machine that made these files:\n" + "\n".join(found)
