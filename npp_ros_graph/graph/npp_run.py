"""npp-run's options, declared once: npp-run parses its command line with them, and GraphClient.start checks
the names it is given against them before it starts any process."""

from __future__ import annotations

import argparse
from pathlib import Path

from npp_ros.cli.args import ListTasks, add_run_arguments
from npp_ros.run.request import FIELD_NAMES


def parser(description: str = "") -> argparse.ArgumentParser:
    """npp-run's command line; ``description`` is its --help text's (npp-run's module docstring)."""
    ap = argparse.ArgumentParser(
        prog="npp-run", description=description, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add_run_arguments(ap, ("task",))
    ap.add_argument("--list-tasks", action=ListTasks, help="list every task and where it comes from, then exit")
    add_run_arguments(ap, tuple(name for name in FIELD_NAMES if name != "task"))  # every setting, one help each
    ap.add_argument("--run-dir", type=Path, default=None, help="run folder; default runs/graph-TASK-seedSEED")
    ap.add_argument("--no-rollouts", action="store_true", help="skip the policy's episodes (gap checks only)")
    ap.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID for the four nodes (default: inherited)")
    ap.add_argument("--record", action="store_true", help="also record every /npp topic into RUN_DIR/bag (npp-record)")
    ap.add_argument(
        "--dashboard", type=int, nargs="?", const=8765, default=None, metavar="PORT",
        help="also serve the live dashboard on 127.0.0.1:PORT (npp-dashboard; default port 8765)",
    )  # fmt: skip
    return ap


def option_names() -> frozenset[str]:
    """npp-run's options as keyword names (``max_episodes`` for --max-episodes), without --help and --list-tasks."""
    return frozenset(a.dest for a in parser()._actions if a.option_strings and a.dest not in ("help", "list_tasks"))
