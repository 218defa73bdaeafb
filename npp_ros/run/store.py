"""Crash-safe persistence of a run: expert trajectories, the episode log and the metadata.

The file is SQLite (format "npp_ros.run", version FORMAT_VERSION), readable by the sqlite3 shell, pandas,
R or any language; no pickle. Tables (see README, "Run file format"):

- ``meta(key, value)``: format, format_version, created, run_id (the run's identity: random, drawn when the file
  is made, recorded at the next writable open of a file from before it existed; the ROS graph seals every
  message of the run with it), the run's metadata (``RunConfig.metadata()``:
  task, seed, dims, horizon, gamma, the plant's model fingerprint, what it certifies, L with its source), and the
  certificate (JSON) once issued. A resumed run must ask for the same values; a file from before the
  fingerprint was recorded records its resuming run's;
- ``trajectories(id, episode, steps, sha256, created, feedback)``: one row per expert trajectory, ids from 0;
  ``feedback`` is 1 when its expert gave feedback gains;
- ``points(trajectory, step, s_0.., a_0.., q, k_0_0..)``: the (s, a, Q) triplets, one row per step, with the
  expert's feedback gain K (action_dim x state_dim; ``k_i_j`` is row i, column j; zero without gains);
- ``episodes(episode, ...)``: Algorithm 1's decision per episode, the policy's return, and whether the expert's
  answer and the policy's rollout met the task's success criterion (``expert_success``, ``policy_success``:
  1, 0 or NULL when not judged).

- ``seal(part, sha256)``: the seal (``seal.py``), rewritten in every write transaction: a SHA-256 digest of each
  meta key and of each column of the tables above, and ``run``, the one digest over them all.

Each trajectory is committed in one transaction together with the episode that asked for it.
Crash safety, while a writer runs: journal_mode=WAL with synchronous=FULL. A commit appends the
transaction's pages to ``run.sqlite-wal`` and ends with a commit frame; FULL fsyncs the WAL at
every commit, so an acknowledged trajectory survives a killed process and a power cut. Frames
carry checksums and a salt: on the next open SQLite replays only complete, committed
transactions and ignores a torn tail, so the interrupted trajectory is absent, never half
written. Checkpoints copy pages into run.sqlite only from a synced WAL and sync the file before
the WAL is reused. WAL is what lets readers (sqlite3 shell, pandas, npp-bench) hold a read
transaction for as long as they like without ever making the writer wait: a reader sees the
snapshot it started with, the writer appends behind it. On a clean close the file goes back to
a rollback journal, so a finished run is one self-contained file (copy it, read it from
read-only media) exactly as older npp_ros wrote them; those open and resume unchanged.

One writer per run file: the writer holds an exclusive ``flock`` on ``run.lock`` beside it
(pid and command line inside; ``writer_lock.py``), which the OS drops when the writer exits or dies. A second
writer is refused up front, naming the first; readers take no lock. The file is created
atomically (schema built in a temporary file, then renamed), so a full disk or a kill during
creation never leaves an empty run.sqlite that blocks the folder. A failed write says what ran
out (disk full, folder not writable) and where; the rollback never hides the cause (``write_safety.py``).

Loading reads everything inside one read transaction (one snapshot), so a commit by a live
writer between two reads is never mistaken for damage. Loading verifies the format version,
the dimensions, every trajectory's row count and its SHA-256 (over its gains too, where it has them;
``trajectory_checksum.py``), so a damaged or foreign file is refused with a clear error instead of loading partially.

Files of version 2 (before gains were stored) open unchanged for reading, their trajectories without
gains (``gains_note`` says so); the first write upgrades them in place to version 3, in one transaction
that adds the gain columns as zeros. Files made before success was recorded (version 2, and version 3 from
before the columns existed) open with None for it; the first write adds the two columns, NULL for the rows
already there. Nullable columns leave the version at 3: an older npp_ros reads such a file as before.
"""

from __future__ import annotations

import json
import math
import os
import secrets
import sqlite3
import time
import warnings
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

import numpy as np

from npp_ros.policy.dataset import Dataset, DatasetError, Trajectory
from npp_ros.run.policy_lipschitz import LipschitzChoice
from npp_ros.run.records import (
    EPISODE_COLUMNS,
    LATER_COLUMNS,
    ROBOT_EPISODE_COLUMNS,
    SUCCESS_COLUMNS,
    EpisodeRow,
    RobotEpisode,
    RunFileError,
    RunMetadata,
)
from npp_ros.run.seal import SealCheck, check_seal
from npp_ros.run.trajectory_checksum import SignedZeroChecksum, signed_zeros_behind, trajectory_digest
from npp_ros.run.write_safety import (
    SQLITE_BUSY,
    SQLITE_LOCKED,
    connect,
    holds_nothing,
    make_folder,
    primary_code,
    remove_leftovers,
    sync_folder,
    transaction,
    write_error,
)
from npp_ros.run.writer_lock import WriterLock

RUN_FILE = "run.sqlite"  # a run folder's run file: every writer and reader names it by this

FORMAT_NAME = "npp_ros.run"
FORMAT_VERSION = 3  # 2: certification mode, stopping rule, checked gap and test per episode; 3: feedback gains
READABLE_VERSIONS = (2, 3)
# Meta keys that are not the run's metadata (RunConfig.metadata()): the file's own, and what the run adds.
_FILE_KEYS = ("format", "format_version", "created", "certificate", "run_id")


def gain_columns(state_dim: int, action_dim: int) -> list[str]:
    """k_i_j: row i (actuator), column j (state entry) of each point's gain, row-major."""
    return [f"k_{i}_{j}" for i in range(action_dim) for j in range(state_dim)]


class RunStore:
    """One run file. Open with :meth:`create`, :meth:`open` or :meth:`open_or_create`.

    :meth:`create` and :meth:`open_or_create` make this process the file's one writer;
    :meth:`open` reads without a lock, and becomes the writer at its first write.
    """

    def __init__(
        self, path: Path, conn: sqlite3.Connection, metadata: RunMetadata, lock: WriterLock | None = None
    ) -> None:
        self.path = path
        self._conn = conn
        self.metadata = metadata
        self._lock = lock
        self._wal = False
        self.format_version = FORMAT_VERSION

    # ---------------------------------------------------------------- opening
    @classmethod
    def create(cls, path: str | Path, metadata: RunMetadata) -> RunStore:
        path = Path(path)
        make_folder(path.parent)
        lock = WriterLock.acquire(path)
        try:
            if not holds_nothing(path):
                raise RunFileError(f"{path} already exists; open it to resume, or choose a new path")
            return cls._create_locked(path, metadata, lock)
        except BaseException:
            lock.release()
            raise

    @classmethod
    def _create_locked(cls, path: Path, metadata: RunMetadata, lock: WriterLock) -> RunStore:
        """Build the schema in a temporary file and rename it into place: the run file either
        does not exist or is complete, whatever happens meanwhile (disk full, a kill)."""
        remove_leftovers(path)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.new")
        conn: sqlite3.Connection | None = None
        try:
            conn = connect(tmp)
            conn.execute("PRAGMA journal_mode=DELETE")
            cls._write_schema(conn, metadata, path)
            conn.close()
            conn = None
            os.replace(tmp, path)
            sync_folder(path.parent)
        except BaseException as exc:
            if conn is not None:
                conn.close()
            for leftover in (tmp, tmp.with_name(tmp.name + "-journal")):
                leftover.unlink(missing_ok=True)
            if isinstance(exc, (OSError, sqlite3.Error)):
                raise write_error(exc, path) from exc
            raise
        store = cls(path, connect(path), metadata, lock)
        try:
            store._use_wal()
        except BaseException:
            store._conn.close()
            raise
        return store

    @staticmethod
    def _write_schema(conn: sqlite3.Connection, metadata: RunMetadata, path: Path) -> None:
        s_cols = ", ".join(f"s_{k} REAL NOT NULL" for k in range(metadata.state_dim))
        a_cols = ", ".join(f"a_{k} REAL NOT NULL" for k in range(metadata.action_dim))
        k_cols = ", ".join(
            f"{k} REAL NOT NULL DEFAULT 0" for k in gain_columns(metadata.state_dim, metadata.action_dim)
        )
        with transaction(conn, path):
            conn.execute("CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)")
            conn.execute(
                "CREATE TABLE trajectories (id INTEGER PRIMARY KEY, episode INTEGER, "
                "steps INTEGER NOT NULL, sha256 TEXT NOT NULL, created REAL NOT NULL, "
                "feedback INTEGER NOT NULL DEFAULT 0)"
            )
            conn.execute(
                f"CREATE TABLE points (trajectory INTEGER NOT NULL REFERENCES trajectories(id), "
                f"step INTEGER NOT NULL, {s_cols}, {a_cols}, q REAL NOT NULL, {k_cols}, "
                "PRIMARY KEY (trajectory, step))"
            )
            conn.execute(
                "CREATE TABLE episodes (episode INTEGER PRIMARY KEY, initial_state TEXT NOT NULL, "
                "v_lb REAL, v_ub REAL, gap REAL, oracle_called INTEGER NOT NULL, trajectory INTEGER, "
                "dataset_size INTEGER NOT NULL, oracle_calls INTEGER NOT NULL, "
                "quiet_episodes INTEGER NOT NULL, window INTEGER NOT NULL, required INTEGER NOT NULL, "
                "certified INTEGER NOT NULL, expert_value REAL, policy_return REAL, wall_time REAL, "
                "checked_gap REAL, test INTEGER NOT NULL, test_delta REAL NOT NULL, "
                "explored INTEGER NOT NULL DEFAULT 0, expert_success INTEGER, policy_success INTEGER, robot TEXT)"
            )
            rows = {"format": FORMAT_NAME, "format_version": str(FORMAT_VERSION), "created": str(time.time()),
                    "run_id": new_run_id()}  # fmt: skip
            rows.update({k: json.dumps(v) for k, v in vars(metadata).items()})
            conn.executemany("INSERT INTO meta VALUES (?, ?)", rows.items())

    @classmethod
    def open(cls, path: str | Path) -> RunStore:
        """Open for reading; no lock, so it never stops a running writer."""
        path = Path(path)
        if not path.is_file():
            raise RunFileError(f"run file {path} does not exist")
        if holds_nothing(path):
            raise RunFileError(f"{path} is not a readable npp_ros run file: it is empty, no run was stored in it")
        try:
            conn = connect(path)
            check = conn.execute("PRAGMA quick_check").fetchone()[0]
            if check != "ok":
                raise RunFileError(f"{path} is damaged (SQLite quick_check: {check})")
            meta = dict(conn.execute("SELECT key, value FROM meta").fetchall())
        except sqlite3.DatabaseError as exc:
            raise RunFileError(f"{path} is not a readable npp_ros run file: {exc}") from exc
        if meta.get("format") != FORMAT_NAME:
            raise RunFileError(f"{path} is not an npp_ros run file (format {meta.get('format')!r})")
        if meta.get("format_version") not in [str(v) for v in READABLE_VERSIONS]:
            raise RunFileError(
                f"{path} has format version {meta.get('format_version')}, this npp_ros reads versions "
                f"{', '.join(map(str, READABLE_VERSIONS))}; convert it or use the npp_ros that wrote it"
            )
        try:
            metadata = RunMetadata(**{k: json.loads(v) for k, v in meta.items() if k not in _FILE_KEYS})
        except (ValueError, TypeError) as exc:
            raise RunFileError(f"{path} has unreadable metadata: {exc}") from exc
        missing = {"state_dim", "action_dim"} - vars(metadata).keys()  # the tables' shape
        if missing:
            raise RunFileError(f"{path} has incomplete metadata: no {' or '.join(sorted(missing))}")
        store = cls(path, conn, metadata)
        store.format_version = int(meta["format_version"])
        return store

    @classmethod
    def open_or_create(cls, path: str | Path, metadata: RunMetadata) -> RunStore:
        """Resume an existing file made for the same run, or start a new one; as its one writer."""
        path = Path(path)
        make_folder(path.parent)
        lock = WriterLock.acquire(path)
        try:
            if holds_nothing(path):  # absent, or empty (an older npp_ros died creating it)
                return cls._create_locked(path, metadata, lock)
            store = cls.open(path)
        except BaseException:
            lock.release()
            raise
        try:
            problems = store.metadata.mismatches(metadata)
            if problems:
                raise RunFileError(f"{path} belongs to another run and was left untouched:\n  " + "\n  ".join(problems))
            store._refuse_unless_as_sealed()
            store._lock = lock
            store._use_wal()
            store._upgrade()
            store._record_meta(store.metadata.unrecorded(metadata))
            if store._meta_value("run_id") is None:  # a file from before runs had an identity gets one now
                with transaction(store._conn, store.path):
                    store._conn.execute("INSERT INTO meta VALUES ('run_id', ?)", (new_run_id(),))
            return store
        except BaseException:
            store.close()
            lock.release()
            raise

    def _refuse_unless_as_sealed(self) -> None:
        """Before a run writes to its file again: the file must hold what the run sealed, or the next write would
        seal an edit made since (a changed episode, a changed L) as the run's own. An unsealed file (from before
        seals) is sealed by that write, as it is."""
        changed = self.check_seal().mismatches
        if changed:
            raise RunFileError(
                f"{self.path} no longer holds what its run sealed ({', '.join(changed)} changed since): it was left "
                "untouched, and no run resumes from it. Restore the file from a copy, or start the run in a new "
                "folder"
            )

    def _writable(self) -> None:
        """Become the file's one writer before the first write of a store opened for reading."""
        if self._lock is None:
            self._lock = WriterLock.acquire(self.path)
            try:
                self._refuse_unless_as_sealed()
                self._use_wal()
                self._upgrade()
            except BaseException:
                self._lock.release()
                self._lock = None
                raise

    def _upgrade(self) -> None:
        """A version-2 file gets the gain columns (zeros) and becomes version 3, and a file without the success
        columns gets them (NULL: not judged), in one transaction."""
        present = self._episode_columns()
        missing = [column for column in SUCCESS_COLUMNS if column not in present]
        later = [column for column in LATER_COLUMNS if column not in present]
        if self.format_version == FORMAT_VERSION and not missing and not later:
            return
        meta = self.metadata
        with transaction(self._conn, self.path):
            if self.format_version != FORMAT_VERSION:
                self._conn.execute("ALTER TABLE trajectories ADD COLUMN feedback INTEGER NOT NULL DEFAULT 0")
                self._conn.execute("ALTER TABLE episodes ADD COLUMN explored INTEGER NOT NULL DEFAULT 0")
                for column in gain_columns(meta.state_dim, meta.action_dim):
                    self._conn.execute(f"ALTER TABLE points ADD COLUMN {column} REAL NOT NULL DEFAULT 0")
                self._conn.execute("UPDATE meta SET value = ? WHERE key = 'format_version'", (str(FORMAT_VERSION),))
            for column in missing:
                self._conn.execute(f"ALTER TABLE episodes ADD COLUMN {column} INTEGER")
            for column in later:
                self._conn.execute(f"ALTER TABLE episodes ADD COLUMN {column} {LATER_COLUMNS[column]}")
        self.format_version = FORMAT_VERSION

    def _episode_columns(self) -> set[str]:
        """The columns the file's episodes table has (an older file lacks some of EPISODE_COLUMNS)."""
        return {str(row[1]) for row in self._conn.execute("PRAGMA table_info(episodes)")}

    @property
    def gains_note(self) -> str:
        """What a reader should know of the stored gains: "" when the file records them."""
        if self.format_version >= 3:
            return ""
        return (
            f"{self.path} was made before run files stored feedback gains (format version {self.format_version}): "
            "its trajectories carry none, so a feedback policy acts on them open loop"
        )

    def _use_wal(self) -> None:
        """WAL while writing: readers then never make a commit wait (see the module docstring)."""
        try:
            mode = self._conn.execute("PRAGMA journal_mode=WAL").fetchone()[0]
        except sqlite3.Error as exc:
            if primary_code(exc) in (SQLITE_BUSY, SQLITE_LOCKED):
                raise RunFileError(
                    f"{self.path} is held by a reader inside a transaction opened before this run started "
                    "(a sqlite3 shell after BEGIN?); end that transaction (COMMIT) and start again"
                ) from exc
            raise write_error(exc, self.path) from exc
        # A file system without shared memory keeps the rollback journal: still crash-safe,
        # but there a long read transaction can make a commit wait.
        self._wal = mode == "wal"

    def close(self) -> None:
        """Back to a rollback journal (one self-contained file) unless a reader still has it open."""
        if self._wal:
            self._wal = False
            with suppress(sqlite3.Error):  # then it stays in WAL mode, just as safe
                self._conn.execute("PRAGMA busy_timeout = 0")
                self._conn.execute("PRAGMA journal_mode=DELETE")
        self._conn.close()
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def __enter__(self) -> RunStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---------------------------------------------------------------- writing
    def record_episode(
        self, row: EpisodeRow, trajectory: Trajectory | None = None, explored: Sequence[Trajectory] = ()
    ) -> None:
        """Store an episode, the trajectory it asked for from s0 and those asked where the policy went, atomically."""
        if (trajectory is None) != (row.trajectory is None):
            raise ValueError("an episode row names a trajectory if and only if one is given")
        if len(explored) != row.explored or (explored and trajectory is None):
            raise ValueError("an episode row counts the trajectories it explored, after the one from s0")
        self._writable()
        with transaction(self._conn, self.path):
            if trajectory is not None:
                self._insert_trajectory(row.trajectory, row.episode, trajectory)
            for k, extra in enumerate(explored, start=1):
                assert row.trajectory is not None
                self._insert_trajectory(row.trajectory + k, row.episode, extra)
            values = [_encode(getattr(row, name)) for name in EPISODE_COLUMNS]
            marks = ", ".join("?" * len(values))
            self._conn.execute(f"INSERT INTO episodes ({', '.join(EPISODE_COLUMNS)}) VALUES ({marks})", values)

    def _insert_trajectory(self, index: int | None, episode: int | None, trajectory: Trajectory) -> None:
        meta = self.metadata
        Trajectory.validated(
            trajectory.states, trajectory.actions, trajectory.values,
            state_dim=meta.state_dim, action_dim=meta.action_dim, label=f"trajectory {index}", gains=trajectory.gains,
        )  # fmt: skip
        expected = self._conn.execute("SELECT COUNT(*) FROM trajectories").fetchone()[0]
        if index != expected:
            raise RunFileError(f"trajectory index {index} out of order: the file holds {expected}")
        self._conn.execute(
            "INSERT INTO trajectories VALUES (?, ?, ?, ?, ?, ?)",
            (index, episode, len(trajectory), trajectory_digest(trajectory), time.time(), trajectory.gains is not None),
        )
        steps = np.arange(len(trajectory), dtype=np.float64)[:, None]
        gains = (
            np.zeros((len(trajectory), meta.action_dim, meta.state_dim))
            if trajectory.gains is None
            else trajectory.gains
        )
        block = np.hstack([
            steps, trajectory.states, trajectory.actions, trajectory.values[:, None], gains.reshape(len(trajectory), -1)
        ])  # fmt: skip
        marks = ", ".join("?" * (block.shape[1] + 1))
        self._conn.executemany(
            f"INSERT INTO points VALUES ({marks})",
            ((index, int(r[0]), *r[1:].tolist()) for r in block),
        )

    def set_policy_return(self, episode: int, policy_return: float, policy_success: bool | None = None) -> None:
        """The policy's return (and its success) of an episode it drove after the episode was stored."""
        self._writable()
        with transaction(self._conn, self.path):
            self._conn.execute(
                "UPDATE episodes SET policy_return = ?, policy_success = ? WHERE episode = ?",
                (policy_return, _encode(policy_success), episode),
            )

    def record_prior(self, trajectories: Sequence[Trajectory]) -> None:
        """The trajectories the run starts with, from another run (RunConfig.prior), in one transaction: stored before
        any episode, under no episode of this run (a stop in between leaves all of them or none)."""
        self._writable()
        if self._conn.execute("SELECT COUNT(*) FROM episodes").fetchone()[0] or self.num_trajectories():
            raise RunFileError(f"{self.path}: a run's first trajectories come before anything else it stores")
        with transaction(self._conn, self.path):
            for index, trajectory in enumerate(trajectories):
                self._insert_trajectory(index, None, trajectory)

    def record_robot_episode(self, episode: RobotEpisode) -> None:
        """A robot's episode, the moment it ended (npp_ros.run.on_robot): a check kept before its row is stored, so a
        run stopped in between takes that same check up again instead of running the robot anew; a fault, marked."""
        if episode.role not in RobotEpisode.ROLES:
            raise ValueError(f"a robot episode is one of {', '.join(RobotEpisode.ROLES)}, got {episode.role!r}")
        self._writable()
        with transaction(self._conn, self.path):
            self._conn.execute(ROBOT_EPISODES_SCHEMA)
            expected = self._conn.execute("SELECT COUNT(*) FROM robot_episodes").fetchone()[0]
            if episode.id != expected:
                raise RunFileError(f"robot episode {episode.id} out of order: the file holds {expected}")
            values = [_encode(getattr(episode, name)) for name in ROBOT_EPISODE_COLUMNS]
            marks = ", ".join("?" * len(values))
            self._conn.execute(f"INSERT INTO robot_episodes VALUES ({marks})", values)

    def robot_episodes(self) -> list[RobotEpisode]:
        """Every episode a robot ran for this run, in order (none for a run on a model)."""
        if not self._conn.execute("SELECT 1 FROM sqlite_master WHERE name = 'robot_episodes'").fetchone():
            return []
        out = []
        for raw in self._conn.execute(f"SELECT {', '.join(ROBOT_EPISODE_COLUMNS)} FROM robot_episodes ORDER BY id"):
            item = dict(zip(ROBOT_EPISODE_COLUMNS, raw, strict=True))
            for key in ("requested", "start"):
                item[key] = None if item[key] is None else tuple(json.loads(item[key]))
            item["success"] = None if item["success"] is None else bool(item["success"])
            item["rollout"] = bytes(item["rollout"])
            out.append(RobotEpisode(**item))
        return out

    def record_lipschitz_choice(self, choice: LipschitzChoice) -> None:
        """The policy's L chosen at a choice point (npp_ros.run.policy_lipschitz): kept, so that the run, its gate and
        its readers act by the L it chose, whatever machine reads it."""
        self._writable()
        with transaction(self._conn, self.path):
            self._conn.execute(LIPSCHITZ_CHOICES_SCHEMA)
            self._conn.execute(
                "INSERT INTO lipschitz_choices VALUES (?, ?, ?, ?)",
                (choice.trajectories, choice.value, choice.starts, choice.record()),
            )

    def lipschitz_choices(self) -> dict[int, LipschitzChoice]:
        """The policy's L chosen at each choice point, by its data size in trajectories (none: the claim's L)."""
        if not self._conn.execute("SELECT 1 FROM sqlite_master WHERE name = 'lipschitz_choices'").fetchone():
            return {}
        rows = self._conn.execute("SELECT trajectories, value, starts, scores FROM lipschitz_choices ORDER BY 1")
        return {int(row[0]): LipschitzChoice.from_record(*row) for row in rows}

    def set_certificate(self, certificate: Mapping[str, Any]) -> None:
        self._writable()
        with transaction(self._conn, self.path):
            self._conn.execute("INSERT OR REPLACE INTO meta VALUES ('certificate', ?)", (json.dumps(certificate),))

    def _record_meta(self, values: Mapping[str, Any]) -> None:
        """Add metadata a file made by an older npp_ros lacks (never changes a recorded value)."""
        if not values:
            return
        with transaction(self._conn, self.path):
            self._conn.executemany("INSERT INTO meta VALUES (?, ?)", [(k, json.dumps(v)) for k, v in values.items()])
        for name, value in values.items():
            setattr(self.metadata, name, value)

    # ---------------------------------------------------------------- reading
    @contextmanager
    def snapshot(self) -> Iterator[None]:
        """Reads inside see one committed state of the file while a writer goes on (reads only)."""
        if self._conn.in_transaction:  # nested: the outer snapshot holds
            yield
            return
        self._conn.execute("BEGIN")
        try:
            yield
        finally:
            if self._conn.in_transaction:
                self._conn.execute("COMMIT")

    def _meta_value(self, key: str) -> str | None:
        row = self._conn.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        return None if row is None else str(row[0])

    @property
    def run_id(self) -> str:
        """The run's identity ("" for a file from before runs had one, until a writer opens it)."""
        return self._meta_value("run_id") or ""

    def check_seal(self) -> SealCheck:
        """Whether the file still holds exactly what its writer sealed, and what no longer matches (seal.py)."""
        try:
            with self.snapshot():
                return check_seal(self._conn)
        except sqlite3.DatabaseError as exc:
            raise RunFileError(f"{self.path}: cannot check its seal: {exc}") from exc

    def certificate(self) -> dict[str, Any] | None:
        value = self._meta_value("certificate")
        return None if value is None else json.loads(value)

    def episodes(self) -> list[EpisodeRow]:
        # The columns this file has: one from an older npp_ros lacks the newer ones, whose fields keep their defaults.
        present = self._episode_columns()
        columns = [c for c in EPISODE_COLUMNS if c in present]
        cur = self._conn.execute(f"SELECT {', '.join(columns)} FROM episodes ORDER BY episode")
        rows = []
        for raw in cur:
            item = dict(zip(columns, raw, strict=True))
            item["initial_state"] = tuple(json.loads(item["initial_state"]))
            for flag in ("oracle_called", "certified"):
                item[flag] = bool(item[flag])
            for flag in SUCCESS_COLUMNS:  # 1, 0 or NULL (not judged)
                if item.get(flag) is not None:
                    item[flag] = bool(item[flag])
            rows.append(EpisodeRow(**item))
        return rows

    def num_trajectories(self) -> int:
        return int(self._conn.execute("SELECT COUNT(*) FROM trajectories").fetchone()[0])

    def load_dataset(self) -> Dataset:
        """All trajectories, verified row count and SHA-256 each; any damage raises."""
        meta = self.metadata
        n, m = meta.state_dim, meta.action_dim
        with_gains = self.format_version >= 3
        feedback = "feedback" if with_gains else "0"
        try:
            with self.snapshot():  # a commit between the two reads would look like damage
                table = self._conn.execute(
                    f"SELECT id, steps, sha256, {feedback} FROM trajectories ORDER BY id"
                ).fetchall()
                cols = [f"s_{k}" for k in range(n)] + [f"a_{k}" for k in range(m)] + ["q"]
                cols += gain_columns(n, m) if with_gains else []
                points = self._conn.execute(
                    f"SELECT trajectory, step, {', '.join(cols)} FROM points ORDER BY trajectory, step"
                ).fetchall()
        except sqlite3.DatabaseError as exc:
            raise RunFileError(f"{self.path}: cannot read the dataset: {exc}") from exc
        total = sum(row[1] for row in table)
        dataset = Dataset(n, m, capacity=max(total, 1))
        if len(points) != total:
            raise RunFileError(f"{self.path} is damaged: {len(points)} points stored, trajectories declare {total}")
        arr = np.asarray(points, dtype=np.float64).reshape(len(points), 2 + len(cols))
        lo = 0
        q = 2 + n + m  # the column of Q; the gains follow it
        for expected_id, (traj_id, steps, digest, has_gains) in enumerate(table):
            block = arr[lo : lo + steps]
            lo += steps
            if traj_id != expected_id:
                raise RunFileError(f"{self.path} is damaged: trajectory {expected_id} is missing")
            if not (np.all(block[:, 0] == traj_id) and np.array_equal(block[:, 1], np.arange(steps))):
                raise RunFileError(f"{self.path} is damaged: trajectory {traj_id} has missing or extra steps")
            gains = block[:, q + 1 :].reshape(steps, m, n).copy() if has_gains else None
            traj = Trajectory(block[:, 2 : 2 + n].copy(), block[:, 2 + n : q].copy(), block[:, q].copy(), gains=gains)
            if trajectory_digest(traj) != digest:
                flipped = signed_zeros_behind(traj, digest)
                if flipped is None:
                    raise RunFileError(f"{self.path} is damaged: trajectory {traj_id} fails its SHA-256 check")
                warnings.warn(
                    f"{self.path}: trajectory {traj_id}'s checksum was taken before {flipped} of its -0.0 values were "
                    "stored as 0.0 (a writer from before checksums of stored values); it verifies with them, and "
                    "nothing else differs",
                    SignedZeroChecksum,
                    stacklevel=2,
                )
            try:
                dataset.append(traj)
            except DatasetError as exc:
                raise RunFileError(f"{self.path} holds an invalid trajectory: {exc}") from exc
        return dataset


ROBOT_EPISODES_SCHEMA = (
    "CREATE TABLE IF NOT EXISTS robot_episodes (id INTEGER PRIMARY KEY, episode INTEGER NOT NULL, role TEXT NOT NULL, "
    "requested TEXT, start TEXT NOT NULL, steps INTEGER NOT NULL, started_at REAL NOT NULL, robot_time REAL NOT NULL, "
    "late_commands INTEGER NOT NULL, fault TEXT, success INTEGER, policy_return REAL, rollout BLOB NOT NULL)"
)

LIPSCHITZ_CHOICES_SCHEMA = (
    "CREATE TABLE IF NOT EXISTS lipschitz_choices (trajectories INTEGER PRIMARY KEY, value REAL NOT NULL, "
    "starts INTEGER NOT NULL, scores TEXT NOT NULL)"
)


def _encode(value: Any) -> Any:
    if isinstance(value, tuple):
        return json.dumps([float(v) for v in value])
    if isinstance(value, float) and math.isnan(value):
        return None
    if isinstance(value, bool):
        return int(value)
    return value


def new_run_id() -> str:
    """A fresh run identity: 128 random bits, so that no two runs share one."""
    return secrets.token_hex(16)
