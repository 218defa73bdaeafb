"""Feedback gains in the run file: stored exactly with their trajectory, covered by its SHA-256, and files made
before gains were stored still open (without gains, saying so) and upgrade in place at their first write."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np
import pytest

from npp_ros.policy.dataset import Trajectory
from npp_ros.run.records import RunFileError
from npp_ros.run.seal import SEAL_TABLE
from npp_ros.run.store import FORMAT_VERSION, RunStore, gain_columns
from tests.test_storage import META, row, trajectory


def with_gains(seed: int, steps: int = 50) -> Trajectory:
    plain = trajectory(seed, steps)
    gains = np.random.default_rng(100 + seed).normal(size=(steps, 1, 4))
    return Trajectory(plain.states, plain.actions, plain.values, gains=gains)


def test_gains_round_trip_exactly_beside_trajectories_without_them(tmp_path: Path) -> None:
    trajs = [with_gains(0), trajectory(1), with_gains(2)]
    with RunStore.create(tmp_path / "run.sqlite", META) as store:
        for k, traj in enumerate(trajs):
            store.record_episode(row(k, k, 50 * (k + 1)), traj)
    with RunStore.open(tmp_path / "run.sqlite") as store:
        data = store.load_dataset()
        assert store.gains_note == ""
    assert data.trajectories_with_gains == 2
    np.testing.assert_array_equal(data.trajectory(0).gains, trajs[0].gains)
    assert data.trajectory(1).gains is None
    np.testing.assert_array_equal(data.gains[50:100], 0.0)
    np.testing.assert_array_equal(data.trajectory(2).gains, trajs[2].gains)
    # Plain columns, row-major: k_0_3 is the gain from state entry 3 to actuator 0.
    conn = sqlite3.connect(tmp_path / "run.sqlite")
    got = conn.execute("SELECT k_0_3 FROM points WHERE trajectory = 2 ORDER BY step").fetchall()
    np.testing.assert_array_equal(np.ravel(got), trajs[2].gains[:, 0, 3])


def test_an_altered_gain_is_damage(tmp_path: Path) -> None:
    with RunStore.create(tmp_path / "run.sqlite", META) as store:
        store.record_episode(row(0, 0, 50), with_gains(0))
    conn = sqlite3.connect(tmp_path / "run.sqlite")
    conn.execute("UPDATE points SET k_0_1 = k_0_1 + 1e-9 WHERE trajectory = 0 AND step = 7")
    conn.commit()
    conn.close()
    with RunStore.open(tmp_path / "run.sqlite") as store, pytest.raises(RunFileError, match="SHA-256"):
        store.load_dataset()


def make_version_2(path: Path) -> None:
    """Turn a file into what npp_ros wrote before gains: no gain columns, no feedback flag, version 2, no seal."""
    conn = sqlite3.connect(path)
    conn.execute(f"DROP TABLE IF EXISTS {SEAL_TABLE}")
    for column in gain_columns(META.state_dim, META.action_dim):
        conn.execute(f"ALTER TABLE points DROP COLUMN {column}")
    conn.execute("ALTER TABLE trajectories DROP COLUMN feedback")
    conn.execute("ALTER TABLE episodes DROP COLUMN explored")
    conn.execute("UPDATE meta SET value = '2' WHERE key = 'format_version'")
    conn.commit()
    conn.close()


def test_a_file_from_before_gains_opens_without_them_and_upgrades_at_its_first_write(tmp_path: Path) -> None:
    path = tmp_path / "run.sqlite"
    first = trajectory(0)
    with RunStore.create(path, META) as store:
        store.record_episode(row(0, 0, 50), first)
    make_version_2(path)
    with RunStore.open(path) as store:
        data = store.load_dataset()
        assert [row.explored for row in store.episodes()] == [0]
        assert "before run files stored feedback gains" in store.gains_note
    assert data.trajectories_with_gains == 0
    np.testing.assert_array_equal(data.states, first.states)
    assert sqlite3.connect(path).execute("SELECT value FROM meta WHERE key = 'format_version'").fetchone() == ("2",)

    second = with_gains(1)
    with RunStore.open_or_create(path, META) as store:  # a resumed run: the writer upgrades the file
        assert store.gains_note == ""
        store.record_episode(row(1, 1, 100), second)
    with RunStore.open(path) as store:
        data = store.load_dataset()
    assert data.trajectory(0).gains is None
    np.testing.assert_array_equal(data.trajectory(1).gains, second.gains)
    version = sqlite3.connect(path).execute("SELECT value FROM meta WHERE key = 'format_version'").fetchone()
    assert version == (str(FORMAT_VERSION),)
