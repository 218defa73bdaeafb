"""The mixture rule through the graph: npp-run reaches the in-process run's certificate, held data included.

A run to its certificate through two verifications: a long run, in `make test-long` (`make test` checks the
mixture rule's loop in process, test_loop_mixture.py)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from reference import decisions, uninterrupted_run

from npp_ros.run.store import RunStore

pytestmark = pytest.mark.long

HORIZON = 200  # with it, seed 0 needs two verifications: the first gives up, the second certifies despite a failure


def test_graph_and_in_process_loop_give_the_same_mixture_certificate(tmp_path: Path, ros_domain: int) -> None:
    run_dir = tmp_path / "graph"
    run = subprocess.run(
        [sys.executable, "-m", "npp_ros_graph.tools.run", "--run-dir", str(run_dir), "--rule", "mixture",
         "--horizon", str(HORIZON), "--max-episodes", "1000"],
        capture_output=True, text=True, timeout=1500,
    )  # fmt: skip
    logs = "\n".join(f"== {p.name}\n{p.read_text()[-3000:]}" for p in sorted((run_dir / "logs").glob("*.log")))
    assert run.returncode == 0, f"{run.stderr[-3000:]}\n{logs}"
    assert "[certificate] condition (i), epsilon 50" in run.stdout
    with RunStore.open(run_dir / "run.sqlite") as store:
        graph_data, graph_rows, certificate = store.load_dataset(), store.episodes(), store.certificate()

    local_loop, local = uninterrupted_run(horizon=HORIZON, max_episodes=1000, rule="mixture")
    cert = local.certificate
    assert cert is not None and (cert.spec.rule, cert.proven) == ("mixture", True)
    assert cert.test >= 2 and cert.failures >= 1  # a verification gave up, and the certifying one held a failure
    assert certificate == cert.record()  # the same certificate, field by field: rule, v, delta_v, n, F, M
    assert decisions(graph_rows) == decisions(local.rows)
    # The graph held the verifications' data back from its policy node exactly as the loop did: the same
    # policy data, rule state and checked gap per episode (a return summed in the sim may differ in its
    # last bits from one summed in process).
    assert [(r.dataset_size, r.test, r.window) for r in graph_rows] == [
        (r.dataset_size, r.test, r.window) for r in local.rows
    ]
    np.testing.assert_allclose([r.checked_gap for r in graph_rows], [r.checked_gap for r in local.rows], rtol=1e-12)
    np.testing.assert_array_equal(graph_data.states, local_loop.dataset.states)
    np.testing.assert_array_equal(graph_data.values, local_loop.dataset.values)
