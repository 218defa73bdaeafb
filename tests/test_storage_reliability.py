"""The run file against real and careless users: readers, a second writer, a full disk, a read-only folder.

Each test reproduces the situation the way a user met it. Where that needs a small file system,
the tests mount a tmpfs (root only) and skip that variant with the reason otherwise; the
simulated variant (SQLite's max_page_count makes the database full) runs everywhere.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from test_storage import META, fill, row, trajectory

from npp_ros.run import write_safety
from npp_ros.run.records import RunFileError, RunMetadata
from npp_ros.run.store import RunStore

LEARN = [sys.executable, "-m", "npp_ros.cli.learn"]


def record(store: RunStore, first: int, count: int, steps: int = 1000) -> None:
    """`count` more oracle episodes, each with its trajectory, after `first` stored trajectories."""
    for k in range(first, first + count):
        store.record_episode(row(k, k, steps * (k + 1)), trajectory(k, steps))


@pytest.fixture
def no_waiting(monkeypatch: pytest.MonkeyPatch) -> None:
    """Writers give up at once instead of after 30 s: any wait on a reader fails the test at once."""
    monkeypatch.setattr(write_safety, "BUSY_TIMEOUT_S", 0.0)


@pytest.fixture
def tmpfs(tmp_path: Path) -> Iterator[Path]:
    """A fresh 256 KiB tmpfs (needs root); the test is skipped with the reason if it cannot be mounted."""
    where = tmp_path / "tmpfs"
    where.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root; the max_page_count variant covers a full disk")
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(where)], capture_output=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.decode().strip()}")
    try:
        yield where
    finally:
        if subprocess.run(["umount", str(where)], capture_output=True).returncode != 0:
            subprocess.run(["umount", "-l", str(where)], capture_output=True)


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# ------------------------------------------------------------------------------------ readers
class ShellReader:
    """The sqlite3 shell, as a user types into it: statements in, result lines out."""

    def __init__(self, path: Path) -> None:
        self.proc = subprocess.Popen(
            ["sqlite3", str(path)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
        )

    def query(self, sql: str) -> str:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(f"{sql}\nSELECT 'done';\n")
        self.proc.stdin.flush()
        lines = []
        while (line := self.proc.stdout.readline().strip()) != "done":
            assert line or self.proc.poll() is None, "the sqlite3 shell exited"
            lines.append(line)
        return "\n".join(lines)

    def close(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        self.proc.wait(timeout=60)


class PythonReader:
    """Python's sqlite3 module (what pandas uses underneath), with an explicit transaction."""

    def __init__(self, path: Path) -> None:
        self.conn = sqlite3.connect(path, isolation_level=None)

    def query(self, sql: str) -> str:
        rows = []
        for statement in filter(None, (s.strip() for s in sql.split(";"))):
            rows = self.conn.execute(statement).fetchall()
        return "\n".join("|".join(str(v) for v in r) for r in rows)

    def close(self) -> None:
        self.conn.close()


@pytest.mark.parametrize("kind", ["sqlite3 shell", "python sqlite3"])
def test_a_reader_holding_a_transaction_never_stops_the_writer(tmp_path: Path, no_waiting: None, kind: str) -> None:
    """A reader keeps BEGIN; SELECT ... open while the run records episodes and trajectories:
    the writer never waits (it would fail at once here), and the reader keeps its snapshot."""
    if kind == "sqlite3 shell" and shutil.which("sqlite3") is None:
        pytest.skip("the sqlite3 shell is not installed")
    path = tmp_path / "run.sqlite"
    store = RunStore.create(path, META)
    record(store, 0, 2)
    reader = ShellReader(path) if kind == "sqlite3 shell" else PythonReader(path)
    held = time.monotonic()
    assert reader.query("BEGIN; SELECT COUNT(*) FROM points;") == "2000"
    record(store, 2, 30)
    store.set_policy_return(3, 812.5)
    store.set_certificate({"episodes": 32})
    assert store.load_dataset().num_trajectories == 32
    assert reader.query("SELECT COUNT(*) FROM points;") == "2000"  # still the snapshot it began with
    seconds = time.monotonic() - held
    assert reader.query("COMMIT; SELECT COUNT(*) FROM points;") == "32000"
    store.close()  # the reader still has the file open: it stays in WAL mode, consistent
    reader.close()
    with RunStore.open(path) as again:
        assert again.load_dataset().num_trajectories == 32 and len(again.episodes()) == 32
    print(f"\n{kind}: read transaction held {seconds:.2f} s while the writer committed 30 episodes (30,000 points)")


def test_a_reader_inside_a_transaction_before_the_run_starts_gets_a_clear_refusal(
    tmp_path: Path, no_waiting: None
) -> None:
    """Switching a closed file to WAL needs a moment without open transactions: the run says which."""
    path = tmp_path / "run.sqlite"
    RunStore.create(path, META).close()
    reader = PythonReader(path)
    assert reader.query("BEGIN; SELECT COUNT(*) FROM episodes;") == "0"
    with pytest.raises(RunFileError, match=r"is held by a reader inside a transaction opened before this run"):
        RunStore.open_or_create(path, META)
    reader.query("COMMIT;")
    with RunStore.open_or_create(path, META):  # nothing was changed, nothing is left locked
        pass
    reader.close()


def test_a_closed_run_file_is_one_rollback_journal_file_and_resumes(tmp_path: Path) -> None:
    """WAL only while a writer runs: closed, the folder holds run.sqlite alone, journaled as before."""
    path = tmp_path / "run.sqlite"
    with RunStore.create(path, META) as store:
        fill(store, 2)
        probe = sqlite3.connect(path)
        assert probe.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        probe.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.sqlite"]
    assert path.read_bytes()[18:20] == b"\x01\x01"  # file format header: rollback journal
    with RunStore.open_or_create(path, META) as store:  # what an older npp_ros wrote: resumes
        store.record_episode(row(4, 2, 150), trajectory(2))
        assert store.load_dataset().num_trajectories == 3


def test_loading_a_live_file_reads_one_snapshot(tmp_path: Path) -> None:
    """The writer commits between the loader's reads of `trajectories` and `points`: the load
    sees the file as it was, and the next load sees the new trajectory; neither looks damaged."""
    path = tmp_path / "run.sqlite"
    writer = RunStore.create(path, META)
    fill(writer, 3)
    reader = RunStore.open(path)
    commits = []

    def writer_commits_now(statement: str) -> None:
        if statement.startswith("SELECT trajectory, step") and not commits:
            commits.append(statement)
            writer.record_episode(row(6, 3, 200), trajectory(3))

    reader._conn.set_trace_callback(writer_commits_now)  # runs as the reader starts its second read
    data = reader.load_dataset()
    assert commits, "the writer did not commit between the two reads"
    assert data.num_trajectories == 3 and len(data) == 150
    assert reader.load_dataset().num_trajectories == 4
    reader.close()
    writer.close()


# ------------------------------------------------------------------------------------ one writer
def test_a_second_writer_is_refused_up_front_naming_the_first(tmp_path: Path) -> None:
    """Two npp-learn on one folder: the second is refused before any work and names the first;
    readers still read the live file; the lock dies with its holder (SIGKILL), and a run resumes."""
    folder = tmp_path / "runs" / "a"
    path = folder / "run.sqlite"
    # epsilon so small that the first run keeps calling the oracle until the test kills it
    command = [*LEARN, "--run-dir", str(folder), "--epsilon", "0.001", "--evaluate", "0"]
    first = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 300
        while not path.exists() or _episodes(path) < 2:
            assert first.poll() is None and time.monotonic() < deadline, "the first run did not start"
            time.sleep(0.2)
        second = subprocess.run(command, capture_output=True, text=True, timeout=300)
        assert second.returncode == 2, second.stderr
        message = second.stderr.strip()
        assert message == (
            f"npp-learn: {folder} is in use by pid {first.pid} "
            f"(python -m npp_ros.cli.learn --run-dir {folder} --epsilon 0.001 --evaluate 0); "
            "a run folder has one writer"
        )
        with RunStore.open(path) as reader:  # reading needs no lock
            stored = reader.load_dataset().num_trajectories
            assert stored >= 2
            with pytest.raises(RunFileError, match=rf"is in use by pid {first.pid} "):
                reader.set_policy_return(0, 1.0)  # its first write would make it a second writer
        print(f"\nrefused: {message}")
    finally:
        first.send_signal(signal.SIGKILL)
        first.wait()
    again = subprocess.run([*command, "--max-episodes", "1"], capture_output=True, text=True, timeout=300)
    assert "resuming" in again.stderr, again.stderr  # the lock died with its holder
    with RunStore.open(path) as reader:
        assert reader.load_dataset().num_trajectories >= stored


def _episodes(path: Path) -> int:
    with RunStore.open(path) as reader:
        return len(reader.episodes())


def test_two_writers_in_one_process_are_refused_too(tmp_path: Path) -> None:
    path = tmp_path / "run.sqlite"
    with RunStore.create(path, META):
        with pytest.raises(RunFileError, match=rf"{tmp_path} is in use by pid {os.getpid()} "):
            RunStore.open_or_create(path, META)
        with pytest.raises(RunFileError, match="is in use by"):
            RunStore.create(tmp_path / "run.sqlite", META)
    with RunStore.open_or_create(path, META):  # released on close
        pass


def test_a_forked_child_does_not_release_its_parents_lock(tmp_path: Path) -> None:
    """A child forked while the parent writes (multiprocessing's default on Linux) inherits the
    lock; dropping it there must leave the parent the one writer."""
    path = tmp_path / "run.sqlite"
    with RunStore.create(path, META) as store:
        child = os.fork()
        if child == 0:  # pragma: no cover - the child
            if store._lock is not None:
                store._lock.release()
            os._exit(0)
        os.waitpid(child, 0)
        assert (tmp_path / "run.lock").exists()
        with pytest.raises(RunFileError, match=rf"is in use by pid {os.getpid()} "):
            RunStore.open_or_create(path, META)
        record(store, 0, 1, steps=50)
    assert not (tmp_path / "run.lock").exists()


# ------------------------------------------------------------------------------------ full disk
def test_a_full_database_says_disk_full_and_keeps_what_was_stored(tmp_path: Path) -> None:
    """Simulated everywhere: max_page_count makes SQLite report SQLITE_FULL, as a full disk does,
    in the middle of a transaction; the error names the cause and the file, not the rollback."""
    path = tmp_path / "run.sqlite"
    store = RunStore.create(path, META)
    record(store, 0, 2, steps=50)
    pages = store._conn.execute("PRAGMA page_count").fetchone()[0]
    store._conn.execute(f"PRAGMA max_page_count = {pages + 1}")
    with pytest.raises(RunFileError, match=rf"^disk full: cannot write {path} \(") as failure:
        record(store, 2, 1)
    assert isinstance(failure.value.__cause__, sqlite3.OperationalError)
    assert "database or disk is full" in str(failure.value.__cause__)
    assert not store._conn.in_transaction
    assert store.num_trajectories() == 2 and len(store.episodes()) == 2
    store.close()
    with RunStore.open_or_create(path, META) as again:  # space again: the run resumes
        assert again.load_dataset().num_trajectories == 2
        record(again, 2, 1)


def test_a_failed_creation_leaves_nothing_behind(tmp_path: Path) -> None:
    """A creation that fails half way leaves no run.sqlite (nor temporary or lock file)."""
    folder = tmp_path / "run"
    unwritable = RunMetadata(**(vars(META) | {"lipschitz_detail": object()}))
    with pytest.raises(TypeError):
        RunStore.create(folder / "run.sqlite", unwritable)
    assert list(folder.iterdir()) == []
    with RunStore.open_or_create(folder / "run.sqlite", META) as store:
        assert store.num_trajectories() == 0


def test_an_empty_run_file_from_an_older_npp_ros_does_not_block_the_folder(tmp_path: Path) -> None:
    """Older npp_ros left a 0-byte run.sqlite when the disk was full: it holds nothing, a run replaces it."""
    path = tmp_path / "run.sqlite"
    path.touch()
    with pytest.raises(RunFileError, match="is not a readable npp_ros run file: it is empty"):
        RunStore.open(path)
    with RunStore.open_or_create(path, META) as store:
        record(store, 0, 1, steps=50)
    with RunStore.open(path) as store:
        assert store.load_dataset().num_trajectories == 1


def test_a_full_tmpfs_says_disk_full_and_where_and_leaves_no_empty_file(tmpfs: Path) -> None:
    """A real full file system: creation fails cleanly (no 0-byte run.sqlite), a run that fills
    it stops with 'disk full' and the path, and resumes intact once there is space again."""
    folder = tmpfs / "run"
    path = folder / "run.sqlite"
    filler = tmpfs / "filler"
    with filler.open("wb", buffering=0) as fh:  # fill the file system to its last blocks
        with pytest.raises(OSError):
            while True:
                fh.write(b"\0" * 4096)
                fh.flush()
    with pytest.raises(RunFileError, match=r"^disk full: cannot write .*(run\.sqlite|run\.lock) \(.* free in "):
        RunStore.open_or_create(path, META)
    assert [p.name for p in folder.iterdir()] == []  # nothing that would block the next start
    filler.unlink()

    filler.write_bytes(b"\0" * 96 * 1024)  # leave room for a few trajectories only
    store = RunStore.open_or_create(path, META)
    stored = 0
    with pytest.raises(RunFileError, match=rf"^disk full: cannot write {path} \(") as failure:
        for k in range(1000):
            store.record_episode(row(k, k, 200 * (k + 1)), trajectory(k, 200))
            stored = k + 1
    assert "cannot rollback" not in str(failure.value)
    store.close()
    filler.unlink()
    with RunStore.open_or_create(path, META) as again:
        data = again.load_dataset()  # every checksum verified
        assert data.num_trajectories == stored >= 1
        for k in range(stored):
            np.testing.assert_array_equal(data.trajectory(k).states, trajectory(k, 200).states)
        again.record_episode(row(stored, stored, 0), trajectory(stored, 200))
    print(f"\nfull tmpfs: {stored} trajectories stored, then: {failure.value}")


def test_npp_learn_on_a_full_disk_says_so_in_one_line(tmpfs: Path) -> None:
    """npp-learn as a user runs it, on a file system with room for a few trajectories."""
    folder = tmpfs / "run"
    run = subprocess.run([*LEARN, "--run-dir", str(folder), "--evaluate", "0"], capture_output=True, text=True)
    assert run.returncode == 2, run.stderr
    last = run.stderr.strip().splitlines()[-1]
    assert last.startswith(f"npp-learn: disk full: cannot write {folder / 'run.sqlite'} ("), run.stderr
    assert "Traceback" not in run.stderr
    with RunStore.open(folder / "run.sqlite") as store:  # what was stored is intact
        stored = store.load_dataset().num_trajectories
        assert stored >= 1 and len(store.episodes()) >= stored
    print(f"\n{stored} expert trajectories stored, then: {last}")


# ------------------------------------------------------------------------------------ read-only
def test_a_read_only_folder_is_refused_in_one_line_and_still_readable(tmpfs: Path) -> None:
    """A real read-only file system (tmpfs remounted ro; chmod does not stop root): resuming
    and starting are refused with the folder named; reading the finished run still works."""
    folder = tmpfs / "run"
    with RunStore.create(folder / "run.sqlite", META) as store:
        record(store, 0, 2, steps=50)
    remount = subprocess.run(["mount", "-o", "remount,ro", str(tmpfs)], capture_output=True, text=True)
    if remount.returncode != 0:
        pytest.skip(f"cannot remount the tmpfs read-only: {remount.stderr.strip()}")
    with pytest.raises(RunFileError, match=rf"^{folder} is not writable \(Read-only file system\)"):
        RunStore.open_or_create(folder / "run.sqlite", META)
    with pytest.raises(RunFileError, match=rf"^cannot create the run folder {tmpfs / 'new'} \(Read-only file system\)"):
        RunStore.create(tmpfs / "new" / "run.sqlite", META)
    with RunStore.open(folder / "run.sqlite") as store:
        assert store.load_dataset().num_trajectories == 2
    run = subprocess.run([*LEARN, "--run-dir", str(folder), "--evaluate", "0"], capture_output=True, text=True)
    assert run.returncode == 2
    assert run.stderr.strip() == (
        f"npp-learn: {folder} is not writable (Read-only file system): "
        "a run writes its folder; make it writable or choose another"
    )
