"""Reference pages generated at build time from the code's own tables, so that they cannot drift.

A mkdocs hook (``hooks:`` in mkdocs.yml): before the build it writes, in memory,

- reference/nodes.md: every node's USAGE text (topics, services) and its parameter table (``PARAMETERS``);
- reference/commands.md: every console script's ``--help``, from the scripts the package declares;
- reference/interfaces.md: the .msg and .srv files of msgs_py/npp_interfaces;
- reference/layers.md: every package and module with the first line of its docstring, and which part may
  import which, from the table tests/test_layering.py checks;

and adds the committed results (tables and figures under results/) to the site, so that pages link to
them where they are. Nothing is fetched and nothing is written into docs/.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import os
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

from mkdocs.config.defaults import MkDocsConfig
from mkdocs.structure.files import File, Files

from npp_ros_graph.transport.parameters import parameter_help

REPO = Path(__file__).resolve().parents[2]
NODE_PACKAGE = "npp_ros_graph.nodes"
HELP_TIMEOUT_S = 120.0
RESULT_SUFFIXES = (".png", ".md")


def console_scripts() -> dict[str, str]:
    """The package's commands and their entry points, as pyproject.toml declares them."""
    with open(REPO / "pyproject.toml", "rb") as f:
        return tomllib.load(f)["project"]["scripts"]


def fenced(text: str, language: str = "text") -> str:
    return f"```{language}\n{text.rstrip()}\n```\n"


def cell(value: object) -> str:
    return str(value).replace("|", "\\|").replace("\n", " ")


def node_page() -> str:
    """USAGE and the parameter table of every node the package declares as a command."""
    lines = [
        "# Nodes",
        "",
        "Generated at build time from each node's `USAGE` text (what `--help` prints) and its `PARAMETERS`",
        "table (what `ros2 param describe` shows). Set a parameter with `--ros-args -p name:=value`; an",
        "unknown name or a value outside its range is refused at start with one line naming it.",
        "",
    ]
    for command, entry in console_scripts().items():
        module_name = entry.split(":")[0]
        if not module_name.startswith(NODE_PACKAGE):
            continue
        module = importlib.import_module(module_name)
        params: tuple[Any, ...] = getattr(module, "PARAMETERS", ())
        usage = module.USAGE.replace(parameter_help(params), "") if params else module.USAGE
        lines += [f"## `{command}`", "", f"Module `{module_name}`.", "", fenced(usage), ""]
        if params:
            lines += ["| parameter | default | allowed | meaning |", "|---|---|---|---|"]
            lines += [f"| `{p.name}` | `{p.default!r}` | {cell(p.allowed())} | {cell(p.description)} |" for p in params]
        else:
            lines.append("No parameters.")
        lines.append("")
    return "\n".join(lines)


def help_text(command: str, entry: str) -> str:
    """A command's --help, from its entry point in a fresh interpreter (as the installed script runs it)."""
    module_name, function = entry.split(":")
    code = f"import sys; sys.argv = [{command!r}, '--help']; from {module_name} import {function} as m; sys.exit(m())"
    env = {**os.environ, "COLUMNS": "100"}
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=HELP_TIMEOUT_S, env=env, cwd=REPO
    )
    if done.returncode != 0 or not done.stdout.strip():
        raise RuntimeError(f"{command} --help failed (exit {done.returncode}): {done.stderr.strip()[-500:]}")
    return done.stdout


def command_page() -> str:
    """Every command's options from its own parser (nodes are on the Nodes page)."""
    lines = [
        "# Commands",
        "",
        "Generated at build time from each command's `--help` (its argparse parser). The four nodes' texts",
        "and parameters are on the [Nodes](nodes.md) page.",
        "",
    ]
    for command, entry in console_scripts().items():
        if entry.startswith(NODE_PACKAGE):
            lines += [f"## `{command}`", "", f"A node: see [Nodes](nodes.md#{command}).", ""]
            continue
        lines += [f"## `{command}`", "", f"Entry point `{entry}`.", "", fenced(help_text(command, entry)), ""]
    return "\n".join(lines)


def interface_page() -> str:
    """The message and service definitions, verbatim."""
    root = REPO / "msgs_py" / "npp_interfaces"
    lines = [
        "# Interfaces",
        "",
        "Generated at build time from the definitions in `msgs_py/npp_interfaces`, which the set-up builds",
        "with rosidl. Fields are sealed in this order (see [Reliability](../reliability.md#the-runs-seal)).",
        "",
    ]
    for kind, folder in (("Messages", "msg"), ("Services", "srv")):
        lines += [f"## {kind}", ""]
        for path in sorted((root / folder).glob(f"*.{folder}")):
            lines += [f"### `npp_interfaces/{folder}/{path.stem}`", "", fenced(path.read_text()), ""]
    return "\n".join(lines)


def layering_table() -> dict[str, frozenset[str]]:
    """The layering test's own table (which part may import which)."""
    spec = importlib.util.spec_from_file_location("npp_layering", REPO / "tests" / "test_layering.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.MAY_IMPORT


def first_line(path: Path) -> str:
    """The first line of a module's docstring ("" without one)."""
    doc = ast.get_docstring(ast.parse(path.read_text()))
    return doc.strip().splitlines()[0] if doc else ""


def layers_page() -> str:
    """Every package and module, bottom up as the layering table lists them, with what each part may import."""
    table = layering_table()
    lines = [
        "# Packages and modules",
        "",
        "Generated at build time from the packages' and modules' docstrings and from the table that",
        "`tests/test_layering.py` checks every import against (imports inside functions included).",
        "",
    ]
    for part, allowed in table.items():
        folder = REPO / part.replace(".", "/")
        if not (folder / "__init__.py").exists():
            continue
        may = ", ".join(f"`{name}`" for name in sorted(allowed)) or "nothing else of the packages"
        lines += [f"## `{part}`", "", first_line(folder / "__init__.py"), "", f"May import: {may}.", ""]
        modules = sorted(p for p in folder.glob("*.py") if p.name != "__init__.py")
        if modules:
            lines += ["| module | what it holds |", "|---|---|"]
            lines += [f"| `{part}.{m.stem}` | {cell(first_line(m))} |" for m in modules]
            lines.append("")
    return "\n".join(lines)


def on_files(files: Files, config: MkDocsConfig) -> Files:
    """Add the generated reference pages and the committed results to the site."""
    pages = {
        "reference/nodes.md": node_page(),
        "reference/commands.md": command_page(),
        "reference/interfaces.md": interface_page(),
        "reference/layers.md": layers_page(),
    }
    for uri, content in pages.items():
        files.append(File.generated(config, uri, content=content))
    for path in sorted((REPO / "results").rglob("*")):
        if path.suffix in RESULT_SUFFIXES and "runs" not in path.relative_to(REPO).parts:
            uri = path.relative_to(REPO).as_posix()
            files.append(File(uri, str(REPO), config.site_dir, config.use_directory_urls))
    return files
