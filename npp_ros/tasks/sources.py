"""Where tasks come from besides npp_ros's own: plug-in packages and task files.

- Plug-ins: any installed package that declares entry points in the group ``npp_ros.tasks``
  (``name = "module:attribute"`` of a :class:`~npp_ros.tasks.task.Task`), e.g. in its pyproject.toml::

      [project.entry-points."npp_ros.tasks"]
      my_arm_reach = "my_robot.tasks:REACH"

  Listing reads the installed packages' metadata and imports nothing, so a CLI's ``--task`` and
  the sim's ``task`` parameter list every task without loading a plant. A plug-in is imported
  when its task is asked for; one that fails to import is refused by name with its error, and
  every other task still works. A plug-in cannot replace a built-in task (same name): it is
  listed as ignored. An entry point that names a built-in task with the built-in's own target is
  that task, registered once (an install of npp_ros made while its pyproject.toml still declared its
  acrobot as an entry point has one).
- Task files: a path ending in ``.toml`` (npp_ros.tasks.task_file.loader), accepted wherever a name is.

:func:`merge` joins the plug-ins to the built-in tasks; npp_ros.tasks.registry holds the built-in
table (``REGISTRY``) and the lookup every command and node uses.
"""

from __future__ import annotations

import importlib
import importlib.metadata
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from npp_ros.tasks.task import Task, UnknownTaskError
from npp_ros.tasks.task_file.schema import HASH_MARK

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


def merge(built_in: Mapping[str, str]) -> tuple[dict[str, TaskSource], tuple[str, ...]]:
    """The built-in tasks (name -> "module:attribute") and every installed plug-in's, by name, and the
    plug-in entries that were not registered, each in words."""
    found = {name: TaskSource(name, target, BUILT_IN) for name, target in built_in.items()}
    problems: list[str] = []
    entries = sorted(importlib.metadata.entry_points(group=ENTRY_POINT_GROUP), key=lambda e: (e.name, e.value))
    for entry in entries:
        dist = getattr(entry, "dist", None)
        origin = f"plug-in {dist.name} {dist.version}" if dist is not None else "plug-in"
        if entry.name in found and found[entry.name].built_in and found[entry.name].target == entry.value:
            continue  # the built-in task itself, declared again as an entry point
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


def load(source: TaskSource) -> Task:
    """The Task a registered source names, imported now; a plug-in that does not load is a TaskLoadError."""
    module, _, attribute = source.target.partition(":")
    try:
        task = getattr(importlib.import_module(module), attribute)
    except Exception as exc:
        if source.built_in:
            raise
        raise TaskLoadError(
            f"task {source.name!r} ({source.origin}, {source.target}) does not load: {type(exc).__name__}: {exc}"
        ) from None
    if not isinstance(task, Task) or task.name != source.name:
        what = f"the Task named {task.name!r}" if isinstance(task, Task) else f"a {type(task).__name__}, not a Task"
        raise TaskLoadError(f"task {source.name!r} ({source.origin}): {source.target} is {what}")
    return task


def is_task_file(name: str) -> bool:
    """A task file's path, or the name a sim published for one (path and content hash)."""
    return name.endswith(TASK_FILE_SUFFIX) or f"{TASK_FILE_SUFFIX}{HASH_MARK}" in name


def short_name(name: str) -> str:
    """A name fit for a folder: a registered task's own, or a task file's folder and stem (arm-task)."""
    if not is_task_file(name):
        return name
    path = Path(name.split(HASH_MARK, 1)[0])
    return f"{path.parent.name}-{path.stem}" if path.parent.name else path.stem
