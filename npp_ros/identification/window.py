"""Identification on a sliding window of a commanded robot's motion: whether the robot it drives is one of the set.

The transition monitor (npp_ros.deployment.model_monitor) asks of each step whether some robot of the set explains it;
under the certified policy's own smooth commands a moderately wrong robot (a gear of x0.6, a delay of 2) explains
each step well enough. Fitting the set's parameters to the last few seconds of motion asks the question of all of
them together: a window is *outside* when no robot of the set lies within the identified combinations' intervals
(fit.Identification.verdict, at the fit's confidence), and the robot is found outside when ``in_a_row`` windows in
a row are. A window the fit cannot use (too few transitions, a robot at rest that says nothing) is no finding.

What it cannot find is what the motion cannot show: a robot whose identifiable combinations equal a robot of the
set's (a pendulum of mass x1.5 moves exactly as the set's robot of mass x1.2, gear x0.8, damping x0.8) behaves as
that robot, and the certificate's checks of that robot are checks of it.

:func:`judge` is a plain function of plain values, so npp-deploy runs it in a worker process of its own and its
control loop never waits for a fit.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from npp_ros.identification.fit import identify
from npp_ros.identification.recording import Recording
from npp_ros.policy.dataset import FloatArray
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.uncertainty import UncertaintySet

WINDOW_S = 2.0  # two windows of 2 s, 0.5 s apart, end 2.5 s into the motion: a finding by about 3 s
EVERY_S = 0.5
IN_A_ROW = 2
AUTO = -1.0  # npp-deploy's monitor_window default: see window_seconds


def window_seconds(asked: float, robots: UncertaintySet) -> float:
    """The window npp-deploy runs: ``asked`` seconds (0 = none), or for AUTO WINDOW_S where the set's robots read
    exact states and none where the set declares noise on the reads. That noise sits in the states the fit
    regresses on and biases it while a policy holds the robot still; the intervals do not widen to say so, and
    robots of the set are then found outside."""
    if asked != AUTO:
        return asked
    return 0.0 if robots.state_noise > 0 else WINDOW_S


@dataclass(frozen=True)
class WindowVerdict:
    """One window's finding: outside the set or not, and the identification in one line (or why there is none)."""

    end: float  # the window's last time, seconds
    outside: bool
    said: str


def prepare(task: str, seed: int) -> None:
    """Load what a window's fit needs (MuJoCo, SciPy, the task's model) in a fresh worker, ahead of its first window:
    a spawned process's imports take seconds, which the first finding must not wait for."""
    get_task(task).make_plant(seed)


def judge(
    task: str, seed: int, robots_record: str, times: FloatArray, states: FloatArray, commands: FloatArray
) -> WindowVerdict:
    """Identify the set's parameters from one window of motion and say whether the robot lies outside the set."""
    end = float(times[-1]) if len(times) else 0.0
    try:
        found = identify(task, Recording(times, states, commands), UncertaintySet.from_record(robots_record), seed=seed)
    except ValueError as exc:
        return WindowVerdict(end, False, f"no finding: {exc}")
    combos = ", ".join(f"{c.label} {c.value:.3g} [{c.low:.3g}, {c.high:.3g}]" for c in found.combinations)
    said = f"{found.verdict} the set: {combos}; delay {found.delay}"
    if found.reasons:
        said += f" ({'; '.join(found.reasons)})"
    return WindowVerdict(end, found.verdict == "outside", said)


class MotionWindow:
    """The last seconds of (time, state as read, command sent) a deployment saw, and when a window is due.

    A command sent late is no evidence: the robot stepped on the one before it (a ros2_control robot holds the latest
    command), and a fit that reads the late one finds a weaker motor or a longer delay. Each row's lag is the wall
    time its command went out minus the state's stamp; its least over the window is the robot's clock offset and the
    transport's own time, and a row whose lag exceeds that by more than ``late_after`` seconds is left out of the
    window's arrays, as a skipped state is (the fit takes only rows one control step apart)."""

    def __init__(
        self, seconds: float = WINDOW_S, every: float = EVERY_S, in_a_row: int = IN_A_ROW, late_after: float = np.inf
    ) -> None:
        if not (seconds > 0 and every > 0 and in_a_row >= 1 and late_after > 0):
            raise ValueError(
                f"a window needs seconds > 0, every > 0, in_a_row >= 1 and late_after > 0; got {seconds}, {every}, "
                f"{in_a_row}, {late_after}"
            )
        self.seconds, self.every, self.in_a_row, self.late_after = seconds, every, in_a_row, late_after
        self.rows: deque[tuple[float, FloatArray, FloatArray, float]] = deque()
        self.next_due = -np.inf
        self.verdicts: deque[WindowVerdict] = deque(maxlen=in_a_row)
        self.late = 0  # rows the last due window left out: their commands went out late

    def restart(self) -> None:
        """A break in the motion (a stop, a stale spell): windows start afresh after it."""
        self.rows.clear()
        self.verdicts.clear()
        self.next_due = -np.inf

    def add(self, at: float, state: FloatArray, command: FloatArray, sent_at: float | None = None) -> None:
        """A state stamped ``at`` (the robot's clock) and the command sent for it at wall time ``sent_at``."""
        lag = 0.0 if sent_at is None else float(sent_at) - float(at)
        self.rows.append((float(at), np.array(state, dtype=np.float64), np.array(command, dtype=np.float64), lag))
        while self.rows and self.rows[0][0] < at - self.seconds:
            self.rows.popleft()

    def due(self) -> tuple[FloatArray, FloatArray, FloatArray] | None:
        """A full window's arrays when one is due (at most one per ``every`` seconds of motion), else None."""
        if len(self.rows) < 3:
            return None
        first, last = self.rows[0][0], self.rows[-1][0]
        if last - first < 0.95 * self.seconds or last < self.next_due:
            return None
        self.next_due = last + self.every
        least = min(row[3] for row in self.rows)
        timely = [row for row in self.rows if row[3] - least <= self.late_after]
        self.late = len(self.rows) - len(timely)
        times = np.array([row[0] for row in timely])
        return times, np.array([row[1] for row in timely]), np.array([row[2] for row in timely])

    def found(self, verdict: WindowVerdict) -> bool:
        """Take a window's verdict; True when the last ``in_a_row`` windows all found the robot outside."""
        self.verdicts.append(verdict)
        return len(self.verdicts) == self.in_a_row and all(v.outside for v in self.verdicts)
