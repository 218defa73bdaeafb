"""Strangers on /npp/sim/plant cannot hide the run's own plant description from a node that waits for it.

A plant description is latched: each sim publishes it once and keeps it for late joiners. A node that
starts (or restarts) while other publishers on the domain also hold a description must still receive the
run's: its reader keeps one sample per publisher, so a stranger's description, refused for its seal, never
takes the place of the run's. Checked for the policy and the expert, with strangers that publish before the
node starts and strangers that start after it has restarted.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import pytest
from npp_interfaces.msg import PlantDescription

from npp_ros.tasks.builtin.lqr import LQRPlant
from npp_ros_graph.transport.convert import plant_description
from npp_ros_graph.transport.message_seal import KEY_ENV, RunSeal
from npp_ros_graph.transport.topics import LATCHED_QOS, PLANT

if TYPE_CHECKING:
    from tests.ros.conftest import Launcher, RosClient

STRANGERS = 40  # publishers of other plants' descriptions, each its own latched writer
TIMEOUT = 60.0
NODES = {"npp-policy": "plant lqr_2_1 seed 0; catching up", "npp-expert": "modelling lqr_2_1 seed 0"}


def stranger_descriptions(client: RosClient, count: int) -> list[object]:
    """``count`` latched publishers, each holding another plant's description (unsealed or another run's)."""
    other = LQRPlant("lqr_2_1", 1)
    foreign = RunSeal(b"another run's key", private=True)
    publishers = []
    for k in range(count):
        publisher = client.node.create_publisher(PlantDescription, PLANT, LATCHED_QOS)
        desc = plant_description(other, 1, 50)
        publisher.publish(foreign.seal(desc) if k % 2 else desc)
        publishers.append(publisher)
    return publishers


@pytest.mark.parametrize("command", sorted(NODES))
def test_a_node_gets_the_runs_plant_whatever_strangers_publish(
    command: str, launch: Launcher, ros_client: Callable[..., RosClient]
) -> None:
    key = {KEY_ENV: RunSeal.new_key()}
    client = ros_client("strangers")
    held = stranger_descriptions(client, STRANGERS)  # before the run's sim and before the node
    launch("npp-sim", {"task": "lqr_2_1", "seed": 0, "horizon": 50}, extra_env=key)
    accepted = NODES[command]
    node = launch(command, {}, extra_env=key)
    client.wait_for(
        lambda: accepted in launch.log(node) and "does not carry this run's seal" in launch.log(node),
        TIMEOUT,
        f"{command} adopting the run's plant and refusing the strangers'",
    )

    # Restarted with the strangers still on the domain, then more strangers after the restart.
    launch.stop(node)
    node = launch(command, {}, extra_env=key)
    held += stranger_descriptions(client, STRANGERS)
    client.wait_for(lambda: accepted in launch.log(node), TIMEOUT, f"the restarted {command} adopting the run's plant")
    launch.assert_alive(node)
    assert len(held) == 2 * STRANGERS
