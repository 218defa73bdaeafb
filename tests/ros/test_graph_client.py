"""GraphClient against real graphs: docs/tutorials/graph-client.md runs as written (start, ask the expert, join,
follow gaps and episodes, the certificate, the stop, on lqr_2_1 with 50-step episodes); the certificate it returns
is the one the run folder holds; an option npp-run does not know is a TypeError before any process, and a
start npp-run refuses raises its reason."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

import npp_ros
from npp_ros.certificate.certifier import Certificate
from npp_ros.run.records import EpisodeOutcome, GapRecord, PlantRecord
from npp_ros_graph import GraphClient, GraphError
from npp_ros_graph.transport.message_seal import KEY_ENV

PAGE = Path(__file__).resolve().parents[2] / "docs" / "tutorials" / "graph-client.md"


@pytest.mark.long
def test_the_graph_client_tutorial_runs_as_written(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], ros_domain: int
) -> None:
    blocks = re.findall(r"```python\n(.*?)```", PAGE.read_text(), flags=re.S)
    assert len(blocks) == 5
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv(KEY_ENV, raising=False)
    namespace: dict[str, object] = {}
    try:
        for block in blocks:
            exec(compile(block, str(PAGE), "exec"), namespace)  # the page's own code, on the session's domain
    finally:
        for name in ("watcher", "client"):  # a failed block leaves no graph behind
            if isinstance(namespace.get(name), GraphClient):
                namespace[name].stop()  # type: ignore[union-attr]
    out = capsys.readouterr().out
    # What the page says it prints.
    assert "lqr_2_1 50 4 1" in out
    assert "5 [47.07, 47.1, 47.12, 47.14, 47.16] 4.89" in out
    assert "the expert refused the request: state has 2 entries, expected 4 (qpos then qvel of 2 joints" in out
    assert "the expert was asked in episodes [0, 1, 2]..." in out
    assert "True 100.0 With probability at least 0.9" in out
    assert "True True" in out
    assert "done: True" in out
    assert "['/npp_expert', '/npp_policy', '/npp_sim', '/npp_supervisor']" in out
    assert namespace["code"] == 0
    assert (tmp_path / "runs" / "client-lqr_2_1" / "run.sqlite").is_file()
    certificate, client = namespace["certificate"], namespace["client"]
    assert isinstance(certificate, Certificate)
    stored = npp_ros.read_run(tmp_path / "runs" / "client-lqr_2_1").certificate
    assert stored is not None
    # One record, over the graph or from the file; the file's spec (its metadata) does not keep L's margin.
    assert {**certificate.record(), "lipschitz_margin": 0.0} == stored.record()
    assert isinstance(client.latest(), (GapRecord, EpisodeOutcome, Certificate))  # type: ignore[attr-defined]
    assert isinstance(namespace["plant"], PlantRecord)  # plant() and the callbacks give records, as the iterators do
    assert "npp-run: started" in (tmp_path / "runs" / "client-lqr_2_1" / "logs" / "npp-run.log").read_text()


def test_an_option_npp_run_does_not_know_is_a_type_error_before_any_process(tmp_path: Path) -> None:
    with pytest.raises(TypeError, match=r"npp-run does not know: epsilonn \(its options: "):
        GraphClient.start("lqr_2_1", run_dir=tmp_path / "run", epsilonn=3)
    assert not (tmp_path / "run").exists()  # nothing started, nothing made


def test_a_start_npp_run_refuses_raises_its_reason(tmp_path: Path, ros_domain: int) -> None:
    with pytest.raises(GraphError, match=r"invalid choice: 'nope'"):
        GraphClient.start("lqr_2_1", run_dir=tmp_path / "run", policy="nope")
