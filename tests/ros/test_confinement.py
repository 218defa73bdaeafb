"""Test runs are confined: node processes carry the session's domain and localhost discovery, and a
graph on another ROS_DOMAIN_ID is invisible to this one."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from domain_coordinator import domain_id
from npp_interfaces.msg import PlantDescription

from npp_ros_graph.transport.topics import LATCHED_READER_QOS, PLANT

if TYPE_CHECKING:
    from tests.ros.conftest import Launcher, RosClient

QUIET_S = 3.0  # how long "nothing from the other domain" is watched for; discovery on loopback takes < 1 s


def environ_of(pid: int) -> dict[str, str]:
    raw = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    return dict(item.decode(errors="replace").split("=", 1) for item in raw if b"=" in item)


def test_nodes_run_on_the_session_domain_with_localhost_discovery(launch: Launcher, ros_domain: int) -> None:
    proc = launch("npp-sim", {"horizon": 10}, namespace="/confined")
    env = environ_of(proc.pid)
    assert env["ROS_DOMAIN_ID"] == str(ros_domain)
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert "ROS_STATIC_PEERS" not in env
    launch.assert_alive(proc)


def test_a_graph_on_another_domain_is_invisible(launch: Launcher, ros_client: Callable[..., RosClient]) -> None:
    client = ros_client("confinement_watcher", namespace="/confined")
    plants = client.collect(PlantDescription, PLANT, LATCHED_READER_QOS)
    with domain_id() as other:
        foreign = launch("npp-sim", {"seed": 7}, namespace="/confined", domain=int(other))
        client.wait_for(lambda: "ready" in launch.log(foreign), 60.0, "the foreign sim to publish its plant")
        deadline = time.monotonic() + QUIET_S
        client.wait_for(lambda: time.monotonic() > deadline, QUIET_S + 5)
        assert plants == [], "a node on another domain was discovered"
        launch.assert_alive(foreign)
        launch.stop(foreign)
    # Control: the same node on this session's domain is seen.
    launch("npp-sim", {"seed": 7}, namespace="/confined")
    client.wait_for(lambda: bool(plants), 60.0, "the plant description from this domain")
    assert plants[-1].seed == 7
