"""Starting a run's four-node graph in a test, from the description npp-run starts it from.

The roles, their commands and the per-node parameters come from npp_ros_graph.graph.description, so
a test graph is the graph npp-run starts; a test adds only what it changes (a namespace, a run key).
"""

from __future__ import annotations

import subprocess
from typing import TYPE_CHECKING, Any

from npp_ros_graph.graph.description import NODES, ROLES, graph_parameters

if TYPE_CHECKING:
    from tests.ros.conftest import Launcher

__all__ = ["graph_parameters", "start_graph", "start_node"]


def start_node(
    launch: Launcher, role: str, params: dict[str, Any] | None = None, **options: Any
) -> subprocess.Popen[bytes]:
    """One node of the graph by its role (sim, expert, policy, supervisor), through its console script."""
    return launch(NODES[role].command, params or {}, **options)


def start_graph(
    launch: Launcher, params: dict[str, dict[str, Any]], **options: Any
) -> dict[str, subprocess.Popen[bytes]]:
    """The four nodes in npp-run's order, each with its parameters (see graph_parameters); role -> process."""
    return {role: start_node(launch, role, params.get(role, {}), **options) for role in ROLES}
