"""One writer per run file: an exclusive flock on ``run.lock`` beside it, with the writer's pid and command line
inside, by which a second writer is refused, naming the first.
"""

from __future__ import annotations

import errno
import fcntl
import os
import shlex
import sys
from contextlib import suppress
from pathlib import Path

from npp_ros.run.records import RunFileError
from npp_ros.run.write_safety import write_error


class WriterLock:
    """An exclusive flock on RUN.lock beside the run file: one writer per run file. The OS
    releases it when its holder exits or dies, so a crash never leaves the folder locked; a
    clean release removes the file, so a folder at rest holds only the run's own files."""

    def __init__(self, fd: int, path: Path) -> None:
        self._fd = fd
        self._path = path
        self._owner = os.getpid()

    @classmethod
    def acquire(cls, run_path: Path) -> WriterLock:
        lock_path = run_path.with_suffix(".lock")
        while True:
            try:
                fd = os.open(lock_path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
            except OSError as exc:
                raise write_error(exc, lock_path) from exc
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                holder = _lock_holder(fd)
                os.close(fd)
                if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN):
                    raise RunFileError(
                        f"{run_path.parent} is in use by {holder}; a run folder has one writer"
                    ) from None
                raise RunFileError(f"cannot lock {lock_path} ({os.strerror(exc.errno or 0)})") from exc
            try:
                current = os.stat(lock_path)
                mine = os.fstat(fd)
                if (current.st_dev, current.st_ino) == (mine.st_dev, mine.st_ino):
                    break
            except FileNotFoundError:
                pass
            os.close(fd)  # the previous writer removed this file as we locked it: lock the current one
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n{_command_line()}\n".encode(), 0)
        except OSError as exc:
            cls(fd, lock_path).release()
            raise write_error(exc, lock_path) from exc
        return cls(fd, lock_path)

    def release(self) -> None:
        if self._fd >= 0 and os.getpid() == self._owner:  # never from a forked child: the parent writes on
            with suppress(OSError):  # removed while still held: a newcomer never locks a stale file
                self._path.unlink()
            os.close(self._fd)
            self._fd = -1

    def __del__(self) -> None:  # a store dropped without close() must not keep the folder
        self.release()


def _lock_holder(fd: int) -> str:
    """'pid N (command line)' of the writer, from the lock file it wrote (or /proc)."""
    try:
        pid_text, _, command = os.pread(fd, 4096, 0).decode(errors="replace").partition("\n")
    except OSError:
        return "another process"
    if not pid_text.strip().isdigit():
        return "another process"
    pid = int(pid_text)
    command = command.strip()
    if not command:
        with suppress(OSError):
            command = shlex.join(Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")[:-1])
    return f"pid {pid} ({command})" if command else f"pid {pid}"


def _command_line() -> str:
    """How this process was started, as a user would type it (npp-learn --run-dir runs/a)."""
    argv = sys.argv
    if argv and argv[0] not in ("", "-c") and not argv[0].endswith(".py"):
        words = [Path(argv[0]).name, *argv[1:]]  # a console script
    else:
        words = [Path(sys.orig_argv[0]).name, *sys.orig_argv[1:]]
    line = " ".join(shlex.join(words).split())  # one line, whatever a -c script holds
    return line if len(line) <= 200 else line[:197] + "..."
