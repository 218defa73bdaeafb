"""docs/tutorials/python.md runs as written: its Python blocks, in order, in one namespace, in a fresh folder."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

PAGE = Path(__file__).resolve().parents[1] / "docs" / "tutorials" / "python.md"


def test_the_python_tutorial_runs_as_written(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    blocks = re.findall(r"```python\n(.*?)```", PAGE.read_text(), flags=re.S)
    assert len(blocks) >= 2
    monkeypatch.chdir(tmp_path)
    namespace: dict[str, object] = {}
    for block in blocks:
        exec(compile(block, str(PAGE), "exec"), namespace)  # the page's own code
    out = capsys.readouterr().out
    assert "True 31 31" in out  # what the page says it prints
    run = namespace["run"]
    assert run.certificate is not None and run.policy.kind == "feedback"  # type: ignore[attr-defined]
    assert (tmp_path / "runs" / "python-lqr_2_1" / "run.sqlite").is_file()
