"""npp-bench-deploy's smoke run on a certified run of a task whose state holds a target (tests/fixtures/point_reach,
made here with the core loop): npp-deploy, its own process, deploys it through the gate, the bench's robot gives it
a target per s0 and answers in lockstep, and the report holds every part for that case. It runs as a user runs it,
on a domain it reserves. No speed is asserted: a busy machine only makes the figures larger."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from deploy_runs import make_reach_run

from npp_ros.run.read import read_run
from npp_ros_graph.bench.deploy import main

pytestmark = [pytest.mark.slow, pytest.mark.long]  # a command line as its own process, with npp-deploy and npp-robot

QUICK_STATES, QUICK_STOPS, WARM_UP = 300, 3, 50  # --quick's states and stops, and the bench's warm-up states


def test_the_quick_bench_measures_a_certified_target_run_through_the_gate(tmp_path: Path) -> None:
    run = make_reach_run(tmp_path / "reach")
    certified = read_run(run)
    assert certified.certificate is not None
    points = certified.dataset.trajectory_offsets[certified.certificate.policy_trajectories]
    out = tmp_path / "out"
    command = [sys.executable, "-m", "npp_ros_graph.bench.deploy", "--quick", "--only-runs", "--case-run", str(run),
               "--runs", str(tmp_path / "runs"), "--out", str(out)]  # fmt: skip
    bench = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert bench.returncode == 0, bench.stderr[-3000:]

    report = json.loads((out / "bench.json").read_text())
    assert "--case-run" in report["command"] and len(report["load_average_start"]) == 3
    [case] = report["cases"]  # --only-runs: no lqr case
    assert (case["task"], case["run"], case["case"]) == ("point_reach", str(run), "reach (point_reach)")
    assert case["gate"] and case["deployed"].startswith("through the gate: certified"), case["deployed"]
    assert case["target"] and case["points"] == points and case["horizon"] == certified.metadata.horizon
    # Every state timed got its command, each episode a target npp-deploy took, and npp-deploy answered them all.
    assert case["states"] == case["states_sent"] == case["commands_received"] == QUICK_STATES
    assert case["targets_given"] >= QUICK_STATES // case["horizon"] - 1  # the first episode's is the warm-up's
    counters = case["node_counters"]
    assert counters["answered"] >= QUICK_STATES + WARM_UP and counters["refused states"] == 0, counters
    assert 0 < case["round_trip_p50_us"] <= case["round_trip_p99_us"] <= case["round_trip_max_us"]
    answer = [float(x) for x in case["node_answer_p50_p99_us"].split("/")]
    assert 0 < answer[0] <= answer[1]
    # The watchdog and the state period against npp-robot, given the target it simulates.
    assert case["stops"] == QUICK_STOPS == len(case["safe_command_after_last_state_ms"])
    assert case["safe_p50_ms"] >= case["state_timeout_ms"]  # it waited its timeout; how soon it acted after is timing
    assert case["state_periods"] > 0 and case["control_period_ms"] == pytest.approx(20.0)
    assert 0 < case["state_period_p50_ms"] <= case["state_period_p99_ms"] <= case["state_period_max_ms"]

    tables = (out / "bench.md").read_text()
    assert "reach (point_reach): through the gate" in tables and "Its state holds a target" in tables
    assert tables.count("| reach (point_reach)") == 3  # the latency, watchdog and state-period tables


def test_only_runs_needs_a_run(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as stopped:
        main(["--only-runs"])
    assert stopped.value.code == 2 and "--only-runs needs --case-run" in capsys.readouterr().err
