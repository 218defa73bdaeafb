"""Crash-safe persistence of a run: expert trajectories, the episode log and the metadata.

The file is SQLite (format "npp_ros.run", version 1), readable by the sqlite3 shell, pandas,
R or any language; no pickle. Tables (see README, "Run file format"):

- ``meta(key, value)``: format, format_version, task, seed, dims, L and its source, gamma,
  horizon, epsilon, condition, p, delta, created, and the certificate (JSON) once issued;
- ``trajectories(id, episode, steps, sha256)``: one row per expert trajectory, ids from 0;
- ``points(trajectory, step, s_0.., a_0.., q)``: the (s, a, Q) triplets, one row per step;
- ``episodes(episode, ...)``: Algorithm 1's decision per episode, and the policy's return.

Each trajectory is committed in one transaction together with the episode that asked for it,
with synchronous=FULL and a rollback journal: a process killed mid-write leaves every earlier
trajectory intact and the interrupted one absent, never half-written. Loading verifies the
format version, the dimensions, every trajectory's row count and its SHA-256, so a damaged or
foreign file is refused with a clear error instead of loading partially.
"""

from __future__ import annotations

import hashlib
import json
import math
import sqlite3
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from npp_ros.dataset import Dataset, DatasetError, FloatArray, Trajectory

FORMAT_NAME = "npp_ros.run"
FORMAT_VERSION = 2  # 2: certification mode, stopping rule, checked gap and test per episode


class RunFileError(RuntimeError):
    """The run file is missing, damaged, of another version, or made for another run."""


@dataclass(frozen=True)
class RunMetadata:
    """What a run file was made for; a resume must ask for the same."""

    task: str
    seed: int
    state_dim: int
    action_dim: int
    lipschitz: float
    lipschitz_source: str
    lipschitz_detail: str
    gamma: float
    horizon: int
    epsilon: float
    condition: str
    p: float
    delta: float
    certify: str
    rule: str

    # Fields a resumed run must match exactly; the rest is provenance.
    IDENTITY = (
        "task", "seed", "state_dim", "action_dim", "lipschitz", "lipschitz_source",
        "gamma", "horizon", "epsilon", "condition", "p", "delta", "certify", "rule",
    )  # fmt: skip

    def mismatches(self, other: RunMetadata) -> list[str]:
        return [
            f"{name}: file has {getattr(self, name)!r}, this run asks for {getattr(other, name)!r}"
            for name in self.IDENTITY
            if getattr(self, name) != getattr(other, name)
        ]


@dataclass(frozen=True)
class EpisodeRow:
    """One episode of Algorithm 1 as stored (and as logged to CSV)."""

    episode: int
    initial_state: tuple[float, ...]
    v_lb: float
    v_ub: float
    gap: float
    oracle_called: bool
    trajectory: int | None
    dataset_size: int
    oracle_calls: int
    quiet_episodes: int
    window: int
    required: int
    certified: bool
    expert_value: float | None = None
    policy_return: float | None = None
    wall_time: float = 0.0
    checked_gap: float = math.inf  # the quantity the certification checked (see certification.py)
    test: int = 0  # the test this episode belongs to (0: no policy yet)
    test_delta: float = 0.0  # the confidence that test may spend


_EPISODE_COLUMNS = tuple(EpisodeRow.__dataclass_fields__)


def trajectory_digest(trajectory: Trajectory) -> str:
    h = hashlib.sha256()
    for arr in (trajectory.states, trajectory.actions, trajectory.values):
        h.update(np.ascontiguousarray(arr, dtype="<f8").tobytes())
    return h.hexdigest()


class RunStore:
    """One run file. Open with :meth:`create`, :meth:`open` or :meth:`open_or_create`."""

    def __init__(self, path: Path, conn: sqlite3.Connection, metadata: RunMetadata) -> None:
        self.path = path
        self._conn = conn
        self.metadata = metadata

    # ---------------------------------------------------------------- opening
    @staticmethod
    def _connect(path: Path) -> sqlite3.Connection:
        conn = sqlite3.connect(str(path), isolation_level=None, timeout=30.0)
        conn.execute("PRAGMA journal_mode=DELETE")
        conn.execute("PRAGMA synchronous=FULL")
        return conn

    @classmethod
    def create(cls, path: str | Path, metadata: RunMetadata) -> RunStore:
        path = Path(path)
        if path.exists():
            raise RunFileError(f"{path} already exists; open it to resume, or choose a new path")
        path.parent.mkdir(parents=True, exist_ok=True)
        conn = cls._connect(path)
        s_cols = ", ".join(f"s_{k} REAL NOT NULL" for k in range(metadata.state_dim))
        a_cols = ", ".join(f"a_{k} REAL NOT NULL" for k in range(metadata.action_dim))
        with _transaction(conn):
            conn.execute("CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)")
            conn.execute(
                "CREATE TABLE trajectories (id INTEGER PRIMARY KEY, episode INTEGER, "
                "steps INTEGER NOT NULL, sha256 TEXT NOT NULL, created REAL NOT NULL)"
            )
            conn.execute(
                f"CREATE TABLE points (trajectory INTEGER NOT NULL REFERENCES trajectories(id), "
                f"step INTEGER NOT NULL, {s_cols}, {a_cols}, q REAL NOT NULL, "
                "PRIMARY KEY (trajectory, step))"
            )
            conn.execute(
                "CREATE TABLE episodes (episode INTEGER PRIMARY KEY, initial_state TEXT NOT NULL, "
                "v_lb REAL, v_ub REAL, gap REAL, oracle_called INTEGER NOT NULL, trajectory INTEGER, "
                "dataset_size INTEGER NOT NULL, oracle_calls INTEGER NOT NULL, "
                "quiet_episodes INTEGER NOT NULL, window INTEGER NOT NULL, required INTEGER NOT NULL, "
                "certified INTEGER NOT NULL, expert_value REAL, policy_return REAL, wall_time REAL, "
                "checked_gap REAL, test INTEGER NOT NULL, test_delta REAL NOT NULL)"
            )
            rows = {"format": FORMAT_NAME, "format_version": str(FORMAT_VERSION), "created": str(time.time())}
            rows.update({k: json.dumps(v) for k, v in asdict(metadata).items()})
            conn.executemany("INSERT INTO meta VALUES (?, ?)", rows.items())
        return cls(path, conn, metadata)

    @classmethod
    def open(cls, path: str | Path) -> RunStore:
        path = Path(path)
        if not path.is_file():
            raise RunFileError(f"run file {path} does not exist")
        try:
            conn = cls._connect(path)
            check = conn.execute("PRAGMA quick_check").fetchone()[0]
            if check != "ok":
                raise RunFileError(f"{path} is damaged (SQLite quick_check: {check})")
            meta = dict(conn.execute("SELECT key, value FROM meta").fetchall())
        except sqlite3.DatabaseError as exc:
            raise RunFileError(f"{path} is not a readable npp_ros run file: {exc}") from exc
        if meta.get("format") != FORMAT_NAME:
            raise RunFileError(f"{path} is not an npp_ros run file (format {meta.get('format')!r})")
        if meta.get("format_version") != str(FORMAT_VERSION):
            raise RunFileError(
                f"{path} has format version {meta.get('format_version')}, this npp_ros reads version "
                f"{FORMAT_VERSION}; convert it or use the npp_ros that wrote it"
            )
        try:
            fields = {k: json.loads(meta[k]) for k in RunMetadata.__dataclass_fields__}
            metadata = RunMetadata(**fields)
        except (KeyError, ValueError, TypeError) as exc:
            raise RunFileError(f"{path} has incomplete metadata: {exc}") from exc
        return cls(path, conn, metadata)

    @classmethod
    def open_or_create(cls, path: str | Path, metadata: RunMetadata) -> RunStore:
        """Resume an existing file made for the same run, or start a new one."""
        path = Path(path)
        if not path.exists():
            return cls.create(path, metadata)
        store = cls.open(path)
        problems = store.metadata.mismatches(metadata)
        if problems:
            store.close()
            raise RunFileError(f"{path} belongs to another run and was left untouched:\n  " + "\n  ".join(problems))
        return store

    def close(self) -> None:
        self._conn.close()

    def __enter__(self) -> RunStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---------------------------------------------------------------- writing
    def record_episode(self, row: EpisodeRow, trajectory: Trajectory | None = None) -> None:
        """Store an episode, and the trajectory it asked for, atomically."""
        if (trajectory is None) != (row.trajectory is None):
            raise ValueError("an episode row names a trajectory if and only if one is given")
        with _transaction(self._conn):
            if trajectory is not None:
                self._insert_trajectory(row.trajectory, row.episode, trajectory)
            values = [_encode(getattr(row, name)) for name in _EPISODE_COLUMNS]
            marks = ", ".join("?" * len(values))
            self._conn.execute(f"INSERT INTO episodes ({', '.join(_EPISODE_COLUMNS)}) VALUES ({marks})", values)

    def add_trajectory(self, index: int, trajectory: Trajectory, episode: int | None = None) -> None:
        with _transaction(self._conn):
            self._insert_trajectory(index, episode, trajectory)

    def _insert_trajectory(self, index: int | None, episode: int | None, trajectory: Trajectory) -> None:
        meta = self.metadata
        Trajectory.validated(
            trajectory.states, trajectory.actions, trajectory.values,
            state_dim=meta.state_dim, action_dim=meta.action_dim, label=f"trajectory {index}",
        )  # fmt: skip
        expected = self._conn.execute("SELECT COUNT(*) FROM trajectories").fetchone()[0]
        if index != expected:
            raise RunFileError(f"trajectory index {index} out of order: the file holds {expected}")
        self._conn.execute(
            "INSERT INTO trajectories VALUES (?, ?, ?, ?, ?)",
            (index, episode, len(trajectory), trajectory_digest(trajectory), time.time()),
        )
        steps = np.arange(len(trajectory), dtype=np.float64)[:, None]
        block = np.hstack([steps, trajectory.states, trajectory.actions, trajectory.values[:, None]])
        marks = ", ".join("?" * (block.shape[1] + 1))
        self._conn.executemany(
            f"INSERT INTO points VALUES ({marks})",
            ((index, int(r[0]), *r[1:].tolist()) for r in block),
        )

    def set_policy_return(self, episode: int, policy_return: float) -> None:
        with _transaction(self._conn):
            self._conn.execute("UPDATE episodes SET policy_return = ? WHERE episode = ?", (policy_return, episode))

    def set_certificate(self, certificate: Mapping[str, Any]) -> None:
        with _transaction(self._conn):
            self._conn.execute("INSERT OR REPLACE INTO meta VALUES ('certificate', ?)", (json.dumps(certificate),))

    # ---------------------------------------------------------------- reading
    def certificate(self) -> dict[str, Any] | None:
        row = self._conn.execute("SELECT value FROM meta WHERE key = 'certificate'").fetchone()
        return None if row is None else json.loads(row[0])

    def episodes(self) -> list[EpisodeRow]:
        cur = self._conn.execute(f"SELECT {', '.join(_EPISODE_COLUMNS)} FROM episodes ORDER BY episode")
        rows = []
        for raw in cur:
            item = dict(zip(_EPISODE_COLUMNS, raw, strict=True))
            item["initial_state"] = tuple(json.loads(item["initial_state"]))
            for flag in ("oracle_called", "certified"):
                item[flag] = bool(item[flag])
            rows.append(EpisodeRow(**item))
        return rows

    def num_trajectories(self) -> int:
        return int(self._conn.execute("SELECT COUNT(*) FROM trajectories").fetchone()[0])

    def load_dataset(self) -> Dataset:
        """All trajectories, verified row count and SHA-256 each; any damage raises."""
        meta = self.metadata
        n, m = meta.state_dim, meta.action_dim
        try:
            table = self._conn.execute("SELECT id, steps, sha256 FROM trajectories ORDER BY id").fetchall()
            cols = [f"s_{k}" for k in range(n)] + [f"a_{k}" for k in range(m)] + ["q"]
            points = self._conn.execute(
                f"SELECT trajectory, step, {', '.join(cols)} FROM points ORDER BY trajectory, step"
            ).fetchall()
        except sqlite3.DatabaseError as exc:
            raise RunFileError(f"{self.path}: cannot read the dataset: {exc}") from exc
        total = sum(steps for _, steps, _ in table)
        dataset = Dataset(n, m, capacity=max(total, 1))
        if len(points) != total:
            raise RunFileError(f"{self.path} is damaged: {len(points)} points stored, trajectories declare {total}")
        arr = np.asarray(points, dtype=np.float64).reshape(len(points), 2 + n + m + 1)
        lo = 0
        for expected_id, (traj_id, steps, digest) in enumerate(table):
            block = arr[lo : lo + steps]
            lo += steps
            if traj_id != expected_id:
                raise RunFileError(f"{self.path} is damaged: trajectory {expected_id} is missing")
            if not (np.all(block[:, 0] == traj_id) and np.array_equal(block[:, 1], np.arange(steps))):
                raise RunFileError(f"{self.path} is damaged: trajectory {traj_id} has missing or extra steps")
            traj = Trajectory(block[:, 2 : 2 + n].copy(), block[:, 2 + n : 2 + n + m].copy(), block[:, -1].copy())
            if trajectory_digest(traj) != digest:
                raise RunFileError(f"{self.path} is damaged: trajectory {traj_id} fails its SHA-256 check")
            try:
                dataset.append(traj)
            except DatasetError as exc:
                raise RunFileError(f"{self.path} holds an invalid trajectory: {exc}") from exc
        return dataset


def _encode(value: Any) -> Any:
    if isinstance(value, tuple):
        return json.dumps([float(v) for v in value])
    if isinstance(value, float) and math.isnan(value):
        return None
    if isinstance(value, bool):
        return int(value)
    return value


@contextmanager
def _transaction(conn: sqlite3.Connection) -> Iterator[None]:
    conn.execute("BEGIN IMMEDIATE")
    try:
        yield
    except BaseException:
        conn.execute("ROLLBACK")
        raise
    conn.execute("COMMIT")


def state_tuple(state: FloatArray) -> tuple[float, ...]:
    return tuple(float(x) for x in np.asarray(state).ravel())
