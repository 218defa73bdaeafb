"""Security basics: nothing that loads data can execute it.

Every module of the core (npp_ros/), the ROS graph (npp_ros_graph/) and the node scripts (nodes/) is parsed,
and the test fails on: pickle-like modules (pickle, cPickle, dill, shelve, marshal, joblib),
eval/exec/compile/__import__, unsafe YAML loading (yaml.load, yaml.unsafe_load, yaml.full_load,
yaml.Loader / UnsafeLoader / FullLoader), numpy.load with allow_pickle=True, torch.load, and subprocess
calls with shell=True.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SOURCES = sorted(p for folder in ("npp_ros", "npp_ros_graph", "nodes") for p in (REPO / folder).rglob("*.py"))
PICKLE_LIKE = {"pickle", "cPickle", "_pickle", "dill", "shelve", "marshal", "joblib", "cloudpickle"}
CALLS = {"eval", "exec", "compile", "__import__"}
UNSAFE_ATTRS = {
    ("yaml", "load"), ("yaml", "unsafe_load"), ("yaml", "full_load"), ("yaml", "load_all"),
    ("yaml", "Loader"), ("yaml", "UnsafeLoader"), ("yaml", "FullLoader"), ("torch", "load"),
}  # fmt: skip


def findings(path: Path, root: Path = REPO) -> list[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    found: list[str] = []
    where = path.relative_to(root)
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [
                f"{where}:{node.lineno} imports {a.name}" for a in node.names if a.name.split(".")[0] in PICKLE_LIKE
            ]
        elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] in PICKLE_LIKE:
            found.append(f"{where}:{node.lineno} imports from {node.module}")
        elif isinstance(node, ast.ImportFrom) and node.module == "yaml":
            bad = {a.name for a in node.names} & {attr for mod, attr in UNSAFE_ATTRS if mod == "yaml"}
            found += [f"{where}:{node.lineno} imports yaml.{name}" for name in sorted(bad)]
        elif isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            if (node.value.id, node.attr) in UNSAFE_ATTRS:
                found.append(f"{where}:{node.lineno} uses {node.value.id}.{node.attr}")
        elif isinstance(node, ast.Call):
            if isinstance(node.func, ast.Name) and node.func.id in CALLS:
                found.append(f"{where}:{node.lineno} calls {node.func.id}()")
            for kw in node.keywords:
                truthy = isinstance(kw.value, ast.Constant) and bool(kw.value.value)
                if kw.arg in ("allow_pickle", "shell") and (truthy or not isinstance(kw.value, ast.Constant)):
                    found.append(f"{where}:{node.lineno} passes {kw.arg}={ast.unparse(kw.value)}")
    return found


def test_sources_are_found() -> None:
    paths = {str(p.relative_to(REPO)) for p in SOURCES}
    expected = {"npp_ros/run/store.py", "npp_ros/policy/dataset.py", "npp_ros_graph/nodes/supervisor/node.py",
                "npp_ros_graph/runtime/node.py", "nodes/npp_sim.py"}  # fmt: skip
    assert expected <= paths


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(REPO)))
def test_no_pickle_eval_exec_or_unsafe_yaml(path: Path) -> None:
    assert findings(path) == []


def test_the_scanner_catches_what_it_looks_for(tmp_path: Path) -> None:
    """The check itself is checked: each forbidden pattern in a scratch file is reported."""
    bad = tmp_path / "npp_ros" / "bad.py"
    bad.parent.mkdir()
    bad.write_text(
        "import pickle\nfrom yaml import load\nimport yaml, numpy, subprocess\n"
        "eval('1')\nexec('x = 1')\nyaml.load(s)\nnumpy.load(f, allow_pickle=True)\n"
        "subprocess.run('ls', shell=True)\n"
    )
    found = findings(bad, tmp_path)
    assert len(found) == 7, found
