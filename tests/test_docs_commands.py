"""The commands the README and the tutorials show work as shown: each one's flags parse with the command's
own parser, a node's ``-p name:=value`` names one of its parameters with an allowed value, every repository
path in them exists, and each experiment shown over a results folder plans the arms that folder holds.

Fast: a command is run only up to its argument parsing (``parse_args`` stops it there), and no ROS graph
starts. A path under runs/ (not in git, made by running) passes where a shown command writes it (``--out``,
``--run-dir``, ``-o``, the supervisor's ``run_dir``) or where the docs' prose names it beside the command
that makes it.
"""

from __future__ import annotations

import argparse
import importlib
import json
import re
import shlex
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
DOCS = (REPO / "README.md", *sorted((REPO / "docs" / "tutorials").glob("*.md")))
SHELL_BLOCKS = ("bash", "sh", "shell", "console")
NODE_PACKAGE = "npp_ros_graph.nodes"
PLACEHOLDERS = {"my_task": "lqr_2_1"}  # own-task.md's task is the one its reader adds: its flags are tried on another
OUTPUT_OPTIONS = ("--out", "--run-dir", "-o", "--logs")  # what a command writes (a runs/ path there is made by it)
OUTPUT_PARAMETERS = {"npp-supervisor": ("run_dir",), "npp-robot-run": ("run_dir",)}  # they make the run file there
CONTROL = ("&", "&&", ";", "|", "||")


@dataclass(frozen=True)
class Shown:
    """One command line in a shell block of a page: the command's name and its arguments."""

    doc: Path
    line: int
    command: str
    argv: tuple[str, ...]

    def __str__(self) -> str:
        return f"{self.doc.relative_to(REPO)}:{self.line}: {' '.join((self.command, *self.argv))}"


def console_scripts() -> dict[str, str]:
    with open(REPO / "pyproject.toml", "rb") as f:
        return tomllib.load(f)["project"]["scripts"]


def code_blocks(text: str) -> Iterator[tuple[int, str, str]]:
    """Each fenced block's first line number, language and body."""
    for match in re.finditer(r"^```(\w*)[^\n]*\n(.*?)^```", text, re.S | re.M):
        yield text.count("\n", 0, match.start()) + 2, match.group(1), match.group(2)


def command_lines(body: str, first: int) -> Iterator[tuple[int, list[str]]]:
    """Each simple command of a shell block (continuations joined, comments dropped) with its line number."""
    lines = body.split("\n")
    k = 0
    while k < len(lines):
        start, text = k, lines[k]
        while text.endswith("\\") and k + 1 < len(lines):
            k += 1
            text = text[:-1] + " " + lines[k]
        k += 1
        lexer = shlex.shlex(text, posix=True, punctuation_chars=";&|")
        lexer.whitespace_split = True
        command: list[str] = []
        for token in [*lexer, ";"]:
            if token not in CONTROL:
                command.append(token)
            elif command:
                yield first + start, command
                command = []


def shown_commands(doc: Path) -> list[Shown]:
    """Every npp command the page's shell blocks run (``.venv/bin/npp-...`` or ``npp-...``)."""
    found = []
    for first, language, body in code_blocks(doc.read_text()):
        if language not in SHELL_BLOCKS:
            continue
        for line, tokens in command_lines(body, first):
            while tokens and re.fullmatch(r"[A-Z_]+=\S*", tokens[0]):  # VAR=value before the command
                tokens = tokens[1:]
            if tokens and re.fullmatch(r"(\.venv/bin/)?npp-[a-z-]+", tokens[0]):
                argv = tuple(PLACEHOLDERS.get(token, token) for token in tokens[1:])
                found.append(Shown(doc, line, tokens[0].rpartition("/")[2], argv))
    return found


SHOWN = [shown for doc in DOCS for shown in shown_commands(doc)]
NODES = {name for name, entry in console_scripts().items() if entry.startswith(NODE_PACKAGE)}


def ids(shown: Shown) -> str:
    return f"{shown.doc.name}:{shown.line}:{shown.command}"


# ----------------------------------------------------------------------------- parsing a command line
class _Parsed(BaseException):  # not an Exception: no command's own error handling catches it
    def __init__(self, namespace: argparse.Namespace) -> None:
        super().__init__()
        self.namespace = namespace


def parse(command: str, argv: tuple[str, ...] | list[str], monkeypatch: pytest.MonkeyPatch) -> argparse.Namespace:
    """The command's arguments as its own ``main`` parses them; nothing after the parsing runs."""
    module, _, function = console_scripts()[command].partition(":")
    main = getattr(importlib.import_module(module), function)
    known = argparse.ArgumentParser.parse_known_args

    def parse_args(self: argparse.ArgumentParser, args: Any = None, namespace: Any = None) -> None:
        namespace, extras = known(self, args, namespace)
        if extras:
            self.error(f"unrecognized arguments: {' '.join(extras)}")
        raise _Parsed(namespace)

    def parse_known_args(self: argparse.ArgumentParser, args: Any = None, namespace: Any = None) -> None:
        raise _Parsed(known(self, args, namespace)[0])

    with monkeypatch.context() as patch:
        patch.setattr(argparse.ArgumentParser, "parse_args", parse_args)
        patch.setattr(argparse.ArgumentParser, "parse_known_args", parse_known_args)
        try:
            main(list(argv))
        except _Parsed as parsed:
            return parsed.namespace
    raise AssertionError(f"{command} returned without parsing its arguments")


def test_the_pages_show_commands_of_every_kind() -> None:
    """The reader of the pages finds what these tests check: a change in how pages show commands is seen here."""
    commands = {shown.command for shown in SHOWN}
    assert {"npp-experiment", "npp-learn", "npp-run", "npp-sim", "npp-supervisor", "npp-trial"} <= commands
    assert any(shown.doc.name == "README.md" for shown in SHOWN)
    assert all(shown.command in console_scripts() for shown in SHOWN), [str(s) for s in SHOWN]


@pytest.mark.parametrize("shown", [s for s in SHOWN if s.command not in NODES], ids=ids)
def test_a_shown_command_parses(
    shown: Shown, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(REPO)  # paths in the pages are relative to the repository
    try:
        parse(shown.command, shown.argv, monkeypatch)
    except SystemExit:
        pytest.fail(f"{shown}\n{capsys.readouterr().err.strip()}")


# ----------------------------------------------------------------------------- nodes: -p name:=value
def parameters(shown: Shown) -> tuple[list[str], list[tuple[str, str]]]:
    """A node's own arguments (before --ros-args) and its ``-p name:=value`` pairs, with those of a
    ``--params-file`` the page shows (a yaml block whose first line is ``# FILE``), in the node's section."""
    argv = shown.argv
    own = list(argv[: argv.index("--ros-args")]) if "--ros-args" in argv else list(argv)
    ros = list(argv[len(own) + 1 :])
    pairs = []
    while ros:
        flag = ros.pop(0)
        assert flag in ("-p", "--param", "--params-file") and ros, f"{flag!r}: a node is shown -p or --params-file"
        if flag == "--params-file":
            section = shown_yaml(shown.doc, ros.pop(0)).get(shown.command.replace("-", "_"), {})
            pairs += [(name, yaml.safe_dump(value).strip().removesuffix("...").strip())
                      for name, value in section.get("ros__parameters", {}).items()]  # fmt: skip
            continue
        name, sep, value = ros.pop(0).partition(":=")
        assert sep, f"-p {name}: not name:=value"
        pairs.append((name, value))
    return own, pairs


def shown_yaml(doc: Path, name: str) -> dict[str, Any]:
    """The parameters file a page shows as a yaml block that starts with the line ``# NAME``."""
    for block in re.findall(r"```yaml\n(.*?)```", doc.read_text(), re.S):
        if block.splitlines()[0].strip() == f"# {name}":
            return yaml.safe_load(block)
    raise AssertionError(f"{doc.name} shows --params-file {name} but no yaml block starting '# {name}'")


def allowed(param: Any, text: str) -> bool:
    """Whether the node would take ``text`` (read as YAML, as rcl reads -p values) for ``param``."""
    value = yaml.safe_load(text)
    if isinstance(param.default, bool):
        return isinstance(value, bool)
    if isinstance(param.default, (int, float)):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return False
        if isinstance(param.default, int) and not isinstance(value, int):
            return False
        return (param.low is None or value >= param.low) and (param.high is None or value <= param.high)
    if param.choices and isinstance(value, str):
        return value in param.choices
    return isinstance(value, (str, int, float)) and not isinstance(value, bool)  # a number for text-or-number


@pytest.mark.parametrize("shown", [s for s in SHOWN if s.command in NODES], ids=ids)
def test_a_shown_node_gets_only_its_own_parameters(shown: Shown) -> None:
    module = importlib.import_module(console_scripts()[shown.command].partition(":")[0])
    table = {param.name: param for param in getattr(module, "PARAMETERS", ())}
    own, pairs = parameters(shown)
    assert not own, f"{shown}: a node takes no arguments before --ros-args"
    for name, value in pairs:
        assert name in table, f"{shown}: {shown.command} has no parameter {name!r}; it has {', '.join(table)}"
        assert allowed(table[name], value), f"{shown}: {name}:={value}, but {name} must be {table[name].allowed()}"


# ----------------------------------------------------------------------------- paths
def prose_paragraphs() -> list[str]:
    """The pages' text outside code blocks, paragraph by paragraph."""
    pages = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
    text = "\n\n".join(re.sub(r"^```.*?^```", "", page.read_text(), flags=re.S | re.M) for page in pages)
    return [" ".join(paragraph.split()) for paragraph in re.split(r"\n\s*\n", text)]


def made_by_a_command_in_prose(path: str) -> bool:
    """A paragraph names the path (a folder, with or without its slash) and a command that makes it."""
    pattern = re.compile(rf"`{re.escape(path.rstrip('/'))}/?`")
    return any(pattern.search(p) and re.search(r"`(make \w+|npp-[a-z-]+)[ `]", p) for p in prose_paragraphs())


def repository_paths(shown: Shown) -> Iterator[tuple[str, bool]]:
    """Each argument that is a path in the repository (or under runs/), and whether the command writes it."""
    top = {entry.name for entry in REPO.iterdir()} | {"runs"}
    outputs = OUTPUT_PARAMETERS.get(shown.command, ())
    previous = ""
    for token in shown.argv:
        name, sep, value = token.partition(":=")
        path, written = (value, name in outputs) if sep else (token, previous in OUTPUT_OPTIONS)
        previous = token
        if "/" in path and "://" not in path and not path.startswith("/") and path.split("/")[0] in top:
            yield path, written


@pytest.mark.parametrize("shown", SHOWN, ids=ids)
def test_every_repository_path_a_shown_command_names_exists(shown: Shown) -> None:
    for path, written in repository_paths(shown):
        if path.split("/")[0] == "runs":
            assert written or made_by_a_command_in_prose(path), (
                f"{shown}: {path} is not in the repository (runs/ is made by running), and no page says which "
                "command makes it"
            )
        else:
            assert (REPO / path).exists(), f"{shown}: {path} does not exist"


def test_the_path_checks_catch_what_they_look_for() -> None:
    doc = REPO / "README.md"
    missing = Shown(doc, 1, "npp-learn", ("--task", "examples/no_such_arm/task.toml", "--run-dir", "runs/x"))
    assert list(repository_paths(missing)) == [("examples/no_such_arm/task.toml", False), ("runs/x", True)]
    read = Shown(doc, 1, "npp-deploy", ("--ros-args", "-p", "run_dir:=runs/nowhere-made"))
    assert list(repository_paths(read)) == [("runs/nowhere-made", False)]
    assert not made_by_a_command_in_prose("runs/nowhere-made")
    assert made_by_a_command_in_prose("runs/learn-lqr_2_1-seed0")  # tutorials/main-job.md: npp-learn writes it


# ----------------------------------------------------------------------------- experiments over results/
EXPERIMENTS = [s for s in SHOWN if s.command == "npp-experiment"]
DEFAULT_OUT = "results/experiment"
# Shown experiments that no longer plan their folder's recorded arms, as the pages stand: npp-experiment acts
# with the feedback policy by default since it gained --policies, and every recorded run acted open loop (its
# arms' names carry no policy). Each needs --policies open-loop; remove its entry when its page has it (the
# check is strict, so a fixed page fails here until then).
STALE_EXPERIMENTS: set[tuple[str, str]] = set()  # (page, results folder) shown without the recorded policy


def out_folder(shown: Shown) -> str:
    argv = list(shown.argv)
    return argv[argv.index("--out") + 1] if "--out" in argv else DEFAULT_OUT


def experiment_case(shown: Shown) -> Any:
    if (str(shown.doc.relative_to(REPO)), out_folder(shown)) not in STALE_EXPERIMENTS:
        return shown
    reason = "shows no --policies open-loop: it would plan feedback-policy arms beside the recorded open-loop ones"
    return pytest.param(shown, marks=pytest.mark.xfail(strict=True, reason=reason))


@pytest.mark.parametrize("shown", [experiment_case(s) for s in EXPERIMENTS], ids=ids)
def test_a_shown_experiment_plans_the_arms_its_results_folder_holds(
    shown: Shown, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Rerun as shown, the command would resume the recorded runs: the same arms (each arm's figures are named
    after it), seeds and settings as the folder's last recorded command, read by today's parser."""
    from npp_ros.cli.experiment import plan

    monkeypatch.chdir(REPO)
    args = parse(shown.command, shown.argv, monkeypatch)
    record = REPO / args.out / "experiment.json"
    if args.out.is_absolute() or not record.exists():
        pytest.skip(f"{args.out} holds no recorded experiment")
    last = shlex.split(json.loads(record.read_text())["invocations"][-1]["command"])
    recorded = parse(last[0], last[1:], monkeypatch)
    settings, arms = plan(args)
    figures = sorted(path.name for path in (REPO / args.out).glob("fig4-*.png"))
    assert sorted(f"fig4-{arm.name}.png" for arm in arms) == figures, (
        f"{shown}: plans {[arm.name for arm in arms]}; {args.out} holds the arms of {figures}"
    )
    assert (settings, args.seeds) == (plan(recorded)[0], recorded.seeds), f"{shown}: not {' '.join(last)}"


def test_the_parse_check_catches_an_unknown_flag_and_the_node_check_an_unknown_parameter(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    with pytest.raises(SystemExit):
        parse("npp-learn", ["--task", "lqr_2_1", "--no-such-flag"], monkeypatch)
    assert parse("npp-monitor", ["--topics", "gap"], monkeypatch).topics  # a command that parses inside main
    with pytest.raises(AssertionError, match="has no parameter 'horizn'"):
        test_a_shown_node_gets_only_its_own_parameters(
            Shown(REPO / "README.md", 1, "npp-sim", ("--ros-args", "-p", "horizn:=50"))
        )
    with pytest.raises(AssertionError, match="horizon must be an integer"):
        test_a_shown_node_gets_only_its_own_parameters(
            Shown(REPO / "README.md", 1, "npp-sim", ("--ros-args", "-p", "horizon:=fifty"))
        )
