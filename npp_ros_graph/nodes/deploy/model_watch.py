"""The model monitor in npp-deploy, for a run certified on a set of robots: after each command went out, the transition
into the state is checked against the set's corners (npp_ros.deployment.model_monitor), and the robot's latest seconds
of motion are fitted by identification in a worker process (npp_ros.identification.window: a fit never holds up a
command). A robot found outside the set is latched on the node's DeploymentState and, as the operator chose
(on_model_mismatch), stops the node or is warned about."""

from __future__ import annotations

import multiprocessing
import time
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor

import numpy as np
from rclpy.impl.rcutils_logger import RcutilsLogger

from npp_ros.deployment.model_monitor import ModelMonitor
from npp_ros.deployment.state import DeploymentState, StopReason
from npp_ros.identification.window import MotionWindow, WindowVerdict, judge, prepare
from npp_ros.run.read import RunMetadata
from npp_ros_graph.runtime.node import ThrottledWarnings

LATE_SHARE = 0.5  # of a control step: a command whose lag exceeds the window's least by this is left out of it


class ModelWatch:
    """What watches the robot's model while the node commands it: the transition check, the motion window, the
    window fits' worker and the fit under way, and what the last window said. Configured with the run (a run on the
    exact model has neither monitor nor window: nothing is watched), released with it.

    It gets what it uses: the node's DeploymentState (what it finds is latched there; whether the node commands), its
    logger and throttled warnings, and two of the node's actions: publish /diagnostics, and deactivate.
    """

    def __init__(
        self,
        state: DeploymentState,
        *,
        logger: RcutilsLogger,
        warn: ThrottledWarnings,
        publish: Callable[[], None],
        deactivate: Callable[[], object],
    ) -> None:
        self.state, self.logger, self.warn, self.publish, self.deactivate = state, logger, warn, publish, deactivate
        self.monitor: ModelMonitor | None = None  # a run certified on a set of robots: its transitions are watched
        self.on_mismatch = "stop"  # on_model_mismatch, as configured
        # The window identification (npp_ros.identification.window): its motion, its worker and the fit under way.
        self.window: MotionWindow | None = None
        self._run: tuple[str, int, str] | None = None  # the run's task, seed and set of robots, as a fit takes them
        self._judges: ProcessPoolExecutor | None = None
        self._judging: Future[WindowVerdict] | None = None
        self.said = ""  # what the last window's fit found, in words
        self._arrival = -1  # the arrival count of the last state the monitor took
        self._target_moved = False  # a new target since the monitor's last state: its chain starts again

    def configure(
        self, monitor: ModelMonitor | None, seconds: float, dt: float, metadata: RunMetadata, on_mismatch: str
    ) -> None:
        """A configured run: its ``monitor`` (None on the exact model) and, with one, a window of ``seconds`` of
        motion (none for 0) for a plant stepping every ``dt`` seconds; ``on_mismatch`` is what a finding does."""
        self.monitor, self.on_mismatch = monitor, on_mismatch
        late_after = LATE_SHARE * dt  # a command later than this missed the robot's step it answers
        self.window = MotionWindow(seconds, late_after=late_after) if monitor is not None and seconds > 0 else None
        if self.window is not None:  # the fits' worker started and loaded now, not at the first window
            self._run = (str(metadata.task), int(metadata.seed), str(metadata.uncertainty))
            self._window_judges().submit(prepare, *self._run[:2])

    def activated(self) -> None:
        """A new activation: the transitions and the window start afresh."""
        self._arrival = -1
        if self.monitor is not None:
            self.monitor.reset()
        if self.window is not None:
            self.window.restart()

    def cleared(self) -> None:
        """The operator cleared the finding: a new window, so the finding cleared is not found again from the same
        transitions."""
        if self.monitor is not None:
            self.monitor.reset()

    def target_moved(self) -> None:
        """A new target: the target moves between two states, which no transition of the model does."""
        self._target_moved = True

    def released(self) -> None:
        """The run let go: nothing watched, the worker shut down."""
        self.monitor, self.window, self._run, self._judging, self.said = None, None, None, None, ""
        self.close()

    def close(self) -> None:
        """The worker shut down, a fit under way given up (the node is released or destroyed)."""
        if self._judges is not None:
            self._judges.shutdown(wait=False, cancel_futures=True)
            self._judges = None

    def values(self) -> dict[str, object]:
        """What the monitor and the last window say, as /diagnostics names them."""
        values: dict[str, object] = {}
        if self.monitor is not None:
            values["model monitor"] = self.monitor.summary()
        if self.said:
            values["window identification"] = self.said
        return values

    def after_command(self, raw: np.ndarray, action: np.ndarray, resumed: bool, stamp: float) -> None:
        """After the command went out: check the transition into this state against the certified set, and the
        latest seconds of motion by identification (in a worker: a fit never holds up a command)."""
        monitor = self.monitor
        if monitor is None:
            return
        arrived = self.state.arrived_since_activation
        if resumed or arrived != self._arrival + 1 or self._target_moved:
            # A state skipped (overtaken, refused), a stale spell or a new target: no one-step transition
            monitor.restart()
        if self.window is not None and (resumed or self._target_moved):
            # After a stale spell (the safe command went out, unrecorded) or a new target the window starts afresh;
            # a skipped state alone does not: the fit takes only rows one control step apart by their stamps.
            self.window.restart()
        self._arrival, self._target_moved = arrived, False
        self._watch_window(raw, action, stamp)
        was_outside = monitor.outside
        monitor.observe(raw, action)
        if not monitor.outside:
            return
        problem = f"the robot's transitions leave the certified set of robots: {monitor.summary()}"
        self._mismatch(problem, newly=self.state.mismatch_found(problem) and not was_outside)

    def _watch_window(self, raw: np.ndarray, action: np.ndarray, stamp: float) -> None:
        """Feed the motion window; take a finished fit's verdict; hand the next due window to the worker."""
        window, run = self.window, self._run
        if window is None or run is None:
            return
        window.add(stamp, raw, action, time.time())  # sent just now: the wall clock the robot's stamps follow
        judging = self._judging
        if judging is not None and judging.done():
            self._judging = None
            try:
                verdict = judging.result()
            except Exception as exc:  # a worker that died or a fit that failed: said, and the window goes on
                self.warn("window identification", f"a window's identification failed: {type(exc).__name__}: {exc}")
            else:
                late = f"; late commands left out: {window.late}" if window.late else ""
                self.said = f"last window (ending {verdict.end:.2f} s{late}): {verdict.said}"
                if window.found(verdict):
                    problem = (
                        f"the robot identified from its last {window.in_a_row} windows of {window.seconds:g} s of "
                        f"motion lies outside the certified set of robots: {verdict.said}"
                    )
                    self._mismatch(problem, newly=self.state.mismatch_found(problem))
                    return
        due = window.due() if self._judging is None else None
        if due is None:
            return
        self._judging = self._window_judges().submit(judge, *run, *due)

    def _window_judges(self) -> ProcessPoolExecutor:
        """The window fits' worker: spawned, not forked, a process of its own apart from the ROS context."""
        if self._judges is None:
            self._judges = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"))
        return self._judges

    def _mismatch(self, problem: str, *, newly: bool) -> None:
        """The robot was found outside the certified set (by either monitor): stop or warn, as the operator chose."""
        if self.on_mismatch == "stop" and self.state.commanding:
            self.logger.error(f"{problem}; on_model_mismatch is stop: deactivating")
            self.state.stop_requested(StopReason.MODEL_MISMATCH)
            self.deactivate()
            return
        self.warn("model mismatch", problem)
        if newly:  # said on /diagnostics when found, not at its next status a second later
            self.publish()
