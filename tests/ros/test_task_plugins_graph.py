"""The sim takes a plug-in's task by name, and refuses a plug-in that does not load in one line."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from expert_checks import TIMEOUT
from npp_interfaces.msg import PlantDescription
from plugin_env import with_plugin_path

from npp_ros_graph.transport.topics import LATCHED_READER_QOS, PLANT

if TYPE_CHECKING:
    from tests.ros.conftest import Launcher, RosClient


def test_the_sim_runs_a_plugin_task(launch: Launcher, ros_client: Callable[..., RosClient], demo_plugin: Path) -> None:
    env = {"PYTHONPATH": with_plugin_path(demo_plugin)["PYTHONPATH"]}
    sim = launch("npp-sim", {"task": "demo_pendulum", "horizon": 20}, extra_env=env)
    client = ros_client("plugin_client")
    plants = client.collect(PlantDescription, PLANT, LATCHED_READER_QOS)
    client.wait_for(lambda: bool(plants) or sim.poll() is not None, TIMEOUT, "the sim's plant description")
    launch.assert_alive(sim)
    assert (plants[0].task, plants[0].state_dim, plants[0].action_dim) == ("demo_pendulum", 2, 1)


def test_the_sim_refuses_a_plugin_that_does_not_load(launch: Launcher, demo_plugin: Path) -> None:
    env = {"PYTHONPATH": with_plugin_path(demo_plugin)["PYTHONPATH"]}
    sim = launch("npp-sim", {"task": "demo_broken"}, extra_env=env)
    assert sim.wait(timeout=60) == 2
    log = launch.log(sim)
    assert "Traceback" not in log
    last = [line for line in log.splitlines() if line.strip()][-1]
    assert last.startswith("npp-sim: bad parameter: task 'demo_broken' (plug-in npp-demo-tasks 0.1.0")
    assert "ModuleNotFoundError" in last
