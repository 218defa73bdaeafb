"""The run file: round trip, resume, damage, versions, and kills during writes."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from npp_ros.policy.dataset import Trajectory
from npp_ros.run.records import EpisodeRow, RunFileError, RunMetadata
from npp_ros.run.store import RunStore

META = RunMetadata(
    task="lqr_2_1", seed=0, state_dim=4, action_dim=1, lipschitz=263.0, lipschitz_source="lqr-analytic",
    lipschitz_detail="test", gamma=1.0, horizon=1000, epsilon=50.0, condition="i", p=0.9, delta=0.1,
    certify="rollout", rule="sequential",
)  # fmt: skip


def trajectory(seed: int, steps: int = 50) -> Trajectory:
    rng = np.random.default_rng(seed)
    return Trajectory(rng.normal(size=(steps, 4)), rng.normal(size=(steps, 1)), rng.normal(size=steps))


def row(episode: int, traj: int | None, size: int) -> EpisodeRow:
    return EpisodeRow(
        episode=episode, initial_state=(1.0, 0.5, 0.0, 0.0), v_lb=1.0, v_ub=2.0, gap=float("inf") if traj == 0 else 1.0,
        oracle_called=traj is not None, trajectory=traj, dataset_size=size, oracle_calls=0, quiet_episodes=0,
        window=0, required=24, certified=False, expert_value=3.0,
    )  # fmt: skip


def fill(store: RunStore, count: int) -> list[Trajectory]:
    trajs = [trajectory(k) for k in range(count)]
    for k, traj in enumerate(trajs):
        store.record_episode(row(2 * k, k, 50 * (k + 1)), traj)
        store.record_episode(row(2 * k + 1, None, 50 * (k + 1)))
    return trajs


def test_round_trip_is_exact(tmp_path: Path) -> None:
    with RunStore.create(tmp_path / "run.sqlite", META) as store:
        trajs = fill(store, 3)
        store.set_policy_return(1, 812.5)
    with RunStore.open(tmp_path / "run.sqlite") as store:
        assert store.metadata == META
        data = store.load_dataset()
        episodes = store.episodes()
    assert data.num_trajectories == 3 and len(data) == 150
    for k, traj in enumerate(trajs):
        got = data.trajectory(k)
        for name in ("states", "actions", "values"):
            np.testing.assert_array_equal(getattr(got, name), getattr(traj, name))
    assert [e.episode for e in episodes] == list(range(6))
    assert episodes[0].gap == float("inf") and episodes[0].trajectory == 0
    assert episodes[1].policy_return == 812.5 and episodes[1].oracle_called is False


def test_file_is_plain_sqlite_with_named_columns(tmp_path: Path) -> None:
    with RunStore.create(tmp_path / "run.sqlite", META) as store:
        traj = fill(store, 1)[0]
    conn = sqlite3.connect(tmp_path / "run.sqlite")
    rows = conn.execute("SELECT s_0, s_3, a_0, q FROM points WHERE trajectory = 0 ORDER BY step").fetchall()
    np.testing.assert_array_equal(np.array(rows), np.column_stack([traj.states[:, [0, 3]], traj.actions, traj.values]))
    meta = dict(conn.execute("SELECT key, value FROM meta").fetchall())
    assert meta["format"] == "npp_ros.run" and meta["format_version"] == "3" and meta["task"] == '"lqr_2_1"'


def test_resume_requires_the_same_run(tmp_path: Path) -> None:
    path = tmp_path / "run.sqlite"
    RunStore.create(path, META).close()
    with RunStore.open_or_create(path, META) as store:
        assert store.num_trajectories() == 0
    with pytest.raises(RunFileError, match=r"lipschitz: file has 263.0, this run asks for 50.0"):
        RunStore.open_or_create(path, RunMetadata(**(vars(META) | {"lipschitz": 50.0})))
    with pytest.raises(RunFileError, match="already exists"):
        RunStore.create(path, META)


def test_resume_requires_the_same_plant_and_older_files_record_theirs(tmp_path: Path) -> None:
    """The run file names its plant's model fingerprint; data of another plant never join it."""
    path = tmp_path / "run.sqlite"
    mine = RunMetadata(**(vars(META) | {"plant_fingerprint": "a" * 64}))
    RunStore.create(path, mine).close()
    with pytest.raises(
        RunFileError, match=r"belongs to another run.*\n  plant_fingerprint: file has 'a{64}', this run asks"
    ):
        RunStore.open_or_create(path, RunMetadata(**(vars(META) | {"plant_fingerprint": "b" * 64})))
    older = tmp_path / "older.sqlite"  # made before npp_ros recorded the plant
    RunStore.create(older, META).close()
    with RunStore.open_or_create(older, mine) as store:
        assert store.metadata.plant_fingerprint == "a" * 64
    assert RunStore.open(older).metadata.plant_fingerprint == "a" * 64  # recorded in the file
    with pytest.raises(RunFileError, match=r"plant_fingerprint: file has 'a{64}'"):
        RunStore.open_or_create(older, RunMetadata(**(vars(META) | {"plant_fingerprint": "b" * 64})))


def test_wrong_version_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "run.sqlite"
    RunStore.create(path, META).close()
    conn = sqlite3.connect(path)
    conn.execute("UPDATE meta SET value = '1' WHERE key = 'format_version'")
    conn.commit()
    conn.close()
    with pytest.raises(RunFileError, match="format version 1, this npp_ros reads versions 2, 3"):
        RunStore.open(path)


def test_missing_and_foreign_files_are_refused(tmp_path: Path) -> None:
    with pytest.raises(RunFileError, match="does not exist"):
        RunStore.open(tmp_path / "nope.sqlite")
    junk = tmp_path / "junk.sqlite"
    junk.write_bytes(b"this is not a database at all" * 100)
    with pytest.raises(RunFileError, match="not a readable npp_ros run file"):
        RunStore.open(junk)


@pytest.mark.parametrize("keep", [0.3, 0.6, 0.9])
def test_truncated_file_is_refused_never_partially_loaded(tmp_path: Path, keep: float) -> None:
    path = tmp_path / "run.sqlite"
    with RunStore.create(path, META) as store:
        fill(store, 20)
    size = path.stat().st_size
    with path.open("r+b") as fh:
        fh.truncate(int(size * keep))
    with pytest.raises(RunFileError, match=r"damaged|not a readable|cannot read"):
        with RunStore.open(path) as store:
            store.load_dataset()


def test_tampered_trajectory_fails_its_checksum(tmp_path: Path) -> None:
    path = tmp_path / "run.sqlite"
    with RunStore.create(path, META) as store:
        fill(store, 3)
    conn = sqlite3.connect(path)
    conn.execute("UPDATE points SET q = q + 1e-9 WHERE trajectory = 1 AND step = 7")
    conn.commit()
    conn.close()
    with RunStore.open(path) as store, pytest.raises(RunFileError, match="trajectory 1 fails its SHA-256"):
        store.load_dataset()


def test_invalid_trajectory_is_refused_before_writing(tmp_path: Path) -> None:
    with RunStore.create(tmp_path / "run.sqlite", META) as store:
        fill(store, 1)
        bad = Trajectory(np.zeros((5, 3)), np.zeros((5, 1)), np.zeros(5))
        with pytest.raises(ValueError, match="states has 3 columns"):
            store.record_episode(row(2, 1, 55), bad)
        assert store.num_trajectories() == 1 and len(store.episodes()) == 2


WRITER = textwrap.dedent(
    """
    import sys, numpy as np
    from npp_ros.run.records import EpisodeRow
    from npp_ros.run.store import RunStore
    from npp_ros.policy.dataset import Trajectory
    store = RunStore.open(sys.argv[1])
    k = store.num_trajectories()
    print("ready", flush=True)
    while True:
        rng = np.random.default_rng(k)
        t = Trajectory(rng.normal(size=(2000, 4)), rng.normal(size=(2000, 1)), rng.normal(size=2000))
        r = EpisodeRow(k, (0.0,) * 4, 0.0, 1.0, 1.0, True, k, 2000 * (k + 1), k + 1, 0, 0, 24, False)
        store.record_episode(r, t)
        print(k, flush=True)
        k += 1
    """
)


def test_sigkill_during_writes_never_damages_stored_trajectories(tmp_path: Path) -> None:
    path = tmp_path / "run.sqlite"
    RunStore.create(path, META).close()
    acknowledged = -1
    rng = np.random.default_rng(0)
    for trial in range(6):
        proc = subprocess.Popen([sys.executable, "-c", WRITER, str(path)], stdout=subprocess.PIPE, text=True)
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(0.05 + 0.3 * rng.random())
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        acks = [int(line) for line in proc.stdout.read().split()]
        acknowledged = max([acknowledged, *acks])
        with RunStore.open(path) as store:
            data = store.load_dataset()  # verifies every checksum
            assert data.num_trajectories >= acknowledged + 1, f"trial {trial}: lost acknowledged trajectories"
            assert len(store.episodes()) == data.num_trajectories
            for k in range(data.num_trajectories):
                expected = np.random.default_rng(k).normal(size=(2000, 4))
                np.testing.assert_array_equal(data.trajectory(k).states, expected)
    assert acknowledged >= 1
