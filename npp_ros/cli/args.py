"""Typed command-line values shared by the CLIs: a bad count is refused by argparse, naming the option.

argparse turns the ArgumentTypeError into ``npp-learn: error: argument --max-episodes: must be
an integer >= 1, got '0'`` and exit code 2, before any work or any file is written.
"""

from __future__ import annotations

import argparse


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


TASK_HELP = "a task: a registered name (see --list-tasks; plug-ins too) or a task file (path ending in .toml)"
