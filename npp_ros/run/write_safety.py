"""What keeps a write to the run file safe, and says what went wrong when one fails: the connection every reader
and writer opens, the write transaction (sealed before it commits, rolled back on failure), a failed write named in
words a user can act on (disk full, a folder not writable, another connection writing), the run folder made and a
rename into it made durable, and what counts as a file no run was ever stored in (which a creator may replace, with
the leftovers of creators that died).
"""

from __future__ import annotations

import errno
import glob
import os
import shutil
import sqlite3
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

from npp_ros.run.records import RunFileError
from npp_ros.run.seal import write_seal

# How long a write waits for another connection's write transaction (a user's sqlite3 shell
# writing to the file, say) before it gives up. Readers never make a writer wait (WAL).
BUSY_TIMEOUT_S = 30.0

# SQLite primary result codes that name the cause of a failed write.
SQLITE_BUSY, SQLITE_LOCKED, SQLITE_READONLY, SQLITE_IOERR, SQLITE_FULL = 5, 6, 8, 10, 13


def connect(path: Path) -> sqlite3.Connection:
    """A connection to the run file, for reading and writing: transactions are explicit (transaction(), a store's
    snapshot()), every commit is fsynced (synchronous=FULL) and a write waits BUSY_TIMEOUT_S for another's."""
    conn = sqlite3.connect(str(path), isolation_level=None, timeout=BUSY_TIMEOUT_S)
    conn.execute("PRAGMA synchronous=FULL")
    return conn


@contextmanager
def transaction(conn: sqlite3.Connection, path: Path) -> Iterator[None]:
    """One write transaction, sealed before it commits (seal.py: the seal always matches what it commits). On
    failure it rolls back unless SQLite already has (it does on a full disk), and raises the original cause,
    named, never the rollback's own complaint."""
    try:
        conn.execute("BEGIN IMMEDIATE")
        yield
        write_seal(conn)
        conn.execute("COMMIT")
    except BaseException as exc:
        if conn.in_transaction:
            with suppress(sqlite3.Error):  # if this fails too, SQLite undoes it at the next open
                conn.execute("ROLLBACK")
        if isinstance(exc, sqlite3.Error):
            raise write_error(exc, path) from exc
        raise


def primary_code(exc: BaseException) -> int | None:
    code = getattr(exc, "sqlite_errorcode", None)
    return None if code is None else code & 0xFF


def write_error(exc: BaseException, path: Path) -> RunFileError:
    """What a failed write ran into and where, in words a user can act on."""
    folder = path.parent
    code = primary_code(exc)
    err = exc.errno if isinstance(exc, OSError) else None
    if code == SQLITE_FULL or err in (errno.ENOSPC, errno.EDQUOT) or (code == SQLITE_IOERR and _nearly_full(folder)):
        return RunFileError(
            f"disk full: cannot write {path} ({_free_space(folder)} free in {folder}); what was stored before "
            "is intact: free some space and start the run again to resume"
        )
    if code == SQLITE_READONLY or err in (errno.EROFS, errno.EACCES, errno.EPERM):
        reason = os.strerror(err) if err is not None else str(exc)
        return RunFileError(
            f"{folder} is not writable ({reason}): a run writes its folder; make it writable or choose another"
        )
    if code in (SQLITE_BUSY, SQLITE_LOCKED):
        return RunFileError(
            f"cannot write {path}: another connection kept a write transaction open for {BUSY_TIMEOUT_S:g} s "
            "(a sqlite3 shell or script writing to it?); a run file has one writer"
        )
    return RunFileError(f"cannot write {path}: {exc}")


def _nearly_full(folder: Path) -> bool:
    """SQLite reports some out-of-space failures as I/O errors; a near-empty file system says which."""
    try:
        return shutil.disk_usage(folder).free < (1 << 20)
    except OSError:
        return False


def _free_space(folder: Path) -> str:
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return "unknown space"
    for unit in ("bytes", "KiB", "MiB", "GiB"):
        if free < 1024 or unit == "GiB":
            return f"{free:.0f} {unit}" if unit == "bytes" else f"{free:.1f} {unit}"
        free /= 1024
    return f"{free:.1f} GiB"


def make_folder(folder: Path) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            raise write_error(exc, folder) from exc
        raise RunFileError(f"cannot create the run folder {folder} ({exc.strerror}); choose another") from exc


def sync_folder(folder: Path) -> None:
    """Make a rename durable: fsync the folder's entry list (where the OS allows it)."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        with suppress(OSError):
            os.fsync(fd)
    finally:
        os.close(fd)


def holds_nothing(path: Path) -> bool:
    """Absent, or empty with no write-ahead log: no run was ever stored there."""
    try:
        if path.stat().st_size > 0:
            return False
    except FileNotFoundError:
        return True
    wal = path.with_name(path.name + "-wal")
    return not wal.exists() or wal.stat().st_size == 0


def remove_leftovers(path: Path) -> None:
    """Temporary files of creators that died, and an empty run file (only the writer calls this)."""
    for leftover in path.parent.glob(f".{glob.escape(path.name)}.*.new*"):
        leftover.unlink(missing_ok=True)
    if path.exists() and holds_nothing(path):
        path.unlink()
