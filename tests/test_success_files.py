"""Success in files: run files from before it was recorded open with None and gain its columns at their first write;
a task file's [success] table parses, judges stored states, and a bad key is refused naming it."""

from __future__ import annotations

import dataclasses
import shutil
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from npp_ros.run.records import SUCCESS_COLUMNS
from npp_ros.run.seal import SEAL_TABLE
from npp_ros.run.store import FORMAT_VERSION, RunStore
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.task_file.loader import TaskFileError
from tests.test_storage import META, row, trajectory
from tests.test_storage_gains import make_version_2

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "two_link_arm"


# ----------------------------------------------------------------------------- run files
def without_success(path: Path, version_2: bool = False) -> None:
    """What npp_ros wrote before success was recorded: no success columns, no seal (and, for version 2, no gains
    either)."""
    conn = sqlite3.connect(path)
    conn.execute(f"DROP TABLE {SEAL_TABLE}")
    for column in SUCCESS_COLUMNS:
        conn.execute(f"ALTER TABLE episodes DROP COLUMN {column}")
    conn.commit()
    conn.close()
    if version_2:
        make_version_2(path)


def columns(path: Path) -> set[str]:
    return {r[1] for r in sqlite3.connect(path).execute("PRAGMA table_info(episodes)")}


@pytest.mark.parametrize("version_2", [False, True], ids=["version 3", "version 2"])
def test_an_old_run_file_opens_with_none_and_records_success_from_its_first_write(
    tmp_path: Path, version_2: bool
) -> None:
    path = tmp_path / "run.sqlite"
    with RunStore.create(path, META) as store:
        store.record_episode(dataclasses.replace(row(0, 0, 50), expert_success=True), trajectory(0))
    without_success(path, version_2)
    with RunStore.open(path) as store:
        (old,) = store.episodes()
        assert (old.expert_success, old.policy_success) == (None, None) and old.trajectory == 0
    assert not set(SUCCESS_COLUMNS) & columns(path)  # reading never writes
    with RunStore.open_or_create(path, META) as store:  # a resumed run: the writer adds the columns
        store.record_episode(dataclasses.replace(row(1, None, 50), expert_success=None, policy_success=False))
        store.set_policy_return(0, 12.5, True)
    with RunStore.open(path) as store:
        first, second = store.episodes()
    assert (first.expert_success, first.policy_success, first.policy_return) == (None, True, 12.5)
    assert (second.expert_success, second.policy_success) == (None, False)
    assert set(SUCCESS_COLUMNS) <= columns(path)
    version = sqlite3.connect(path).execute("SELECT value FROM meta WHERE key = 'format_version'").fetchone()
    assert version == (str(FORMAT_VERSION),) == ("3",)


def test_success_round_trips_as_true_false_and_none(tmp_path: Path) -> None:
    path = tmp_path / "run.sqlite"
    marks = [(True, False), (False, None), (None, True)]
    with RunStore.create(path, META) as store:
        for k, (expert, policy) in enumerate(marks):
            store.record_episode(dataclasses.replace(row(k, None, 0), expert_success=expert, policy_success=policy))
    with RunStore.open(path) as store:
        assert [(r.expert_success, r.policy_success) for r in store.episodes()] == marks
    stored = sqlite3.connect(path).execute("SELECT expert_success, policy_success FROM episodes").fetchall()
    assert stored == [(1, 0), (0, None), (None, 1)]


# ----------------------------------------------------------------------------- task files
@pytest.fixture
def task_dir(tmp_path: Path) -> Path:
    for name in ("arm.xml", "task.toml"):
        shutil.copy(EXAMPLE / name, tmp_path / name)
    return tmp_path


def with_success(task_dir: Path, table: str) -> str:
    """The example's task file with this [success] table."""
    path = task_dir / "task.toml"
    path.write_text((EXAMPLE / "task.toml").read_text() + "\n[success]\n" + table + "\n")
    return str(path)


def arm_states(shoulder: float, elbow: float, steps: int = 100) -> np.ndarray:
    return np.tile([shoulder, elbow, 0.0, 0.0], (steps, 1))


def test_a_file_without_success_states_none(task_dir: Path) -> None:
    assert get_task(str(task_dir / "task.toml")).success is None


def test_a_joint_band_over_the_last_seconds(task_dir: Path) -> None:
    task = get_task(with_success(task_dir, 'joint = "elbow"\nwithin = [-0.1, 0.1]\nlast_seconds = 0.5'))
    criterion = task.success
    assert criterion is not None and criterion.steps == 50 and criterion.seconds == 0.5  # 0.01 s steps
    assert criterion.describe() == "joint elbow within [-0.1, 0.1] over the last 50 steps (0.5 s)"
    assert criterion.met(arm_states(2.0, 0.05)) and not criterion.met(arm_states(2.0, 0.2))
    states = arm_states(0.0, 0.0)
    states[-51, 1] = 1.0  # before the last half second: not looked at
    assert criterion.met(states)


def test_a_site_position_and_a_distance_come_from_the_models_kinematics(task_dir: Path) -> None:
    distance = get_task(with_success(task_dir, 'distance = ["fingertip", "target"]\nwithin = [0.0, 0.02]'))
    assert distance.success is not None and distance.success.steps == 100  # the default second
    plant = distance.make_plant(0)
    far = arm_states(0.0, 0.0, 3)
    plant.reset(far[0])
    gap = np.linalg.norm(plant.physics.data.site("fingertip").xpos - plant.physics.data.site("target").xpos)
    band = distance.success.holds
    assert band.values(far) == pytest.approx([gap] * 3, rel=1e-12) and not distance.success.met(far)
    table = 'site = "fingertip"\naxis = "x"\nwithin = [-10.0, 10.0]\ndescription = "anywhere"'
    height = get_task(with_success(task_dir, table))
    assert height.success is not None and height.success.description == "anywhere"
    assert height.success.met(far) and height.success.met(arm_states(3.0, -2.0))


BAD = [
    ('joint = "elbow"\nwithin = [0, 1]\nlast_second = 1', "success.last_second: unknown key"),
    ('joint = "elbow"', "success.within: missing"),
    ('joint = "elbow"\nwithin = [1, 0]', "success.within: is empty"),
    ('joint = "elbow"\nwithin = 0.5', "success.within: must be [low, high]"),
    ('joint = "wrist"\nwithin = [0, 1]', "success.joint: unknown joint 'wrist'"),
    ('joint = "elbow"\naxis = "z"\nwithin = [0, 1]', "success.axis: only a site has an axis"),
    ('site = "fingertip"\nwithin = [0, 1]', "success.axis: a site needs axis x, y or z"),
    ('site = "thumb"\naxis = "z"\nwithin = [0, 1]', "success.site: unknown site 'thumb'"),
    ('distance = ["fingertip"]\nwithin = [0, 1]', "success.distance: must name two sites"),
    ('joint = "elbow"\nsite = "fingertip"\nwithin = [0, 1]', "success: one quantity, got joint, site"),
    ("within = [0, 1]", "success: says nothing to check"),
    ('joint = "elbow"\nwithin = [0, 1]\nlast_seconds = -1', "success.last_seconds: must be > 0"),
    ('joint = "elbow"\nwithin = [0, 1]\ndescription = ""', "success.description: must be a non-empty string"),
]


@pytest.mark.parametrize(("table", "expected"), BAD, ids=[b[1].split(":")[0] + " " + b[1][-12:] for b in BAD])
def test_a_bad_success_table_is_refused_naming_the_key(task_dir: Path, table: str, expected: str) -> None:
    path = with_success(task_dir, table)
    with pytest.raises(TaskFileError) as caught:
        get_task(path)
    message = str(caught.value)
    assert expected in message and "\n" not in message and path in message


def test_success_that_is_not_a_table_is_refused(task_dir: Path) -> None:
    path = task_dir / "task.toml"
    path.write_text('success = "yes"\n' + path.read_text())
    with pytest.raises(TaskFileError, match="success: must be a table"):
        get_task(str(path))


def test_npp_bench_times_and_scores_any_task(task_dir: Path) -> None:
    """A closed-form expert and a task file's: seconds per request and the share that met the task's criterion."""
    import io

    from npp_ros.bench.measure import Progress, time_expert

    progress = Progress(4, stream=io.StringIO())
    lqr = get_task("lqr_2_1")
    (closed,) = time_expert("lqr_2_1", [lqr.initial_state(0, k) for k in range(2)], 1000, 0, progress)
    assert (closed["path"], closed["succeeded"], closed["success_fraction"]) == ("closed form", 2, 1.0)
    assert closed["success_rule"].startswith("every joint position within 0.15 of 0")
    never = 'joint = "elbow"\nwithin = [5.0, 6.0]'  # the elbow is stored wrapped to (-pi, pi]
    name = get_task(with_success(task_dir, never)).name
    starts = [get_task(name).initial_state(0, k) for k in range(2)]
    (arm,) = time_expert(name, starts, 20, 0, progress)
    assert arm["task"] == f"{task_dir.name}-task" and arm["requests"] == 2 and arm["seconds"]["max_s"] > 0
    assert (arm["succeeded"], arm["success_fraction"]) == (0, 0.0)
    assert [r["success"] for r in arm["detail"]] == [False, False]
