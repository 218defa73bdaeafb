"""/diagnostics from every node of the graph, and npp-monitor showing it: the four nodes run a real episode loop
as separate processes, and each reports what it is doing on diagnostic_msgs/DiagnosticArray."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray

from npp_ros_graph.runtime.diagnostics import DIAGNOSTICS, DIAGNOSTICS_QOS, ERROR, health_of

NODES = ("/npp_sim", "/npp_expert", "/npp_policy", "/npp_supervisor")


def test_every_node_reports_its_health_and_npp_monitor_shows_it(launch, ros_client, tmp_path: Path) -> None:
    launch("npp-sim", {"horizon": 50})
    launch("npp-expert")
    launch("npp-policy")
    launch("npp-supervisor", {"run_dir": str(tmp_path / "run"), "epsilon": 0.001, "max_episodes": 100000})
    monitor_log = tmp_path / "monitor.log"
    with monitor_log.open("w") as out:  # npp-monitor --topics health, as a user starts it
        monitor = subprocess.Popen(
            [sys.executable, "-m", "npp_ros_graph.tools.monitor", "--topics", "health"],
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    client = ros_client("diagnostics_test")
    statuses: dict[str, list] = {name: [] for name in NODES}

    def on_diagnostics(msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name in statuses:
                statuses[status.name].append(health_of(status))

    client.node.create_subscription(DiagnosticArray, DIAGNOSTICS, on_diagnostics, DIAGNOSTICS_QOS)

    def reported(name: str, doing: str) -> bool:
        return any(health.doing.startswith(doing) for health in statuses[name])

    client.wait_for(lambda: reported("/npp_supervisor", "episode 2"), 180.0, "the supervisor to report its episodes")
    client.wait_for(lambda: reported("/npp_policy", "acting on"), 60.0, "the policy to report it acts")
    client.wait_for(lambda: reported("/npp_sim", "episode"), 60.0, "the sim to report its episode")
    client.wait_for(lambda: reported("/npp_expert", "serving"), 60.0, "the expert to report it serves")
    assert all(health.level != ERROR for name in NODES for health in statuses[name])
    assert "waiting requests" in statuses["/npp_expert"][-1].values
    assert "dropped states" in statuses["/npp_policy"][-1].values
    assert "ignored actions" in statuses["/npp_sim"][-1].values
    assert int(statuses["/npp_supervisor"][-1].values["oracle calls"]) >= 1
    try:
        lines = monitor_log.read_text
        client.wait_for(lambda: all(f"[health]  {n}" in lines() for n in NODES), 60.0, "npp-monitor's health lines")
    finally:
        monitor.send_signal(signal.SIGINT)
        try:
            monitor.wait(10)
        except subprocess.TimeoutExpired:
            monitor.kill()
            monitor.wait()
