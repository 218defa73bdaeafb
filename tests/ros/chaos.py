"""Faults at random moments for whole runs started with npp-run: a plan drawn from a seed, applied while
the run goes on, and what each fault cost.

A fault is one of:
- ``pause``: SIGSTOP of one node (sim, policy, expert or supervisor) for 5-90 s, then SIGCONT, as a
  debugger, Ctrl-Z or an overloaded host does;
- ``kill``: SIGKILL of one node; npp-run then stops the others and exits, and is started again on the
  same folder (the run resumes);
- ``kill-run``: SIGKILL of npp-run itself (its nodes follow it, by their parent-death signal), then
  npp-run started again.

Each fault comes a random 0-20 s after the run (re)started or the previous fault ended, start-up
included. The harness watches /npp/gap to time every recovery, and reads each start's expert log
before the next start replaces it, to count what the expert computed.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from graph import alive, children, node_modules

NODES = tuple(node_modules())  # sim, expert, policy, supervisor
KINDS = ("pause", "pause", "kill", "kill-run")  # pauses twice as often: they are what a busy host does
PAUSE_S = (5.0, 90.0)
GAP_S = (0.0, 20.0)
COMPUTED = re.compile(r"computed a trajectory from s0 ([0-9a-f]{12})")


@dataclass(frozen=True)
class Fault:
    after: float  # seconds after the run (re)started or the previous fault ended
    kind: str  # pause, kill or kill-run
    node: str  # the node it hits ("npp-run" for kill-run)
    seconds: float = 0.0  # how long a pause lasts

    def __str__(self) -> str:
        what = f"{self.kind} {self.node}" + (f" for {self.seconds:.0f} s" if self.kind == "pause" else "")
        return f"+{self.after:.1f} s: {what}"


def plan(rng: np.random.Generator, count: int) -> list[Fault]:
    """`count` faults at random moments, kinds and nodes."""
    faults = []
    for _ in range(count):
        kind = str(rng.choice(KINDS))
        node = "npp-run" if kind == "kill-run" else str(rng.choice(NODES))
        seconds = float(rng.uniform(*PAUSE_S)) if kind == "pause" else 0.0
        faults.append(Fault(float(rng.uniform(*GAP_S)), kind, node, seconds))
    return faults


@dataclass
class Outcome:
    """What the faults of one run cost."""

    faults: list[Fault]
    applied: list[str] = field(default_factory=list)  # each fault as it happened, with its recovery time
    recoveries: dict[str, list[float]] = field(default_factory=lambda: {"pause": [], "restart": []})
    computed: list[str] = field(default_factory=list)  # s0 digests of every trajectory the expert computed
    restarts_at: list[int] = field(default_factory=list)  # len(computed) when npp-run was started again
    starts: int = 0
    seconds: float = 0.0


class ChaosRun:
    """One npp-run run of lqr_2_1 at horizon `horizon` in `run_dir`, with `faults` applied as it goes.

    ``spin(seconds)`` must keep the test's ROS client spinning for that long (it collects /npp/gap);
    ``episodes()`` returns the arrival times of the gap reports collected so far.
    """

    def __init__(
        self,
        run_dir: Path,
        horizon: int,
        faults: list[Fault],
        spin: Callable[[float], None],
        arrivals: Callable[[], list[float]],
        say: Callable[[str], None] = print,
    ) -> None:
        self.run_dir, self.horizon, self.faults = run_dir, horizon, faults
        self.spin, self.arrivals, self.say = spin, arrivals, say
        self.proc: subprocess.Popen[bytes] | None = None
        self.outcome = Outcome(faults)
        self._log_read = False  # whether this start's expert log has been counted

    # ------------------------------------------------------------------ npp-run
    def _start(self) -> float:
        """Start npp-run; while the nodes of the last start still linger on the domain (a killed node's
        participant stays until its lease ends) it refuses, and is started again. The start's time."""
        cmd = [sys.executable, "-m", "npp_ros_graph.tools.run", "--task", "lqr_2_1", "--seed", "0",
               "--horizon", str(self.horizon), "--run-dir", str(self.run_dir), "--max-episodes", "1000"]  # fmt: skip
        while True:
            out = open(self.run_dir.parent / f"{self.run_dir.name}-npp-run.out", "ab")
            self.proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT)
            out.close()
            self._log_read = False
            started = time.monotonic()
            self.outcome.starts += 1
            self.spin(12.0 if self.outcome.starts > 1 else 0.0)
            if self.proc.poll() != 2:  # 2: another graph still on the domain, or the folder still held
                return started
            self.say("  npp-run refused to start beside the last start's nodes; starting it again")

    def _children(self) -> dict[str, int]:
        assert self.proc is not None
        return children(self.proc.pid, node_modules())

    def _wait_until_down(self, pids: dict[str, int], limit: float = 180.0) -> None:
        """Until npp-run and the nodes of its start have exited. The limit is generous (a loaded
        machine slows a shutdown down); a process still there after it hangs, and the failure says
        which, in what kernel state, and what its log said last."""
        assert self.proc is not None
        deadline = time.monotonic() + limit
        while time.monotonic() < deadline:
            running = {name: pid for name, pid in pids.items() if alive(pid)}
            if self.proc.poll() is not None and not running:
                break
            self.spin(0.2)
        else:
            lingering = {"npp-run": self.proc.pid} if self.proc.poll() is None else {}
            lingering.update(running)
            raise AssertionError(
                f"npp-run or its nodes did not exit within {limit:g} s of the fault:\n"
                + "\n".join(self._describe(name, pid) for name, pid in lingering.items())
            )
        self._read_expert_log()
        self.outcome.restarts_at.append(len(self.outcome.computed))

    def _describe(self, name: str, pid: int) -> str:
        """A lingering process: its kernel state and wait channel, and the last lines of its log."""
        proc = Path(f"/proc/{pid}")
        try:
            state = next(line for line in (proc / "status").read_text().splitlines() if line.startswith("State:"))
            wchan = (proc / "wchan").read_text().strip() or "-"
            threads = len(list((proc / "task").iterdir()))
        except (OSError, StopIteration):
            return f"  {name} (pid {pid}): gone while described"
        log = self.run_dir / "logs" / f"{name}.log"
        tail = log.read_text(errors="replace").splitlines()[-5:] if log.exists() else ["(no log)"]
        lines = "\n".join(f"      {line}" for line in tail)
        state = state.split(":", 1)[1].strip()
        return f"  {name} (pid {pid}): {state}, wchan {wchan}, {threads} threads; log ends:\n{lines}"

    def _read_expert_log(self) -> None:
        """Once per start of npp-run, after it ended: the next start replaces the log."""
        log = self.run_dir / "logs" / "expert.log"
        if log.exists() and not self._log_read:
            self.outcome.computed += COMPUTED.findall(log.read_text(errors="replace"))
        self._log_read = True

    # ------------------------------------------------------------------ the run
    def run(self, limit: float = 1800.0) -> Outcome:
        began = time.monotonic()
        self._start()
        for fault in self.faults:
            self.spin(fault.after)
            assert self.proc is not None
            if self.proc.poll() is not None:
                self.outcome.applied.append(f"{fault}: not applied, the run had ended")
                continue
            pids = self._children()
            deadline = time.monotonic() + 30.0
            while fault.node != "npp-run" and fault.node not in pids and time.monotonic() < deadline:
                self.spin(0.05)  # start-up: npp-run has not started that node yet; hit it as soon as it runs
                pids = self._children()
            if fault.node != "npp-run" and fault.node not in pids:
                self.outcome.applied.append(f"{fault}: not applied, npp-{fault.node} did not start")
                continue
            if fault.kind == "pause":
                self._pause(fault, pids[fault.node])
            else:
                self._kill(fault, pids)
        assert self.proc is not None
        deadline = time.monotonic() + limit
        while self.proc.poll() is None and time.monotonic() < deadline:
            self.spin(0.5)
        if self.proc.poll() is None:
            self.proc.kill()
            raise AssertionError(f"the run did not end within {limit:g} s after its last fault")
        self.spin(0.5)
        self._read_expert_log()
        self.outcome.seconds = time.monotonic() - began
        return self.outcome

    def _pause(self, fault: Fault, pid: int) -> None:
        os.kill(pid, signal.SIGSTOP)
        self.spin(fault.seconds)
        try:
            os.kill(pid, signal.SIGCONT)
        except ProcessLookupError:  # the run certified without it meanwhile, and npp-run ended the stopped node
            self.outcome.applied.append(f"{fault}: the run ended during the pause")
            return
        self._recovered(fault, "pause", time.monotonic(), "SIGCONT")

    def _kill(self, fault: Fault, pids: dict[str, int]) -> None:
        assert self.proc is not None
        if fault.kind == "kill-run":
            self.proc.kill()
        else:
            os.kill(pids[fault.node], signal.SIGKILL)
        self._wait_until_down(pids)
        if self.proc.returncode == 0:  # it had certified just before the fault
            self.outcome.applied.append(f"{fault}: the run had just ended")
            return
        self._recovered(fault, "restart", self._start(), "npp-run started again")

    def _recovered(self, fault: Fault, kind: str, moment: float, what: str) -> None:
        """How long after `moment` (SIGCONT, a restart) the next episode came: in the report and the recoveries."""
        waited = self._next_episode_after(moment)
        self.outcome.applied.append(f"{fault}: next episode {_seconds(waited)} after {what}")
        if waited is not None:
            self.outcome.recoveries[kind].append(waited)

    def _next_episode_after(self, moment: float, limit: float = 600.0) -> float | None:
        """Seconds from `moment` to the first gap report after it (None: the run ended first)."""
        assert self.proc is not None
        deadline = moment + limit
        while time.monotonic() < deadline:
            later = [t for t in self.arrivals() if t > moment]
            if later:
                return min(later) - moment
            if self.proc.poll() is not None:
                return None
            self.spin(0.1)
        raise AssertionError(f"no episode within {limit:g} s")


def _seconds(value: float | None) -> str:
    return "- (the run ended)" if value is None else f"{value:.1f} s"
