"""Typed command-line values shared by the CLIs: a bad count is refused by argparse, naming the option.

argparse turns the ArgumentTypeError into ``npp-learn: error: argument --max-episodes: must be
an integer >= 1, got '0'`` and exit code 2, before any work or any file is written.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Mapping
from typing import Any

from npp_ros.run.request import COUNT, INDEX, NUMBER, TASK, RunRequest, request_fields
from npp_ros.run.request import TASK_HELP as TASK_HELP


def _integer(text: str, least: int) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer >= {least}, got {text!r}") from None
    if value < least:
        raise argparse.ArgumentTypeError(f"must be an integer >= {least}, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """A count that must be at least 1 (episodes, rollouts, steps, processes)."""
    return _integer(text, 1)


def nonnegative_int(text: str) -> int:
    """A seed, or a count where 0 means none."""
    return _integer(text, 0)


def positive_ints(text: str) -> tuple[int, ...]:
    """A comma-separated list of counts, each at least 1 (e.g. checkpoints: 10,20,30)."""
    try:
        return tuple(positive_int(part) for part in text.split(","))
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"must be integers >= 1 separated by commas, got {text!r}") from None


def task_name(text: str) -> str:
    """A task: a registered name (built in or from a plug-in) or a task file, as its canonical name.

    A plug-in that does not load, or a bad task file, is refused here with its one-line reason.
    """
    from npp_ros.tasks.registry import get_task

    try:
        return get_task(text).name
    except (ValueError, TypeError) as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


class ListTasks(argparse.Action):
    """``--list-tasks``: print every task and where it comes from, then exit."""

    def __init__(self, option_strings: list[str], dest: str, **kwargs: object) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, help=kwargs.get("help"))  # type: ignore[arg-type]

    def __call__(self, parser: argparse.ArgumentParser, *_: object) -> None:
        from npp_ros.tasks.registry import describe_tasks

        print(describe_tasks())
        parser.exit()


def flag(name: str) -> str:
    """A request field's command-line option: ``max_episodes`` is ``--max-episodes``."""
    return "--" + name.replace("_", "-")


def add_run_arguments(
    ap: argparse.ArgumentParser,
    names: tuple[str, ...] | None = None,
    *,
    flags: Mapping[str, str] | None = None,
    lists: tuple[str, ...] = (),
    choices: Mapping[str, tuple[str, ...]] | None = None,
    defaults: Mapping[str, Any] | None = None,
    helps: Mapping[str, Callable[[str], str]] | None = None,
) -> None:
    """The request's fields (those named; all by default) as options, each with the request's one help text.

    A command that differs says so by field: another option name (``flags``), several values side by side
    (``lists``, each a list), other allowed values (``choices``) or defaults (``defaults``), and its help around
    the request's (``helps``: the request's text in, the command's out). The parsed values keep the field's name.
    """
    flags, choices, defaults, helps = flags or {}, choices or {}, defaults or {}, helps or {}
    types: dict[str, Callable[[str], Any]] = {
        TASK: task_name,
        INDEX: nonnegative_int,
        COUNT: positive_int,
        NUMBER: float,
    }
    for field, setting in request_fields(names):
        name = field.name
        default = defaults.get(name, field.default)
        allowed = choices.get(name, setting.choices if setting.kind != "lipschitz" else ())
        text = setting.text()
        options: dict[str, Any] = {
            "dest": name,
            "default": [default] if name in lists and name not in defaults and default is not None else default,
            "help": helps[name](text) if name in helps else text,
        }
        if name in lists:
            options["nargs"] = "+"
        if allowed:
            options["choices"] = allowed
        if setting.kind in types:
            options["type"] = types[setting.kind]
        if setting.metavar:
            options["metavar"] = setting.metavar
        ap.add_argument(flags.get(name, flag(name)), **options)


def help_of(name: str) -> str:
    """A request field's one help text, for a command that spells its option its own way (several values)."""
    return next(setting for _, setting in request_fields((name,))).text()


def run_request(args: argparse.Namespace, **given: Any) -> RunRequest:
    """The request a command's parsed options make (the fields it has), with ``given`` over them."""
    values = {field.name: getattr(args, field.name) for field, _ in request_fields() if hasattr(args, field.name)}
    return RunRequest(**{**values, **given})
