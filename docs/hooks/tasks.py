"""The plug-in task reference page, generated at build time from npp_ros.tasks.task, so that it cannot drift.

A mkdocs hook (``hooks:`` in mkdocs.yml): before the build it writes, in memory, reference/tasks.md: the
Protocols a plug-in's plant and expert implement (their attributes and methods with their docstrings), the
fields of Task and OptimizerTask (type, default and the comment beside each in the source), what a Task
provides (its methods' signatures and docstrings), and ExpertOptions. Nothing is written into docs/.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import io
import re
import tokenize
from pathlib import Path
from typing import Any

from mkdocs.config.defaults import MkDocsConfig
from mkdocs.structure.files import File, Files

from npp_ros.tasks import task as task_module

SOURCE = Path(task_module.__file__)
PROTOCOLS = ("Plant", "Expert", "MeasuresValueSlope", "StopsAtTimeBudget")
PROVIDED = ("make_plant", "make_expert", "sample_initial_state", "analytic_lipschitz", "expert_value", "value_slope",
            "optimal_returns", "expert_returns")  # fmt: skip
DERIVED = ("initial_state", "epsilon", "lipschitz_choices", "default_lipschitz_choice", "resolve_lipschitz")


def cell(value: object) -> str:
    return str(value).replace("|", "\\|").replace("\n", " ")


def comments() -> dict[int, str]:
    """Each source line's trailing or own-line comment, by line number (1-based)."""
    found: dict[int, str] = {}
    for token in tokenize.generate_tokens(io.StringIO(SOURCE.read_text()).readline):
        if token.type == tokenize.COMMENT:
            found[token.start[0]] = token.string.lstrip("#").strip()
    return found


def class_nodes() -> dict[str, ast.ClassDef]:
    tree = ast.parse(SOURCE.read_text())
    return {node.name: node for node in tree.body if isinstance(node, ast.ClassDef)}


def field_comment(node: ast.ClassDef, name: str, notes: dict[int, str]) -> str:
    """The comment on a field's line, with the comment lines right above it (a field explained before it)."""
    for statement in node.body:
        if isinstance(statement, ast.AnnAssign) and getattr(statement.target, "id", None) == name:
            above, line = [], statement.lineno - 1
            while line in notes and line not in {s.lineno for s in node.body}:
                above.insert(0, notes[line])
                line -= 1
            end = statement.end_lineno or statement.lineno
            return " ".join([*above, *(notes[n] for n in range(statement.lineno, end + 1) if n in notes)])
    return ""


def default_text(field: dataclasses.Field[Any]) -> str:
    if field.default is not dataclasses.MISSING:
        value = field.default
        return f"`{value.__name__}`" if callable(value) else f"`{value!r}`"
    if field.default_factory is not dataclasses.MISSING:
        return "(a new one each)"
    return "required"


def fields_table(cls: type, own_only: type | None, notes: dict[int, str]) -> list[str]:
    """A dataclass's fields (those ``own_only``'s lacks or re-defaults, when given) as a table."""
    node = class_nodes()[cls.__name__]
    inherited = {f.name: f for f in dataclasses.fields(own_only)} if own_only else {}
    rows = ["| field | type | default | meaning |", "|---|---|---|---|"]
    for field in dataclasses.fields(cls):
        base = inherited.get(field.name)
        if base is not None and default_text(base) == default_text(field):
            continue
        rows.append(
            f"| `{field.name}` | `{cell(field.type)}` | {cell(default_text(field))} | "
            f"{cell(field_comment(node, field.name, notes))} |"
        )
    return rows


def doc_of(obj: Any) -> str:
    """A docstring on one line, its reST roles and double backquotes as Markdown code."""
    text = " ".join((inspect.getdoc(obj) or "").split())
    text = re.sub(r":\w+:`~?([\w.]+)`", lambda m: f"`{m.group(1).rsplit('.', 1)[-1]}`", text)
    return text.replace("``", "`")


def signature(obj: Any) -> str:
    """A method's signature as written (annotations unquoted, the default options by name)."""
    text = str(inspect.signature(obj)).replace("'", "")
    return re.sub(r"ExpertOptions\([^)]*\)", "DEFAULT_OPTIONS", text)


def protocol_section(name: str, notes: dict[int, str]) -> list[str]:
    cls = getattr(task_module, name)
    node = class_nodes()[name]
    lines = [f"### `{name}`", "", doc_of(cls), ""]
    rows = ["| member | kind | meaning |", "|---|---|---|"]
    for statement in node.body:
        if isinstance(statement, ast.AnnAssign):
            member = statement.target.id  # type: ignore[attr-defined]
            annotation = ast.unparse(statement.annotation)
            rows.append(f"| `{member}: {cell(annotation)}` | attribute | {cell(notes.get(statement.lineno, ''))} |")
        elif isinstance(statement, ast.FunctionDef):
            method = getattr(cls, statement.name)
            rows.append(f"| `{statement.name}{cell(signature(method))}` | method | {cell(doc_of(method))} |")
    return [*lines, *rows, ""]


def methods_table(names: tuple[str, ...]) -> list[str]:
    rows = ["| method | what it does |", "|---|---|"]
    for name in names:
        method = getattr(task_module.Task, name)
        rows.append(f"| `{name}{cell(signature(method))}` | {cell(doc_of(method))} |")
    return rows


def tasks_page() -> str:
    notes = comments()
    lines = [
        "# Tasks: what a plug-in implements",
        "",
        "Generated at build time from `npp_ros/tasks/task.py` (its classes, fields, signatures, docstrings and",
        "the comments beside the fields). A plug-in package registers a `Task` under the entry-point group",
        "`npp_ros.tasks` ([Your own robot](../tutorials/own-robot.md#plug-in-packages)); how to write one, step",
        "by step, is [A task of your own](../tutorials/own-task.md).",
        "",
        "## The Protocols",
        "",
        "A task's plant and expert are duck-typed: these are what the sim, the expert node, the supervisor",
        "and the in-process commands use. The last two are optional: an expert that has them is recognised",
        "at run time (`isinstance`).",
        "",
    ]
    for name in PROTOCOLS:
        lines += protocol_section(name, notes)
    lines += ["## `Task`", "", doc_of(task_module.Task), "", *fields_table(task_module.Task, None, notes), ""]
    lines += ["### What each task provides", "", "A subclass overrides these; the first three are required.", ""]
    lines += [*methods_table(PROVIDED), ""]
    lines += ["### Derived, shared", "", "Every task inherits these; a subclass rarely overrides them.", ""]
    lines += [*methods_table(DERIVED), ""]
    lines += [
        "## `OptimizerTask`",
        "",
        doc_of(task_module.OptimizerTask),
        "",
        "Its fields beyond `Task`'s (and those it gives another default):",
        "",
        *fields_table(task_module.OptimizerTask, task_module.Task, notes),
        "",
        "## `ExpertOptions`",
        "",
        doc_of(task_module.ExpertOptions),
        "",
        *fields_table(task_module.ExpertOptions, None, notes),
        "",
    ]
    return "\n".join(lines)


def on_files(files: Files, config: MkDocsConfig) -> Files:
    files.append(File.generated(config, "reference/tasks.md", content=tasks_page()))
    return files
