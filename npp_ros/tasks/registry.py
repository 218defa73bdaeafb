"""The task registry: every task by name, and the one lookup the run set-up, the CLIs and the nodes use.

A task says what its plant and expert are, how s0 ~ rho is drawn, what the dataset stores, which L
choices it can resolve and its paper constants (the contract, npp_ros.tasks.task, whose names this
module re-exports). Nothing outside a task's own module names its plant or expert:
``npp_ros.run.setup``, ``npp-learn``, ``npp-experiment`` and the nodes call :func:`get_task`.

Adding a task is one module (plant, expert and one :class:`Task` instance, usually an
:class:`OptimizerTask` around an :class:`~npp_ros.trajopt.expert.OptimizingExpert`) and one line in
:data:`REGISTRY`, or, outside npp_ros, an entry point in the group ``npp_ros.tasks`` of any installed
package, or a task file (``.toml``, npp_ros.tasks.task_file.loader); npp_ros.tasks.sources reads those. The
registry holds import paths, so listing the names loads no plant, and a task module may import this one.
Every command lists the same tasks: :data:`TASK_NAMES` (help texts, :func:`by_task`) are the built-in
ones, :func:`task_names` and :func:`describe_tasks` add the plug-ins.
"""

from __future__ import annotations

import functools

from npp_ros.tasks.sources import TaskSource, is_task_file, load, merge
from npp_ros.tasks.task import DEFAULT_OPTIONS as DEFAULT_OPTIONS
from npp_ros.tasks.task import MAX_HORIZON as MAX_HORIZON
from npp_ros.tasks.task import SPEED_ONLY_OPTIONS as SPEED_ONLY_OPTIONS
from npp_ros.tasks.task import Expert as Expert
from npp_ros.tasks.task import ExpertOptions as ExpertOptions
from npp_ros.tasks.task import MeasuresValueSlope as MeasuresValueSlope
from npp_ros.tasks.task import OptimizerTask as OptimizerTask
from npp_ros.tasks.task import Plant as Plant
from npp_ros.tasks.task import StopsAtTimeBudget as StopsAtTimeBudget
from npp_ros.tasks.task import Task as Task
from npp_ros.tasks.task import UnknownTaskError as UnknownTaskError
from npp_ros.tasks.task import check_horizon as check_horizon
from npp_ros.tasks.task import control_space as control_space
from npp_ros.tasks.task import episode_rng as episode_rng
from npp_ros.tasks.task_file.loader import load_task_file

REGISTRY: dict[str, str] = {
    "lqr_2_1": "npp_ros.tasks.builtin.lqr:LQR_2_1",
    "lqr_6_2": "npp_ros.tasks.builtin.lqr:LQR_6_2",
    "pendulum_swingup": "npp_ros.tasks.builtin.pendulum:SWINGUP",
    "cartpole_swingup": "npp_ros.tasks.builtin.cartpole:SWINGUP",
    "acrobot_swingup": "npp_ros.tasks.builtin.acrobot:SWINGUP",
}
"""Task name -> "module:attribute" of its :class:`Task`: npp_ros's own tasks, all of them."""

TASK_NAMES: tuple[str, ...] = tuple(sorted(REGISTRY))
"""The built-in tasks, sorted; :func:`task_names` adds the plug-ins."""


@functools.cache
def _registered() -> tuple[dict[str, TaskSource], tuple[str, ...]]:
    """Every registered task by name, and what could not be registered (in words); cached per process."""
    return merge(REGISTRY)


def refresh() -> None:
    """Forget what was scanned (after installing a plug-in in a running process)."""
    _registered.cache_clear()
    _load_registered.cache_clear()


def registered() -> dict[str, TaskSource]:
    """Every registered task (built-in and plug-in) by name."""
    return dict(_registered()[0])


def registration_problems() -> tuple[str, ...]:
    """Plug-in entries that were not registered, and why."""
    return _registered()[1]


def task_names() -> tuple[str, ...]:
    """Every registered task's name, sorted (task files are accepted besides these)."""
    return tuple(sorted(_registered()[0]))


def unknown(name: str) -> str:
    return f"unknown task {name!r}; known tasks: {', '.join(task_names())}, or a task file (.toml)"


def get_task(name: str) -> Task:
    """The task ``name``: built in, from a plug-in package (imported on first use), or a task file; an
    unknown name is refused with the known ones, a plug-in that does not load with its error."""
    if is_task_file(name):
        return load_task_file(name)
    return _load_registered(name)


def task_label(name: str) -> str:
    """The task as outputs name it for people: a task file's ``name`` key (its identity, the path and content
    hash, stays in run files and messages); any other task's registered name, or the name as given where it no longer
    loads (a label must not stop an output)."""
    try:
        task = get_task(name)
    except (ValueError, OSError):  # UnknownTaskError, TaskFileError (a file changed or gone): both ValueErrors
        return name
    label = getattr(getattr(task, "definition", None), "label", "")
    return label if isinstance(label, str) and label else name


@functools.cache
def _load_registered(name: str) -> Task:
    found = _registered()[0]
    if name not in found:
        raise UnknownTaskError(unknown(name))
    return load(found[name])


def describe_tasks(check: bool = True) -> str:
    """The task listing (``npp-learn --list-tasks``, the sim's --help): each task and where it comes from.

    ``check`` imports each plug-in to say whether it loads (built-in tasks are npp_ros's own).
    """
    rows = []
    for name in task_names():
        source = _registered()[0][name]
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


def by_task(attribute: str, tasks: tuple[str, ...] | None = None) -> str:
    """A help text's list of one property of every task that has it ("50 lqr_2_1, 300 lqr_6_2, ..."), from the
    tasks themselves (every built-in task by default), so that no command's help can go stale when a task is
    added or changed."""
    values = [(name, getattr(get_task(name), attribute)) for name in (tasks or TASK_NAMES)]
    return ", ".join(f"{value:g} {name}" if isinstance(value, float) else f"{value} {name}"
                     for name, value in values if value is not None)  # fmt: skip
