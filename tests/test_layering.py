"""The packages' layering, read statically from every module's imports (inside functions too).

npp_ros is the ROS-free core, in parts that follow the paper and a run; npp_ros_graph adapts it to
ROS 2. The table below says which part may import which; the test parses every module with ast,
so an import that only runs on request (inside a function) counts as much as one at the top.
Within a part the modules import each other freely, but never in a circle: the module import graph
of both packages (and of the scripts in nodes/) has no cycle, and a cycle is named module by module.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from itertools import pairwise
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

CORE_PARTS = (
    "npp_ros.policy",
    "npp_ros.certificate",
    "npp_ros.trajopt",
    "npp_ros.tasks",
    "npp_ros.run",
    "npp_ros.deployment",
    "npp_ros.identification",
    "npp_ros.experiment",
    "npp_ros.bench",
    "npp_ros.cli",
)
CORE = frozenset(CORE_PARTS)
BELOW_RUN = frozenset({"npp_ros.policy", "npp_ros.certificate", "npp_ros.trajopt", "npp_ros.tasks"})
DEPLOYMENT = "npp_ros.deployment"
LEARNING_NODES = tuple(f"npp_ros_graph.nodes.{node}" for node in ("sim", "expert", "policy", "supervisor"))
ROBOT_NODES = ("npp_ros_graph.nodes.deploy", "npp_ros_graph.nodes.robot", "npp_ros_graph.nodes.robot_run")
NODE_PARTS = LEARNING_NODES + ROBOT_NODES
TRANSPORT, RUNTIME, GRAPH = "npp_ros_graph.transport", "npp_ros_graph.runtime", "npp_ros_graph.graph"

MAY_IMPORT: dict[str, frozenset[str]] = {
    # the core, bottom up; the package itself exports a few names of its parts (loaded on first use)
    "npp_ros": frozenset({"npp_ros.policy", "npp_ros.certificate", "npp_ros.tasks", "npp_ros.run"}),
    "npp_ros.policy": frozenset(),
    "npp_ros.certificate": frozenset({"npp_ros.policy"}),
    "npp_ros.trajopt": frozenset({"npp_ros.policy", "npp_ros.certificate"}),
    "npp_ros.tasks": frozenset({"npp_ros.policy", "npp_ros.certificate", "npp_ros.trajopt"}),
    "npp_ros.run": BELOW_RUN,
    DEPLOYMENT: BELOW_RUN | {"npp_ros.run"},  # a certified run on a robot: reads run files, never runs Algorithm 1
    "npp_ros.identification": BELOW_RUN | {"npp_ros.run"},  # a robot from its motion; the policy checked at it
    "npp_ros.experiment": BELOW_RUN | {"npp_ros.run"},
    "npp_ros.bench": BELOW_RUN | {"npp_ros.run"},
    "npp_ros.cli": CORE - {"npp_ros.cli"},
    # the ROS side: any of the core, and its own parts bottom up
    "npp_ros_graph": frozenset({"npp_ros_graph.client"}),  # exports GraphClient, loaded on first use
    TRANSPORT: CORE,
    RUNTIME: CORE | {TRANSPORT},
    GRAPH: CORE | {TRANSPORT},
    # a node never imports another node; the nodes of Algorithm 1's graph deploy nothing
    **{node: (CORE - {DEPLOYMENT}) | {TRANSPORT, RUNTIME} for node in LEARNING_NODES},
    **{node: CORE | {TRANSPORT, RUNTIME} for node in ROBOT_NODES},
    "npp_ros_graph.nodes": frozenset(),
    "npp_ros_graph.client": CORE | {TRANSPORT, RUNTIME, GRAPH},  # GraphClient: the graph from Python
    "npp_ros_graph.tools": CORE | {TRANSPORT, RUNTIME, GRAPH, "npp_ros_graph.client"},
    "npp_ros_graph.bench": CORE | {TRANSPORT, RUNTIME, GRAPH},
    # the thin scripts in nodes/
    "nodes": frozenset({*NODE_PARTS, "npp_ros_graph.tools"}),
}
ROS = ("rclpy", "rosidl", "npp_interfaces", "std_msgs", "sensor_msgs", "builtin_interfaces", "npp_ros_graph")


def part_of(module: str) -> str:
    """The longest part in the table that holds ``module`` (a module path, or nodes.npp_sim for a script)."""
    parts = [p for p in MAY_IMPORT if module == p or module.startswith(p + ".")]
    if not parts:
        raise KeyError(f"{module} is in no part of the layering table (tests/test_layering.py): add it there")
    return max(parts, key=len)


def module_name(path: Path, root: Path) -> str:
    rel = path.relative_to(root).with_suffix("")
    names = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(names)


def imports(path: Path, module: str) -> list[tuple[int, str]]:
    """Every module that ``path`` imports, anywhere in it, with its line; relative imports resolved."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            found.append((node.lineno, base))
            found += [(node.lineno, f"{base}.{alias.name}") for alias in node.names]  # `from pkg import module`
    return found


def sources(root: Path) -> list[Path]:
    return sorted(p for folder in ("npp_ros", "npp_ros_graph", "nodes") for p in (root / folder).rglob("*.py"))


def violations(root: Path = REPO) -> list[str]:
    found = []
    for path in sources(root):
        module = module_name(path, root)
        part = part_of(module)
        allowed = MAY_IMPORT[part] | {part}
        where = path.relative_to(root)
        told: set[int] = set()  # one line per import statement
        for line, name in imports(path, module):
            if line in told:
                continue
            if part.startswith("npp_ros.") or part == "npp_ros":
                if name.split(".")[0] in ROS:
                    found.append(f"{where}:{line} imports {name}: the core never imports ROS or npp_ros_graph")
                    told.add(line)
                    continue
            if name.split(".")[0] not in ("npp_ros", "npp_ros_graph"):
                continue
            try:
                target = part_of(name)
            except KeyError:
                continue  # `from npp_ros.x import name`: the name is no module; the module itself was checked
            if target not in allowed and target not in ("npp_ros", "npp_ros_graph"):
                found.append(f"{where}:{line} imports {name}: {part} may not import {target}")
                told.add(line)
    return found


def imported_modules(path: Path, module: str, known: dict[str, Path]) -> Iterator[tuple[int, str]]:
    """The modules of ``known`` that ``path`` imports, anywhere in it, with the line.

    ``from pkg import name`` imports the module pkg.name where there is one, else pkg; ``import a.b.c`` the
    longest known module of that path. A package's ``__init__`` counts only where an import names it.
    """
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]

    def longest(name: str) -> str | None:
        while name and name not in known:
            name = name.rpartition(".")[0]
        return name or None

    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            targets = [longest(alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in known else longest(base) for a in node.names]
        else:
            continue
        yield from ((node.lineno, target) for target in targets if target is not None and target != module)


def module_graph(root: Path = REPO) -> dict[str, dict[str, tuple[Path, int]]]:
    """Each module -> the modules it imports, each with the file and line of its first import there."""
    known = {module_name(p, root): p for p in sources(root)}
    graph: dict[str, dict[str, tuple[Path, int]]] = {}
    for module, path in known.items():
        edges = graph.setdefault(module, {})
        for line, target in sorted(imported_modules(path, module, known)):
            edges.setdefault(target, (path.relative_to(root), line))
    return graph


def cycles(root: Path = REPO) -> list[str]:
    """Every set of modules that import each other in a circle (a strongly connected component of the import
    graph), each named by one of its cycles with the line of every import on it."""
    graph = module_graph(root)
    order: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    components: list[list[str]] = []

    def connect(module: str) -> None:  # Tarjan's algorithm
        order[module] = low[module] = len(order)
        stack.append(module)
        for target in graph[module]:
            if target not in order:
                connect(target)
                low[module] = min(low[module], low[target])
            elif target in stack:
                low[module] = min(low[module], order[target])
        if low[module] == order[module]:
            component = []
            while not component or component[-1] != module:
                component.append(stack.pop())
            if len(component) > 1:
                components.append(sorted(component))

    for module in sorted(graph):
        if module not in order:
            connect(module)
    return [describe_cycle(graph, component) for component in sorted(components)]


def describe_cycle(graph: dict[str, dict[str, tuple[Path, int]]], component: list[str]) -> str:
    """The shortest way round from the component's first module back to it, import by import."""
    start, members = component[0], set(component)
    paths = {start: [start]}
    frontier = [start]
    while frontier:
        module = frontier.pop(0)
        for target in sorted(graph[module]):
            if target == start:
                circle = [*paths[module], start]
                steps = [f"{graph[a][b][0]}:{graph[a][b][1]} imports {b}" for a, b in pairwise(circle)]
                others = sorted(members - set(circle))
                more = f" (and, in circles with these, {', '.join(others)})" if others else ""
                return f"import cycle {' -> '.join(circle)}: {'; '.join(steps)}{more}"
            if target in members and target not in paths:
                paths[target] = [*paths[module], target]
                frontier.append(target)
    raise AssertionError(f"no way round {component}")  # a strongly connected component always has one


def test_every_module_is_in_a_part() -> None:
    modules = [module_name(p, REPO) for p in sources(REPO)]
    assert "npp_ros.run.loop" in modules and "npp_ros_graph.nodes.supervisor.node" in modules
    for module in modules:
        part_of(module)


def test_the_layering_holds() -> None:
    assert violations() == []


def test_no_module_imports_itself_in_a_circle() -> None:
    """Across parts the table rules out a cycle; within a part this does, function-level imports included."""
    assert cycles() == []


def test_the_layering_sees_what_npp_ros_exports() -> None:
    """npp_ros loads its exports by name on first use; its TYPE_CHECKING imports, which the checks above read,
    name exactly those, so the table sees what the package imports."""
    tree = ast.parse((REPO / "npp_ros" / "__init__.py").read_text())
    exports = next(
        ast.literal_eval(node.value)
        for node in tree.body
        if isinstance(node, ast.Assign) and any(getattr(t, "id", "") == "_EXPORTS" for t in node.targets)
    )
    imported = {
        alias.name: node.module
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("npp_ros.")
        for alias in node.names
    }
    assert imported == exports
    assert violations() == [] and MAY_IMPORT["npp_ros"]


def test_the_table_has_no_cycle() -> None:
    """Parts import downwards only: the table itself is a partial order."""
    done: set[str] = set()

    def visit(part: str, path: tuple[str, ...]) -> None:
        assert part not in path, " -> ".join([*path, part])
        if part not in done:
            for lower in MAY_IMPORT[part]:
                visit(lower, (*path, part))
            done.add(part)

    for part in MAY_IMPORT:
        visit(part, ())


@pytest.mark.parametrize(
    "folder", sorted({p.parent for p in sources(REPO) if p.parent.name not in ("nodes",)}, key=str)
)
def test_each_subpackage_says_what_it_may_import(folder: Path) -> None:
    doc = ast.get_docstring(ast.parse((folder / "__init__.py").read_text())) or ""
    assert doc.strip(), f"{folder.relative_to(REPO)}/__init__.py has no docstring"
    if folder.name not in ("npp_ros", "npp_ros_graph"):
        assert "May import" in doc or "may import" in doc, f"{folder.relative_to(REPO)}/__init__.py"


def test_the_check_catches_what_it_looks_for(tmp_path: Path) -> None:
    """A core module importing ROS lazily, and a part importing upwards, are both reported."""
    for folder in ("npp_ros/policy", "npp_ros/run", "npp_ros_graph/nodes/sim", "nodes"):
        (tmp_path / folder).mkdir(parents=True)
    (tmp_path / "npp_ros/policy/bad.py").write_text(
        "def later():\n    import rclpy\n    from npp_ros_graph.transport import topics\n    from ..run import loop\n"
    )
    (tmp_path / "npp_ros/run/loop.py").write_text("")
    found = violations(tmp_path)
    assert len(found) == 3, found  # rclpy, npp_ros_graph, npp_ros.run: one line each
    assert any("imports rclpy" in f for f in found) and any("may not import npp_ros.run" in f for f in found)


def test_the_cycle_check_names_a_cycle_through_a_function_level_import(tmp_path: Path) -> None:
    """A lazy import that closes a circle is found and named with its line; a package that re-exports its own
    modules, and a module that imports a sibling, are no cycle."""
    tasks = tmp_path / "npp_ros/tasks"
    tasks.mkdir(parents=True)
    (tmp_path / "npp_ros/__init__.py").write_text("")
    (tasks / "__init__.py").write_text("from npp_ros.tasks.registry import get\n")
    (tasks / "registry.py").write_text("from npp_ros.tasks import task\n\n\ndef get():\n    from . import sources\n")
    (tasks / "sources.py").write_text("import npp_ros.tasks.task_file\n")
    (tasks / "task_file.py").write_text("from npp_ros.tasks.registry import get\n")
    (tasks / "task.py").write_text("import math\n")
    for folder in ("npp_ros_graph", "nodes"):
        (tmp_path / folder).mkdir()
    assert cycles(tmp_path) == [
        "import cycle npp_ros.tasks.registry -> npp_ros.tasks.sources -> npp_ros.tasks.task_file -> "
        "npp_ros.tasks.registry: npp_ros/tasks/registry.py:5 imports npp_ros.tasks.sources; "
        "npp_ros/tasks/sources.py:1 imports npp_ros.tasks.task_file; "
        "npp_ros/tasks/task_file.py:1 imports npp_ros.tasks.registry"
    ]
    (tasks / "task_file.py").write_text("from npp_ros.tasks.task import math\n")
    assert cycles(tmp_path) == []
