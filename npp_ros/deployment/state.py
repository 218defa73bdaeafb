"""What npp-deploy is doing and has done, as one typed record: its lifecycle state, the last event, its counters,
why it stopped, and the timing of its answers and of the robot's states.

npp-deploy (npp_ros_graph/nodes/deploy/node.py) holds one :class:`DeploymentState` and changes it only through its
methods, each one thing that happened (a state refused, a command sent, the watchdog's expiry, a stop), so
that what /diagnostics shows follows from what happened and is tested here without ROS. A stop comes with its
:class:`StopReason`, whose kind (not its words) decides the level while the node is inactive.
:meth:`DeploymentState.status` is the node's status in words and its level, which /diagnostics publishes
(npp_ros_graph/runtime/diagnostics.py); the values keep the names operators and npp-deploy-ctl read.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from enum import Enum, IntEnum
from typing import Literal

from npp_ros.deployment.timing import percentiles

Lifecycle = Literal["unconfigured", "inactive", "active", "finalized"]

LATENCY_WINDOW = 1000  # the latency and state-period percentiles are over this many latest ones
RECENT_S = 1.0  # a refusal this recent makes an active node's status WARN


class StopReason(Enum):
    """Why npp-deploy stopped commanding: its words (what the log and /diagnostics show, with the time and the safe
    command) and whether the node stopped by itself, on a finding of its own. Such a stop is WARN while the node is
    inactive, until the next configure or activate; a stop the operator or the process asked for is not."""

    DEACTIVATED = ("deactivated", False)  # the operator's deactivate (a lifecycle transition nobody gave a reason for)
    STOP_REQUESTED = ("stop requested", False)  # the operator's stop service
    OUTSIDE_COVERAGE = ("stopped outside the certificate's coverage (stop_outside_coverage)", True)
    MODEL_CHANGED = ("the robot's model changed", True)
    MODEL_MISMATCH = ("the robot's transitions left the certified set of robots (on_model_mismatch stop)", True)
    SHUTDOWN = ("shutting down", False)  # the lifecycle's shutdown
    ERROR = ("error", False)  # the lifecycle's error processing
    SIGINT = ("SIGINT", False)  # the process stops on a signal (Ctrl-C), or
    SIGTERM = ("SIGTERM", False)
    EXITING = ("exiting", False)  # for any other reason, the node torn down while commanding

    def __init__(self, words: str, by_itself: bool) -> None:
        self.words = words
        self.by_itself = by_itself


def _reason(why: StopReason) -> StopReason:
    """``why``, checked: a reason in free text would decide no level."""
    if not isinstance(why, StopReason):
        raise TypeError(f"a stop's reason is a StopReason, not {type(why).__name__} {why!r}")
    return why


class Level(IntEnum):
    """A status's level, with diagnostic_msgs/DiagnosticStatus's numbers (OK 0, WARN 1, ERROR 2)."""

    OK = 0
    WARN = 1
    ERROR = 2


def wall_time(at: float | None = None) -> str:
    """A wall-clock time as /diagnostics shows it: 2026-11-25 14:03:22.512 UTC."""
    at = time.time() if at is None else at
    return time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(at)) + f".{int(at % 1 * 1000):03d} UTC"


@dataclass(frozen=True)
class Event:
    """The last thing that happened to the deployment, and when (wall-clock, as /diagnostics shows it)."""

    what: str
    at: str


@dataclass
class Counters:
    """What npp-deploy counts, since it started; each field is one /diagnostics value (its name with spaces)."""

    answered: int = 0  # fresh commands sent in answer to a joint state
    refused_states: int = 0
    overtaken_states: int = 0  # states a newer one overtook before they were answered
    repeated_stamps: int = 0  # states repeating the last answered stamp, not answered twice
    clamped_entries: int = 0  # command entries clamped to the actuator limits
    outside_coverage: int = 0  # states farther from the policy's data than the coverage radius, or non-finite
    watchdog_expiries: int = 0  # safe commands the watchdog sent

    def values(self) -> dict[str, int]:
        return {item.name.replace("_", " "): getattr(self, item.name) for item in fields(self)}


@dataclass
class SinceFresh:
    """States that arrived since the last fresh command and were not answered: what the watchdog's expiry names."""

    refused: int = 0
    repeated: int = 0

    def any(self) -> bool:
        return bool(self.refused or self.repeated)


@dataclass(frozen=True)
class Status:
    """The node's status in words (what /diagnostics publishes): what it does now, its values, the level, and the
    problem behind a WARN ("" for none)."""

    doing: str
    values: Mapping[str, object]
    level: Level = Level.OK
    error: str = ""


@dataclass
class DeploymentState:
    """npp-deploy's state; changed through the methods below, read by :meth:`status` and :meth:`values`."""

    lifecycle: Lifecycle = "unconfigured"
    commanding: bool = False  # active and not stopped: joint states are answered
    refusal: str = ""  # the gate's or a transition's last reason, or a changed model: ERROR until configure passes
    event: Event | None = None
    counters: Counters = field(default_factory=Counters)
    fingerprint: str = ""  # the robot model fingerprint configure checked, and where it came from
    fingerprint_source: str = ""
    stale: str = ""  # while the watchdog has expired: what it found
    stopped_because: str = ""  # why the node last stopped commanding, and when: shown while inactive
    stopped_for: StopReason | None = None  # the same, the reason alone (None: not stopped since configure or activate)
    # What the model monitor found when the robot's transitions first left the certified set: WARN until the operator
    # clears it (or cleans up), however the robot moves after. The robot is the same robot; a quiet spell says
    # nothing of it.
    model_mismatch: str = ""
    stopping_for: StopReason | None = None  # the reason a deactivate now in progress was asked for
    # A task whose state holds a target: the topic it comes from ("" for any other task), the target the policy
    # acts on in words ("" until one is given), and the last target refused (WARN until one is taken again).
    target_topic: str = ""
    target: str = ""
    target_refusal: str = ""
    refused_at: float = -math.inf  # monotonic time of the last refused state
    refused_reason: str = ""
    answered_at: float | None = None  # monotonic time the last fresh command went out, since activation
    arrived_since_activation: int = 0
    last_arrival: float | None = None
    since_fresh: SinceFresh = field(default_factory=SinceFresh)
    latencies: deque[float] = field(default_factory=lambda: deque(maxlen=LATENCY_WINDOW))
    periods: deque[float] = field(default_factory=lambda: deque(maxlen=LATENCY_WINDOW))  # between joint states

    # ------------------------------------------------------------------ what happened
    def note(self, what: str, at: float | None = None) -> None:
        """Remember ``what`` happened now (or at the wall-clock time ``at``): the last event, with its time."""
        self.event = Event(what, wall_time(at))

    def became(self, lifecycle: Lifecycle) -> None:
        self.lifecycle = lifecycle

    def refuse(self, transition: str, reason: str) -> str:
        """A transition refused: ERROR until a configure passes; the refusal in words."""
        self.refusal = f"{transition} refused: {reason}"
        self.note(self.refusal)
        return self.refusal

    def model_changed(self, problem: str) -> None:
        """The robot published another model than configure checked: ERROR until it is configured again."""
        self.refusal = f"robot model changed: {problem}"
        self.note(self.refusal)

    def configured(self, fingerprint: str, source: str) -> None:
        self.fingerprint, self.fingerprint_source = fingerprint, source
        self.refusal = self.stopped_because = ""
        self.stopped_for = None

    def released(self) -> None:
        """The run let go (cleanup, shutdown, error): its target with it."""
        self.fingerprint = self.fingerprint_source = ""
        self.target_topic = self.target = self.target_refusal = ""

    def awaits_target(self, topic: str) -> None:
        """Configured on a task whose state holds a target, which comes on ``topic``: none yet."""
        self.target_topic, self.target, self.target_refusal = topic, "", ""

    def target_taken(self, words: str) -> None:
        """A target the policy acts on from now on, in words."""
        self.target, self.target_refusal = words, ""
        self.note(f"target taken: {words}")

    def target_refused(self, reason: str) -> str:
        """A target refused for ``reason``: the one before (or none) is kept, and WARN says so until another is
        taken; the refusal in words."""
        kept = f"the target kept is {self.target}" if self.target else "there is still no target"
        self.target_refusal = f"target refused: {reason}; {kept}"
        self.note(self.target_refusal)
        return self.target_refusal

    def cleaned_up(self) -> None:
        self.refusal = self.stopped_because = self.model_mismatch = ""
        self.stopped_for = None

    def mismatch_found(self, problem: str) -> bool:
        """The model monitor finds the robot outside the certified set: latched (True when newly found)."""
        if self.model_mismatch:
            return False
        self.model_mismatch = problem
        self.note(problem)
        return True

    def mismatch_cleared(self) -> str:
        """The operator clears the latched finding; what was cleared ('' when there was none)."""
        cleared, self.model_mismatch = self.model_mismatch, ""
        if cleared:
            self.note("the operator cleared the model monitor's finding")
        return cleared

    def activated(self) -> None:
        """A new activation: its timing, arrivals and refusals start afresh (the counters go on)."""
        self.latencies.clear()
        self.periods.clear()
        self.last_arrival = self.answered_at = None
        self.arrived_since_activation = 0
        self.since_fresh = SinceFresh()
        self.refused_at = -math.inf
        self.stale = self.stopped_because = ""
        self.stopped_for = None
        self.commanding = True

    def stop_requested(self, why: StopReason) -> None:
        """A deactivate is about to be asked for, for ``why`` (shown once it is done)."""
        self.stopping_for = _reason(why)

    def deactivating(self) -> StopReason:
        """The reason of the deactivate now in progress (DEACTIVATED when nobody gave one), taken."""
        why, self.stopping_for = self.stopping_for or StopReason.DEACTIVATED, None
        return why

    def stop_commanding(self) -> bool:
        """Commanding stops; whether it was commanding."""
        was, self.commanding = self.commanding, False
        return was

    def stopped(self, why: StopReason, sent: str) -> None:
        """Commanding stopped for ``why``, after ``sent`` (the safe command, in words)."""
        self.stopped_for = _reason(why)
        self.stopped_because = f"{why.words} at {wall_time()}: {sent}"

    def arrived(self, now: float) -> None:
        """A joint state taken at monotonic ``now``: the state period is measured between these, while commanding."""
        if not self.commanding:
            return
        self.arrived_since_activation += 1
        if self.last_arrival is not None:
            self.periods.append(now - self.last_arrival)
        self.last_arrival = now

    def state_refused(self, reason: str, now: float) -> str:
        """A joint state the policy cannot act on, at monotonic ``now``: counted, never fresh; the reason in words."""
        self.counters.refused_states += 1
        self.since_fresh.refused += 1
        self.refused_at, self.refused_reason = now, f"joint state refused: {reason}"
        self.note(self.refused_reason)
        return self.refused_reason

    def overtaken(self, count: int = 1) -> None:
        self.counters.overtaken_states += count

    def repeated_stamp(self) -> None:
        """The same state again: not new, not answered twice."""
        self.counters.repeated_stamps += 1
        self.since_fresh.repeated += 1

    def outside_coverage(self, problem: str) -> None:
        """A state the certificate does not cover: counted and named."""
        self.counters.outside_coverage += 1
        self.note(f"outside the certificate's coverage: {problem}")

    def clamped(self, entries: int) -> None:
        self.counters.clamped_entries += entries

    def answered(self, latency: float, now: float, resumed: bool) -> None:
        """A fresh command went out at monotonic ``now``, ``latency`` seconds after its state was taken."""
        self.counters.answered += 1
        self.latencies.append(latency)
        self.answered_at = now
        self.since_fresh = SinceFresh()
        if resumed:
            self.stale = ""

    def watchdog_expired(self, age: float, timeout: float, sent: str) -> str:
        """No fresh command for ``age`` seconds (``timeout`` the limit) and ``sent`` the safe command: counted; what
        the watchdog found, in words."""
        self.counters.watchdog_expiries += 1
        if self.waiting_for_target:
            what = f"no target received on {self.target_topic} in the {age * 1e3:.0f} ms since activation"
        elif self.answered_at is None:
            what = f"no joint state answered in the {age * 1e3:.0f} ms since activation"
        else:
            what = f"no new joint state for {age * 1e3:.0f} ms"
        refused, repeated = self.since_fresh.refused, self.since_fresh.repeated
        if refused or repeated:
            arrived = [f"{refused} refused (the last: {self.refused_reason})"] if refused else []
            arrived += [f"{repeated} repeated the last answered stamp"] if repeated else []
            what += f"; states arrived but none was usable: {', '.join(arrived)}"
        self.stale = (
            f"{what} (state_timeout {timeout * 1e3:.0f} ms): {sent}; no commanding until usable states flow again"
        )
        return self.stale

    # ------------------------------------------------------------------ what it says
    @property
    def waiting_for_target(self) -> bool:
        """Configured on a task whose state holds a target, and none given yet: no state to act on."""
        return bool(self.target_topic) and not self.target

    @property
    def waiting_for_first_state(self) -> bool:
        """Activated, and the robot has sent no joint state yet."""
        return self.answered_at is None and self.arrived_since_activation == 0

    def values(self) -> dict[str, object]:
        """The counters, the answer time and the state period, and the last event, as /diagnostics names them."""
        values: dict[str, object] = dict(self.counters.values())
        if self.latencies:
            p50, p99 = percentiles(self.latencies)
            values["answer time p50 / p99 (us)"] = f"{p50 * 1e6:.0f} / {p99 * 1e6:.0f}"
        if self.periods:
            p50, p99, most = percentiles(self.periods, (50, 99, 100))
            values["state period p50 / p99 / max (ms)"] = f"{p50 * 1e3:.2f} / {p99 * 1e3:.2f} / {most * 1e3:.2f}"
            values["state periods measured"] = len(self.periods)  # since activation, up to LATENCY_WINDOW
        if self.target_topic:
            values["target"] = self.target or f"none received on {self.target_topic}"
        if self.target_refusal:
            values["target refused"] = self.target_refusal
        if self.event is not None:
            values["last event"], values["last event at"] = self.event.what, self.event.at
        return values

    def status(
        self,
        values: Mapping[str, object],
        *,
        overridden: bool = False,
        watchdog_expired: bool = False,
        model_mismatch: str = "",
        now: float | None = None,
    ) -> Status:
        """What the node does now: ``values`` are shown with it; ``overridden`` (the gate was), ``watchdog_expired``
        and ``model_mismatch`` (the model monitor's finding, latched until the operator clears it) are what the
        node's parts say; ``now`` is monotonic. The last event is among the values, never the level."""
        if self.refusal:
            return Status(self.refusal, values, Level.ERROR)
        if self.commanding:
            return self._commanding_status(values, overridden, watchdog_expired, model_mismatch, now)
        doing = f"{self.lifecycle}: not commanding"
        if self.stopped_because and self.lifecycle == "inactive":
            doing += f" ({self.stopped_because})"
        if model_mismatch:
            return Status(doing, values, Level.WARN, model_mismatch)
        if self.target_refusal:
            return Status(doing, values, Level.WARN, self.target_refusal)
        by_itself = self.stopped_for is not None and self.stopped_for.by_itself
        return Status(doing, values, Level.WARN if by_itself else Level.OK)

    def _commanding_status(
        self, values: Mapping[str, object], overridden: bool, expired: bool, mismatch: str, now: float | None
    ) -> Status:
        level = Level.WARN if overridden else Level.OK
        if self.waiting_for_target:  # no state to act on: the watchdog's safe command is all it sends, as it waits
            doing = f"active: waiting for a target on {self.target_topic}"
            if self.target_refusal:
                return Status(doing, values, Level.WARN, self.target_refusal)
            return Status(doing, values, level)
        if expired:
            if self.waiting_for_first_state:
                return Status("active: waiting for the robot's first joint state", values, level)
            usable = "joint states stopped" if not self.since_fresh.any() else "joint states unusable"
            doing = f"active, {usable}: safe command sent; commanding resumes when usable states flow"
            return Status(doing, values, Level.WARN, self.stale)
        if mismatch:  # latched: said while the robot is commanded at all, whatever its last transitions look like
            doing = "active: commanding the robot, whose transitions leave the certified set of robots"
            return Status(doing, values, Level.WARN, mismatch)
        if self.target_refusal:  # the robot goes on towards the target kept, not the one asked for last
            doing = "active: commanding the robot towards the target kept; the last target given was refused"
            return Status(doing, values, Level.WARN, self.target_refusal)
        recent = (time.monotonic() if now is None else now) - self.refused_at < RECENT_S
        if self.answered_at is None:
            if recent:
                return Status("active: waiting for a usable joint state", values, Level.WARN, self.refused_reason)
            return Status("active: waiting for the robot's first joint state", values, level)
        if recent:
            return Status("active: commanding the robot; some joint states refused", values, Level.WARN,
                          self.refused_reason)  # fmt: skip
        return Status("active: commanding the robot", values, level)
