"""npp-run's options, declared once: npp-run parses its command line with them, and GraphClient.start checks
the names it is given against them before it starts any process."""

from __future__ import annotations

import argparse
import difflib
from pathlib import Path

from npp_ros.cli.args import ListTasks, add_run_arguments
from npp_ros.run.request import FIELD_NAMES

RUN_SECTION = "npp_run"  # the parameters file's section npp-run reads, as a node's name would be


def parser(description: str = "") -> argparse.ArgumentParser:
    """npp-run's command line; ``description`` is its --help text's (npp-run's module docstring)."""
    ap = argparse.ArgumentParser(
        prog="npp-run", description=description, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add_run_arguments(ap, ("task",))
    ap.add_argument("--list-tasks", action=ListTasks, help="list every task and where it comes from, then exit")
    add_run_arguments(ap, tuple(name for name in FIELD_NAMES if name != "task"))  # every setting, one help each
    ap.add_argument(
        "--params-file", type=Path, default=None, metavar="YAML",
        help=f"settings from a ROS 2 parameters file: its '{RUN_SECTION}: ros__parameters:' section, names as the "
        "options' without the dashes (max_episodes, run_dir, ...); an option on the command line wins over the file",
    )  # fmt: skip
    ap.add_argument("--run-dir", type=Path, default=None, help="run folder; default runs/graph-TASK-seedSEED")
    ap.add_argument("--no-rollouts", action="store_true", help="skip the policy's episodes (gap checks only)")
    ap.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID for the four nodes (default: inherited)")
    ap.add_argument("--record", action="store_true", help="also record every /npp topic into RUN_DIR/bag (npp-record)")
    ap.add_argument(
        "--dashboard", type=int, nargs="?", const=8765, default=None, metavar="PORT",
        help="also serve the live dashboard on 127.0.0.1:PORT (npp-dashboard; default port 8765)",
    )  # fmt: skip
    return ap


def parse_args(description: str, argv: list[str] | None = None) -> argparse.Namespace:
    """npp-run's command line, over the settings of its --params-file when it names one."""
    ap = parser(description)
    first, _ = ap.parse_known_args(argv)
    if first.params_file is not None:
        try:
            ap.set_defaults(**file_settings(first.params_file, ap))
        except ValueError as exc:
            ap.error(str(exc))
    return ap.parse_args(argv)


def file_settings(path: Path, ap: argparse.ArgumentParser) -> dict[str, object]:
    """The ``npp_run`` section of a ROS 2 parameters file as option defaults; a ValueError names what is wrong.

    Values go in as the command line would give them (text, parsed by each option's own type), so a file and a
    command line are checked alike; a flag takes true or false."""
    import yaml

    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ValueError(f"cannot read the parameters file {path}: {exc}") from None
    sections = data if isinstance(data, dict) else {}
    section = sections.get(RUN_SECTION, sections.get(f"/{RUN_SECTION}"))
    values = section.get("ros__parameters") if isinstance(section, dict) else None
    if not isinstance(values, dict):
        raise ValueError(f"{path} has no '{RUN_SECTION}: ros__parameters:' section (found: {', '.join(sections)})")
    actions = {a.dest: a for a in ap._actions if a.option_strings and a.dest not in ("help", "list_tasks")}
    out: dict[str, object] = {}
    for name, value in values.items():
        action = actions.get(name)
        if action is None or name == "params_file":
            close = difflib.get_close_matches(str(name), list(actions), n=1)
            hint = f"; did you mean '{close[0]}'?" if close else ""
            raise ValueError(f"{path}: unknown npp-run setting '{name}'{hint}")
        if action.nargs == 0:  # a flag (store_true)
            if not isinstance(value, bool):
                raise ValueError(f"{path}: {name} takes true or false, got {value!r}")
            out[name] = value
        else:
            out[name] = str(value)
    return out


def option_names() -> frozenset[str]:
    """npp-run's options as keyword names (``max_episodes`` for --max-episodes), without --help and --list-tasks."""
    return frozenset(a.dest for a in parser()._actions if a.option_strings and a.dest not in ("help", "list_tasks"))
