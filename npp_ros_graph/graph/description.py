"""The four-node graph, described once: which nodes a run starts, by which command, with which parameters.

npp-run starts a run from this description, and the tests start their graphs from it too, so a node
that is added, renamed or given a new run setting changes here and in no launcher of its own.
"""

from __future__ import annotations

import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.run.request import EXPERT_FIELDS, PLANT_FIELDS, RunRequest
from npp_ros_graph.transport.parameters import TASK_CHOICE


@dataclass(frozen=True)
class GraphNode:
    """One node of the graph: its role in a run, its console script, and the module that runs it."""

    role: str
    command: str
    module: str


NODES: dict[str, GraphNode] = {
    node.role: node
    for node in (
        GraphNode("sim", "npp-sim", "npp_ros_graph.nodes.sim"),
        GraphNode("expert", "npp-expert", "npp_ros_graph.nodes.expert"),
        GraphNode("policy", "npp-policy", "npp_ros_graph.nodes.policy"),
        GraphNode("supervisor", "npp-supervisor", "npp_ros_graph.nodes.supervisor.node"),
    )
}
"""Role -> node, in the order a run starts them."""

ROLES: tuple[str, ...] = tuple(NODES)


def graph_parameters(
    task: str,
    seed: int,
    horizon: int,
    run_dir: Path | str,
    *,
    expert: Mapping[str, Any] | None = None,
    policy: Mapping[str, Any] | None = None,
    supervisor: Mapping[str, Any] | None = None,
) -> dict[str, dict[str, Any]]:
    """Each role's ROS parameters for one run: the sim's plant, the supervisor's run folder, and any others.

    The task, seed and horizon go to the sim alone (the other nodes learn them from its plant
    description), and the run folder to the supervisor, which alone writes it.
    """
    return {
        "sim": {"task": task, "seed": seed, "horizon": horizon},
        "expert": dict(expert or {}),
        "policy": dict(policy or {}),
        "supervisor": {"run_dir": str(run_dir), **(supervisor or {})},
    }


def request_parameters(request: RunRequest, run_dir: Path | str) -> dict[str, dict[str, Any]]:
    """Each role's parameters for a run request, every field of it: the plant's (task, seed, horizon) to the sim,
    the expert's options to the expert and to the supervisor (which builds the same expert for L), every other
    field to the supervisor. None is ``task`` (the task's value); ``request.horizon`` must be known."""
    assert request.horizon is not None, "the sim needs the horizon: the task's default_horizon where none is asked"
    values = {name: parameter_value(value) for name, value in vars(request).items()}
    return graph_parameters(
        request.task, request.seed, request.horizon, run_dir,
        expert={name: values[name] for name in EXPERT_FIELDS},
        supervisor={name: value for name, value in values.items() if name not in PLANT_FIELDS},
    )  # fmt: skip


def parameter_value(value: Any) -> Any:
    """A request field's value as its ROS parameter holds it: None is ``task``, a user's L its number."""
    if value is None:
        return TASK_CHOICE
    return value.value if isinstance(value, LipschitzConstant) else value


def run_options(request: RunRequest) -> dict[str, Any]:
    """The npp-run options that ask for this request: its fields that differ from their defaults (L as its number)."""
    return {
        name: value.value if isinstance(value, LipschitzConstant) else value
        for name, value in request.changed().items()
    }


def ros_literal(value: Any) -> str:
    """A value as a `-p name:=VALUE` literal that keeps its type (a string that reads as a number stays one)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(ros_literal(v) for v in value) + "]"
    return repr(value) if isinstance(value, float) else str(value)


def node_argv(role: str, parameters: Mapping[str, Any], namespace: str = "") -> list[str]:
    """The command line that starts one node of the graph in this interpreter, with its parameters."""
    argv = [sys.executable, "-m", NODES[role].module, "--ros-args"]
    if namespace:
        argv += ["-r", f"__ns:={namespace}"]
    return argv + parameter_args(parameters)


def parameter_args(parameters: Mapping[str, Any]) -> list[str]:
    """``-p name:=VALUE`` for each parameter, each value a literal of its own type (ros_literal)."""
    return [arg for name, value in parameters.items() for arg in ("-p", f"{name}:={ros_literal(value)}")]
