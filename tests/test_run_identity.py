"""A run's identity: every setting that decides its expert's answers or its checks is recorded, resolved, when the run
file is made, and a resume asking for another value of any of them is refused, naming the setting, the recorded value
and the asked one. A file from before the expert's settings were recorded resumes, saying which it never recorded, and
nothing is written that would claim them for its stored answers."""

from __future__ import annotations

import hashlib
import json
import shutil
import sqlite3
import warnings
from dataclasses import fields
from pathlib import Path
from typing import Any

import pytest

from npp_ros.cli.learn import main as learn
from npp_ros.run.held_out import answers_identity
from npp_ros.run.loop import NPPLoop, RunConfig
from npp_ros.run.records import EXPERT_SETTINGS, RunFileError, UnrecordedSettings
from npp_ros.run.request import RunRequest, resolve_run
from npp_ros.run.seal import SEAL_TABLE
from npp_ros.run.setup import build_loop
from npp_ros.run.store import RUN_FILE, RunStore

PENDULUM = {"task": "pendulum_swingup", "horizon": 50, "max_iterations": 2}  # the fastest iLQR run there is
# The detuned lqr expert (an expert kind and a control-cost scale), checked on its own return (any gamma has one).
DETUNED_LQR = {"task": "lqr_2_1", "horizon": 20, "certify": "oracle"}
DETUNED = {"kind": "detuned", "control_weight": 0.1}


def start(run_file: Path, settings: dict[str, Any], expert: dict[str, Any] | None = None) -> NPPLoop:
    """The loop of a run (made or resumed) as every door builds it: resolve_run, then build_loop."""
    run = resolve_run(RunRequest(**settings), run_file=run_file, **(expert or {}))
    return build_loop(run.config, run.expert, store_path=run_file)


def made(folder: Path, settings: dict[str, Any], expert: dict[str, Any] | None = None) -> Path:
    """A run file with one episode."""
    loop = start(folder / RUN_FILE, settings, expert)
    loop.run(1)
    assert loop.store is not None
    loop.store.close()
    return folder / RUN_FILE


def seal_digest(run_file: Path) -> str:
    """The file's seal over everything it holds, and a digest of its whole content (every table, the seal's among
    them, as SQL): what a refused resume must leave as it was. Not its bytes: SQLite may move committed pages from
    the write-ahead log into the file when any connection closes, which changes no content."""
    conn = sqlite3.connect(run_file)
    (run,) = conn.execute(f"SELECT sha256 FROM {SEAL_TABLE} WHERE part = 'run'").fetchone()
    content = hashlib.sha256("\n".join(conn.iterdump()).encode()).hexdigest()
    conn.close()
    return f"{run} {content}"


@pytest.fixture(scope="module")
def pendulum_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return made(tmp_path_factory.mktemp("pendulum"), PENDULUM)


@pytest.fixture(scope="module")
def lqr_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return made(tmp_path_factory.mktemp("lqr"), DETUNED_LQR, DETUNED)


def test_the_file_records_every_setting_resolved_the_task_default_as_its_value(pendulum_run: Path) -> None:
    assert set(EXPERT_SETTINGS) <= {f.name for f in fields(RunConfig)}
    with RunStore.open(pendulum_run) as store:
        recorded = {name: getattr(store.metadata, name) for name in (*EXPERT_SETTINGS, "gamma", "policy")}
        assert set(EXPERT_SETTINGS) <= vars(store.metadata).keys()
    # No --time-budget, --expert-stop or --values was given: the expert's resolved values, never None.
    assert recorded == {
        "expert_kind": "ilqr", "time_budget": 60.0, "max_iterations": 2, "expert_stop": "iterations",
        "values": "window", "control_weight": None, "gamma": 1.0, "policy": "feedback",
    }  # fmt: skip


# (run, a setting asked otherwise, the line the refusal must hold)
REFUSALS = [
    ("pendulum", {"time_budget": 30.0}, "time_budget: file has 60.0, this run asks for 30.0"),
    ("pendulum", {"max_iterations": 9}, "max_iterations: file has 2, this run asks for 9"),
    ("pendulum", {"expert_stop": "time", "time_budget": 60.0},
     "expert_stop: file has 'iterations', this run asks for 'time'"),
    ("pendulum", {"values": "return-to-go"}, "values: file has 'window', this run asks for 'return-to-go'"),
    ("pendulum", {"policy": "open-loop"}, "policy: file has 'feedback', this run asks for 'open-loop'"),
    ("pendulum", {"uncertainty": 1.0}, "uncertainty: file has '', this run asks for '{"),
    ("lqr", {"kind": "optimal"}, "expert_kind: file has 'detuned', this run asks for 'optimal'"),
    ("lqr", {"control_weight": 0.5}, "control_weight: file has 0.1, this run asks for 0.5"),
    ("lqr", {"gamma": 0.99}, "gamma: file has 1.0, this run asks for 0.99"),
]  # fmt: skip


@pytest.mark.parametrize(("which", "asked", "line"), REFUSALS, ids=[line.split(":")[0] for *_, line in REFUSALS])
def test_a_resume_asking_another_value_is_refused_naming_it_and_the_file_is_untouched(
    which: str, asked: dict[str, Any], line: str, request: pytest.FixtureRequest
) -> None:
    run_file: Path = request.getfixturevalue(f"{which}_run")
    settings, expert = (PENDULUM, None) if which == "pendulum" else (DETUNED_LQR, DETUNED)
    expert = {**(expert or {}), **{k: v for k, v in asked.items() if k in ("kind", "control_weight")}}
    settings = {**settings, **{k: v for k, v in asked.items() if k not in ("kind", "control_weight")}}
    before = seal_digest(run_file)
    with pytest.raises(RunFileError, match="belongs to another run") as refused:
        start(run_file, settings, expert)
    assert any(row.startswith(f"  {line}") for row in str(refused.value).splitlines()[1:]), str(refused.value)
    assert seal_digest(run_file) == before
    # The loop's own resume check says the same, on a store opened for reading (no writer's check before it).
    run = resolve_run(RunRequest(**settings), run_file=run_file, **expert)
    with RunStore.open(run_file) as store, pytest.raises(RunFileError, match="belongs to another run") as refused:
        build_loop(run.config, run.expert, store=store)
    assert any(row.startswith(f"  {line}") for row in str(refused.value).splitlines()[1:]), str(refused.value)
    assert seal_digest(run_file) == before


def test_the_same_settings_resume_whether_given_or_left_to_the_task(tmp_path: Path, pendulum_run: Path) -> None:
    run_file = tmp_path / RUN_FILE
    shutil.copy(pendulum_run, run_file)
    explicit = {**PENDULUM, "time_budget": 60.0, "expert_stop": "iterations", "values": "window"}
    with warnings.catch_warnings():
        warnings.simplefilter("error", UnrecordedSettings)  # a file that records them gives no notice
        loop = start(run_file, explicit)
    assert loop.next_episode == 1
    loop.run(2)
    assert loop.store is not None
    loop.store.close()
    # The held-out answers are keyed on the identity the file records (where L came from aside), not a list of its own.
    with RunStore.open(run_file) as store:
        recorded = {k: v for k, v in vars(store.metadata).items() if k != "lipschitz_detail"}
    assert json.loads(answers_identity(loop.config)) == recorded


def make_unrecorded(run_file: Path) -> None:
    """Turn a file into one made before run files recorded the expert's settings: no such keys, and no seal."""
    conn = sqlite3.connect(run_file)
    conn.execute(f"DROP TABLE IF EXISTS {SEAL_TABLE}")
    conn.executemany("DELETE FROM meta WHERE key = ?", [(name,) for name in EXPERT_SETTINGS])
    conn.commit()
    conn.close()


def test_an_older_file_resumes_saying_what_it_never_recorded_and_records_nothing_of_it(
    tmp_path: Path, pendulum_run: Path
) -> None:
    run_file = tmp_path / RUN_FILE
    shutil.copy(pendulum_run, run_file)
    make_unrecorded(run_file)
    for episodes, asked in ((2, PENDULUM), (3, {**PENDULUM, "max_iterations": 3})):  # unknown: nothing to refuse
        with pytest.warns(UnrecordedSettings) as notices:
            loop = start(run_file, asked)
        (notice,) = [str(n.message) for n in notices]
        assert f"{run_file} was made before run files recorded expert_kind, time_budget, max_iterations, " in notice
        assert f"this run asks for expert_kind 'ilqr', time_budget 60.0, max_iterations {asked['max_iterations']}," in (
            notice
        )
        loop.run(episodes)
        assert loop.store is not None
        loop.store.close()
        with RunStore.open(run_file) as store:
            assert not set(EXPERT_SETTINGS) & vars(store.metadata).keys()  # still unknown, at every resume
            assert store.metadata.max_iterations is None and len(store.episodes()) == episodes


def test_npp_learn_refuses_other_expert_settings_on_a_run_folder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    base = ["--task", "pendulum_swingup", "--horizon", "50", "--max-episodes", "1", "--evaluate", "0"]
    base += ["--run-dir", str(tmp_path)]
    assert learn([*base, "--max-iterations", "2"]) == 1  # one episode, not certified
    capsys.readouterr()
    before = seal_digest(tmp_path / RUN_FILE)
    assert learn([*base, "--max-iterations", "9", "--time-budget", "30"]) == 2
    err = capsys.readouterr().err
    assert "belongs to another run and was left untouched" in err and "resuming" not in err
    assert "  time_budget: file has 60.0, this run asks for 30.0" in err.splitlines()
    assert "  max_iterations: file has 2, this run asks for 9" in err.splitlines()
    assert learn([*base, "--max-iterations", "2", "--values", "return-to-go"]) == 2
    err = capsys.readouterr().err
    assert err.splitlines()[1:] == ["  values: file has 'window', this run asks for 'return-to-go'"]
    assert seal_digest(tmp_path / RUN_FILE) == before
    # A file from before the settings were recorded: resumed, with the note, at every resume.
    make_unrecorded(tmp_path / RUN_FILE)
    assert learn([*base, "--max-iterations", "2"]) == 1
    err = capsys.readouterr().err
    assert "resuming" in err and "npp-learn: note: " in err and "was made before run files recorded" in err
