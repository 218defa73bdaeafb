"""Starting a run's four-node graph in a test, from the description npp-run starts it from.

The roles, their commands and the per-node parameters come from npp_ros_graph.graph.description, so
a test graph is the graph npp-run starts; a test adds only what it changes (a namespace, a run key).
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from npp_ros_graph.graph.description import NODES, ROLES, graph_parameters

if TYPE_CHECKING:
    from tests.ros.conftest import Launcher

__all__ = ["alive", "children", "graph_parameters", "node_modules", "npp_run_to_its_end", "start_graph", "start_node"]


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


def node_modules() -> dict[str, str]:
    """role -> the module npp-run starts it from (python -m ...)."""
    return {role: NODES[role].module for role in ROLES}


def children(parent: int, modules: Mapping[str, str]) -> dict[str, int]:
    """The processes `parent` started from the given modules (name -> module): name -> pid."""
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            argv = (entry / "cmdline").read_bytes().decode(errors="replace").split("\0")
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == parent:
            found.update({name: int(entry.name) for name, module in modules.items() if module in argv})
    return found


def alive(pid: int) -> bool:
    """Running (a zombie waiting to be reaped has ended)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def npp_run_to_its_end(options: list[str], run_dir: Path, max_episodes: int, timeout: float = 900.0) -> None:
    """npp-run with ``options`` into ``run_dir`` until it ends, certified or not within ``max_episodes`` (both end a
    run); anything else fails the test with the run's output and its nodes' logs."""
    command = [sys.executable, "-m", "npp_ros_graph.tools.run", *options, "--max-episodes", str(max_episodes),
               "--run-dir", str(run_dir)]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, timeout=timeout)
    ended = done.returncode == 0 or f"NOT CERTIFIED within {max_episodes} episodes" in done.stdout + done.stderr
    logs = "\n".join(f"== {p.name}\n{p.read_text()[-3000:]}" for p in sorted((run_dir / "logs").glob("*.log")))
    assert ended, f"{done.stdout[-2000:]}\n{done.stderr[-3000:]}\n{logs}"
