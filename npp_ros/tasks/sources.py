"""Where tasks come from: npp_ros's own, plug-in packages, and task files.

- Built in: :data:`npp_ros.tasks.registry.REGISTRY`.
- Plug-ins: any installed package that declares entry points in the group ``npp_ros.tasks``
  (``name = "module:attribute"`` of a :class:`~npp_ros.tasks.Task`), e.g. in its pyproject.toml::

      [project.entry-points."npp_ros.tasks"]
      my_arm_reach = "my_robot.tasks:REACH"

  Listing reads the installed packages' metadata and imports nothing, so a CLI's ``--task`` and
  the sim's ``task`` parameter list every task without loading a plant. A plug-in is imported
  when its task is asked for; one that fails to import is refused by name with its error, and
  every other task still works. A plug-in cannot replace a built-in task (same name): it is
  listed as ignored.
- Task files: a path ending in ``.toml`` (npp_ros.tasks.task_file), accepted wherever a name is.
"""

from __future__ import annotations

import functools
import importlib
import importlib.metadata
from dataclasses import dataclass

from npp_ros.tasks.registry import REGISTRY, Task, UnknownTaskError

ENTRY_POINT_GROUP = "npp_ros.tasks"
TASK_FILE_SUFFIX = ".toml"
BUILT_IN = "built-in"


class TaskLoadError(UnknownTaskError):
    """A registered task that cannot be loaded (a plug-in that fails to import, or names no Task)."""


@dataclass(frozen=True)
class TaskSource:
    """Where one registered task comes from."""

    name: str
    target: str  # "module:attribute" of its Task
    origin: str  # "built-in", or "plug-in DIST VERSION"

    @property
    def built_in(self) -> bool:
        return self.origin == BUILT_IN


@functools.cache
def _scan() -> tuple[dict[str, TaskSource], tuple[str, ...]]:
    """Every registered task by name, and what could not be registered (in words); cached per process."""
    found = {name: TaskSource(name, target, BUILT_IN) for name, target in REGISTRY.items()}
    problems: list[str] = []
    entries = sorted(importlib.metadata.entry_points(group=ENTRY_POINT_GROUP), key=lambda e: (e.name, e.value))
    for entry in entries:
        dist = getattr(entry, "dist", None)
        origin = f"plug-in {dist.name} {dist.version}" if dist is not None else "plug-in"
        if entry.name in found:
            problems.append(
                f"task {entry.name!r} of {origin} is ignored: the {found[entry.name].origin} task has that name"
            )
        elif ":" not in entry.value:
            problems.append(f"task {entry.name!r} of {origin} is ignored: {entry.value!r} is not 'module:attribute'")
        elif is_task_file(entry.name):
            problems.append(f"task {entry.name!r} of {origin} is ignored: a task name cannot end in .toml")
        else:
            found[entry.name] = TaskSource(entry.name, entry.value, origin)
    return found, tuple(problems)


def refresh() -> None:
    """Forget what was scanned (after installing a plug-in in a running process)."""
    _scan.cache_clear()
    _load_registered.cache_clear()


def sources() -> dict[str, TaskSource]:
    """Every registered task (built-in and plug-in) by name."""
    return dict(_scan()[0])


def registration_problems() -> tuple[str, ...]:
    """Plug-in entries that were not registered, and why."""
    return _scan()[1]


def task_names() -> tuple[str, ...]:
    """Every registered task's name, sorted (task files are accepted besides these)."""
    return tuple(sorted(_scan()[0]))


def is_task_file(name: str) -> bool:
    return name.endswith(TASK_FILE_SUFFIX) or f"{TASK_FILE_SUFFIX}#sha256=" in name


def short_name(name: str) -> str:
    """A name fit for a folder: a registered task's own, or a task file's folder and stem (arm-task)."""
    if not is_task_file(name):
        return name
    from pathlib import Path

    path = Path(name.split("#", 1)[0])
    return f"{path.parent.name}-{path.stem}" if path.parent.name else path.stem


def unknown(name: str) -> str:
    return f"unknown task {name!r}; known tasks: {', '.join(task_names())}, or a task file (.toml)"


def load_task(name: str) -> Task:
    """The task ``name``: a registered one (imported on first use) or a task file."""
    if is_task_file(name):
        from npp_ros.tasks.task_file import load_task_file

        return load_task_file(name)
    return _load_registered(name)


@functools.cache
def _load_registered(name: str) -> Task:
    found = _scan()[0]
    if name not in found:
        raise UnknownTaskError(unknown(name))
    source = found[name]
    module, _, attribute = source.target.partition(":")
    try:
        task = getattr(importlib.import_module(module), attribute)
    except Exception as exc:
        if source.built_in:
            raise
        raise TaskLoadError(
            f"task {name!r} ({source.origin}, {source.target}) does not load: {type(exc).__name__}: {exc}"
        ) from None
    if not isinstance(task, Task) or task.name != name:
        what = f"the Task named {task.name!r}" if isinstance(task, Task) else f"a {type(task).__name__}, not a Task"
        raise TaskLoadError(f"task {name!r} ({source.origin}): {source.target} is {what}")
    return task


def describe_tasks(check: bool = True) -> str:
    """The task listing (``npp-learn --list-tasks``, the sim's --help): each task and where it comes from.

    ``check`` imports each plug-in to say whether it loads (built-in tasks are npp_ros's own).
    """
    rows = []
    for name in task_names():
        source = _scan()[0][name]
        status = ""
        if check and not source.built_in:
            try:
                _load_registered(name)
            except UnknownTaskError as exc:
                status = f"  DOES NOT LOAD: {str(exc).split(': ', 1)[-1]}"
        rows.append(f"  {name:<24} {source.origin:<28} {source.target}{status}")
    lines = ["tasks (name, where it comes from, its Task):", *rows]
    lines += [f"  ignored: {problem}" for problem in registration_problems()]
    lines.append("  any path ending in .toml: a task file (a MuJoCo model and its task, no Python)")
    return "\n".join(lines)
