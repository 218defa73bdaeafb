"""npp-bench-ros's smoke run: its driver plays a run's supervisor and sim for a real policy node (the dataset
service's answer as a run's supervisor sends it), and both partners answer every lockstep step. It runs as a user
runs it, its own process on a domain it reserves. No speed is asserted: a busy machine only makes the figures
smaller."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path


def test_the_quick_bench_runs_the_policy_node_and_the_bare_ping_pong_in_lockstep(tmp_path: Path) -> None:
    out = tmp_path / "ros.json"
    bench = "npp_ros_graph.bench.ros_loop"
    command = [sys.executable, "-m", bench, "--quick", "--json", str(out), "--logs", str(tmp_path)]
    run = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    cases = json.loads(out.read_text())["cases"]
    assert [case["task"] for case in cases] == ["lqr_2_1", "lqr_6_2"]
    for case in cases:
        assert case["steps"] > 0 and all(rate > 0 for rate in case["graph_steps_per_s"] + case["pingpong_steps_per_s"])
        assert case["ratio"] == case["graph_median"] / case["pingpong_median"]
