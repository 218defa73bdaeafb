"""Live status for long runs: one rewritten line on a terminal, periodic lines in a log."""

from __future__ import annotations

import sys
import time
from typing import TextIO

from npp_ros.certificate.certifier import Certificate, CertificationStatus
from npp_ros.run.loop import Observer
from npp_ros.run.records import EpisodeRow


def status_text(row: EpisodeRow, epsilon: float, status: CertificationStatus, condition: str) -> str:
    """One line: the checked gap against epsilon, and the current test's streak against what it needs."""
    checked = "inf" if row.checked_gap == float("inf") else f"{row.checked_gap:8.2f}"
    mark = "ORACLE" if row.oracle_called else "quiet "
    streak = (
        f"test {status.test} streak {status.quiet_episodes}/{status.required}"
        if condition == "i"
        else f"test {status.test} window {status.window} needs {status.required or '-'}"
    )
    if status.stage == "screen":
        streak = f"screen {status.quiet_episodes}/{status.required}"
    elif status.stage == "verification":
        failed = f"{status.failures} failed"
        streak = f"verification {status.test}: {status.window} checks, {failed}, needs {status.required}"
    return (
        f"episode {row.episode + 1:5d} | checked {checked} / eps {epsilon:g} {mark} | "
        f"|D| {row.dataset_size:8d} | oracle calls {row.oracle_calls:4d} | {streak}"
    )


class StatusLine(Observer):
    """Prints the run's state after each episode; rate-limited when not on a terminal."""

    def __init__(self, epsilon: float, condition: str, stream: TextIO | None = None, every: float = 2.0) -> None:
        self.epsilon = epsilon
        self.condition = condition
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self.every = every
        self._last = 0.0
        self._pending = ""

    def on_episode(self, row: EpisodeRow, status: CertificationStatus) -> None:
        text = status_text(row, self.epsilon, status, self.condition)
        now = time.monotonic()
        if self.tty:
            self.stream.write("\r" + text.ljust(110))
            self.stream.flush()
        elif now - self._last >= self.every or status.certified:
            self.stream.write(text + "\n")
            self.stream.flush()
            self._last = now

    def on_certificate(self, certificate: Certificate) -> None:
        self.close()

    def close(self) -> None:
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()


class Counter:
    """A small progress counter for batches of rollouts ("evaluating 12/100")."""

    def __init__(self, label: str, stream: TextIO | None = None) -> None:
        self.label = label
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self._last = 0.0

    def __call__(self, done: int, total: int) -> None:
        now = time.monotonic()
        if self.tty:
            self.stream.write(f"\r{self.label} {done}/{total}")
            if done == total:
                self.stream.write("\n")
            self.stream.flush()
        elif done == total or now - self._last >= 2.0:
            self.stream.write(f"{self.label} {done}/{total}\n")
            self.stream.flush()
            self._last = now
