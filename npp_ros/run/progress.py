"""Live status for long runs: one rewritten line on a terminal, periodic lines in a log."""

from __future__ import annotations

import math
import sys
import time
from typing import TextIO

from npp_ros.certificate.certifier import L_FREE, Certificate, CertificationSpec, CertificationStatus
from npp_ros.run.loop import Observer
from npp_ros.run.records import EpisodeRow, GapRecord


def claim_header(spec: CertificationSpec, policy_lipschitz: str = "claim") -> str:
    """What a run certifies, in the words its first line says: the claim's own numbers (no epsilon where it bounds
    no gap, no L where it rests on none) and the L the policy chooses by."""
    own = " (then chosen from the run's data)" if policy_lipschitz == "select" else ""
    if spec.certify == "success":
        return (
            f"success claim, p {spec.p:g}, delta {spec.delta:g}; the policy acts with {spec.lipschitz.describe()}{own}"
        )
    if spec.certify in L_FREE:
        return f"{spec.certify} claim, epsilon {spec.epsilon:g}; the policy acts with {spec.lipschitz.describe()}{own}"
    return f"{spec.certify} claim, epsilon {spec.epsilon:g}, {spec.lipschitz.describe()}" + (
        "; the policy's L chosen from the run's data" if own else ""
    )


def checked_text(checked_gap: float, epsilon: float, certify: str, label: str = "checked") -> str:
    """The checked quantity against what it must not exceed; the success claim's check as met or FAILED."""
    if certify == "success":
        met = "no policy" if math.isinf(checked_gap) else "met" if checked_gap == 0 else "FAILED"
        return f"success {met:>9}"
    return f"{label} {'inf' if math.isinf(checked_gap) else f'{checked_gap:.2f}':>8} / eps {epsilon:g}"


def progress_text(gap: GapRecord, status: CertificationStatus | None = None) -> str:
    """One episode's progress line, as npp-learn and npp-run print it: the checked gap against epsilon, whether the
    oracle was asked, the dataset size, the oracle calls, and the current test's streak against what it needs.
    Episodes are counted from 1, as the certificate counts them (the run file's index is from 0).

    Given the loop's ``status`` (npp-learn's), the streak is its own words for condition (ii) (the window against
    its need) and the mixture rule (its screen, or its verification's checks and failures); a gap report carries
    the streak and the need alone, which under condition (i)'s sequential and paper rules are the same words.
    """
    mark = "ORACLE" if gap.oracle_called else "quiet "
    streak = f"test {gap.test} streak {gap.quiet_episodes}/{gap.required}"
    if status is not None and status.stage == "screen":
        streak = f"screen {status.quiet_episodes}/{status.required}"
    elif status is not None and status.stage == "verification":
        failed = f"{status.failures} failed"
        streak = f"verification {status.test}: {status.window} checks, {failed}, needs {status.required}"
    elif status is not None and gap.condition != "i":
        streak = f"test {status.test} window {status.window} needs {status.required or '-'}"
    return (
        f"episode {gap.episode + 1:5d} | {checked_text(gap.checked_gap, gap.epsilon, gap.certify)} {mark} | "
        f"|D| {gap.dataset_size:8d} | oracle calls {gap.oracle_calls:4d} | {streak}"
    )


def status_text(row: EpisodeRow, epsilon: float, status: CertificationStatus, condition: str, certify: str = "") -> str:
    """The progress line of a row the loop just decided, with where the certification stands (``status``)."""
    return progress_text(GapRecord.of(row, epsilon=epsilon, condition=condition, certify=certify), status)


def unreachable_text(status: CertificationStatus, episodes: int, max_episodes: int) -> str | None:
    """The line that says a certificate can no longer come within ``max_episodes``, after ``episodes`` episodes;
    None while it still can, where the rule cannot tell (CertificationStatus.episodes_to_certify), and at the
    run's last episode, which ends it anyway."""
    left = max_episodes - episodes
    if left <= 0 or status.reachable_within(left) is not False:
        return None
    if status.stage == "screen":
        where = f"screen {status.quiet_episodes}/{status.required}, then a verification"
    elif status.stage == "verification":
        where = f"verification {status.test}: {status.window} checks, {status.failures} failed"
    else:
        where = f"test {status.test} streak {status.quiet_episodes}/{status.required}"
    return (
        f"the certificate can no longer be reached within {max_episodes} episodes: after episode {episodes} it "
        f"needs at least {status.episodes_to_certify} more episodes ({where}), and {left} are left"
    )


class StatusLine(Observer):
    """Prints the run's state after each episode; rate-limited when not on a terminal.

    Given ``max_episodes``, it also says once, on its own line, when a certificate can no longer come
    within that many episodes (``unreachable``): the run goes on to its end unless its caller stops it."""

    def __init__(
        self,
        epsilon: float,
        condition: str,
        stream: TextIO | None = None,
        every: float = 2.0,
        *,
        max_episodes: int | None = None,
        prefix: str = "",
        certify: str = "",
    ) -> None:
        self.epsilon = epsilon
        self.certify = certify  # the checked quantity: the success claim's line says met or FAILED
        self.condition = condition
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self.every = every
        self.max_episodes = max_episodes
        self.prefix = prefix  # before the unreachable line, e.g. "npp-learn: "
        self.unreachable = ""  # the line, once said
        self._last = 0.0
        self._pending = ""
        self._passes_unsaid = 0  # passed checks since the last line written (a log's lines count every check)

    def _passed(self, row: EpisodeRow) -> bool:
        if self.certify == "success":
            return row.checked_gap == 0
        return row.checked_gap <= self.epsilon  # inf (no policy yet) and NaN fail

    def on_episode(self, row: EpisodeRow, status: CertificationStatus) -> None:
        """On a terminal, one line rewritten; in a log, a line for every failed check and, at most every ``every``
        seconds, one for the passes, counting those passed since the last line, so that every check is counted."""
        text = status_text(row, self.epsilon, status, self.condition, self.certify)
        now = time.monotonic()
        line = None
        if self.max_episodes is not None and not self.unreachable:
            line = unreachable_text(status, row.episode + 1, self.max_episodes)
        passed = self._passed(row)
        if self.tty:
            self.stream.write("\r" + text.ljust(110))
            self.stream.flush()
        elif not passed or now - self._last >= self.every or status.certified or line is not None:
            before = self._passes_unsaid
            said = f" | {before} more passed since the last line" if before else ""
            self.stream.write(text + said + "\n")
            self.stream.flush()
            self._last, self._passes_unsaid = now, 0
        else:
            self._passes_unsaid += 1
        if line is not None:
            self.unreachable = line
            self.stream.write(("\n" if self.tty else "") + self.prefix + line + "\n")
            self.stream.flush()

    def on_certificate(self, certificate: Certificate) -> None:
        """Said the moment the certificate is issued, before whatever the command does next (a held-out check)."""
        self.close()
        self.stream.write(
            f"{self.prefix}certified after {certificate.episodes} episodes and {certificate.oracle_calls} expert "
            f"calls (the policy over {certificate.policy_trajectories} trajectories)\n"
        )
        self.stream.flush()

    def close(self) -> None:
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()


class Counter:
    """A small progress counter for a batch of slow steps ("evaluating 12/100 (34 s)"): the count and the
    seconds since its first call, so a long phase is never silent."""

    def __init__(self, label: str, stream: TextIO | None = None, every: float = 2.0) -> None:
        self.label = label
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self.every = every
        self._last = -math.inf
        self._started: float | None = None

    def __call__(self, done: int, total: int) -> None:
        now = time.monotonic()
        self._started = now if self._started is None else self._started
        text = f"{self.label} {done}/{total} ({now - self._started:.0f} s)"
        if self.tty:
            self.stream.write(f"\r{text}")
            if done == total:
                self.stream.write("\n")
            self.stream.flush()
        elif done == total or now - self._last >= self.every:
            self.stream.write(f"{text}\n")
            self.stream.flush()
            self._last = now
