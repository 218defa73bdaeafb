"""ROS 2 adapters over the npp_ros core: transport, runtime, graph, nodes, tools and the ROS loop bench.

``from npp_ros_graph import GraphClient`` drives a run's graph from Python (docs/tutorials/graph-client.md); it
loads on first use, so importing a node or a transport module does not load the client. Each subpackage says
what it may import; tests/test_layering.py holds the whole table and checks it.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # `X as X`: re-exported
    from npp_ros_graph.client import GraphClient as GraphClient
    from npp_ros_graph.client import GraphError as GraphError

_EXPORTS = {"GraphClient": "npp_ros_graph.client", "GraphError": "npp_ros_graph.client"}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'npp_ros_graph' has no attribute {name!r}")
    return getattr(importlib.import_module(_EXPORTS[name]), name)


def __dir__() -> list[str]:
    return __all__
