"""The whole graph as a user runs it: npp-run starts four processes and reaches a certificate.

The main job's own run, at its full horizon (1000 steps, some 230 episodes): a long run, in `make test-long`.
`make test` checks the graph against the in-process loop on shorter runs (test_replayed_run.py,
test_graph_mixture.py, test_cross_talk.py)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from reference import decisions, uninterrupted_run

from npp_ros.run.store import RunStore

pytestmark = pytest.mark.long


def test_graph_certifies_lqr_2_1_with_the_same_numbers_as_in_process(tmp_path: Path, ros_domain: int) -> None:
    run_dir = tmp_path / "graph"
    # The monitor writes to a file: a pipe nobody reads during the run fills up (about 64 KiB, some 300
    # episodes of lines) and blocks the monitor in the middle of its output.
    watched_file = tmp_path / "monitor.out"
    with watched_file.open("w") as out:
        monitor = subprocess.Popen(
            [sys.executable, "-m", "npp_ros_graph.tools.monitor", "--exit-on-certificate"], stdout=out
        )
    run = subprocess.run(
        # The main job's run: the paper's open-loop policy, as make run starts it.
        [
            sys.executable,
            "-m",
            "npp_ros_graph.tools.run",
            "--run-dir",
            str(run_dir),
            "--max-episodes",
            "400",
            "--policy",
            "open-loop",
        ],
        capture_output=True,
        text=True,
        timeout=1200,
    )
    logs = "\n".join(f"== {p.name}\n{p.read_text()[-3000:]}" for p in sorted((run_dir / "logs").glob("*.log")))
    assert run.returncode == 0, f"{run.stderr[-3000:]}\n{logs}"
    assert "[certificate] condition (i), epsilon 50" in run.stdout
    assert "(lqr-analytic)" in run.stdout
    assert "oracle calls" in run.stderr  # live progress
    try:
        assert monitor.wait(timeout=120) == 0  # the certificate is latched: the monitor sees it and exits
    finally:
        monitor.kill()  # no-op once it exited
    watched = watched_file.read_text()
    assert "[gap]     episode" in watched and "ORACLE" in watched and "[episode] episode" in watched
    assert "[certificate] condition (i), epsilon 50" in watched
    for name in ("run.sqlite", "gaps.csv", "episodes.csv"):
        assert (run_dir / name).is_file()

    with RunStore.open(run_dir / "run.sqlite") as store:
        graph_data = store.load_dataset()
        graph_rows = store.episodes()
        certificate = store.certificate()
    assert certificate is not None and certificate["episodes"] == len(graph_rows)
    # The policy drove the episodes through the sim: returns were recorded, and none fell below V_lb(s0).
    returns = [(r.policy_return, r.v_lb) for r in graph_rows if r.policy_return is not None]
    assert len(returns) >= len(graph_rows) - 5
    assert all(ret >= v_lb for ret, v_lb in returns)

    local_loop, local = uninterrupted_run(policy="open-loop")
    assert decisions(graph_rows) == decisions(local.rows)
    assert local.certificate is not None and certificate["episodes"] == local.certificate.episodes
    assert certificate == local.certificate.record()  # the same certificate, field by field
    cert = local.certificate
    assert (cert.spec.certify, cert.spec.rule, cert.proven) == ("rollout", "sequential", True)
    np.testing.assert_array_equal(graph_data.states, local_loop.dataset.states)
    np.testing.assert_array_equal(graph_data.values, local_loop.dataset.values)
