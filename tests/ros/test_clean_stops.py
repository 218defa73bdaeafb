"""Every way a run stops leaves its nodes' logs clean: no FATAL line, no traceback, no "context is invalid",
no ERROR from npp_ros's own shutdown.

One run folder (npp-run, lqr_2_1, horizon 50, epsilon 300: about 80 episodes to its certificate), three
stops, each start's logs checked before the next one rotates them:

1. Ctrl-C in a terminal, mid-run: SIGINT to the whole process group (npp-run and its four nodes at once,
   while the sim and the policy exchange states and actions), and then npp-run's own SIGINT to each node.
2. The run resumed on the same folder, stopped by npp-run once the certificate is issued (a clean run).
3. A refusal: the same folder started for another plant (seed 1); the supervisor refuses the run file of
   another run, its one ERROR line says why, and npp-run stops the other three.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from domain_coordinator import domain_id

from npp_ros_graph.graph.description import ROLES

pytestmark = pytest.mark.slow

HORIZON = 50
EPSILON = 300.0  # a short run to its certificate (83 episodes): the stops, not the run's length, are the point
MID_RUN_EPISODES = 30  # episodes done before the Ctrl-C: the control loop is busy when it comes
START_TIMEOUT_S = 180.0  # four Python processes importing rclpy and MuJoCo on a shared 2-core machine
RUN_TIMEOUT_S = 600.0
# What a stop must not leave: rclpy's report of a callback that raised, a traceback, a publication into a
# shut-down context, the EventsExecutor's "Exception in 'timers' callback", and any ERROR line.
NOISE = re.compile(r"\[FATAL\]|Traceback|context is invalid|Exception in '|\[ERROR\]")


def npp_run(run_dir: Path, domain: int, *extra: str, out: Path) -> subprocess.Popen[bytes]:
    """npp-run in a process group of its own, as a terminal runs a command: a Ctrl-C reaches the whole group."""
    command = [sys.executable, "-m", "npp_ros_graph.tools.run", "--run-dir", str(run_dir), "--domain-id",
               str(domain), "--horizon", str(HORIZON), "--epsilon", str(EPSILON), *extra]  # fmt: skip
    with out.open("wb") as fh:
        return subprocess.Popen(command, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)


@contextmanager
def ended_at_exit(proc: subprocess.Popen[bytes]) -> Iterator[subprocess.Popen[bytes]]:
    """The run's process group never outlives the test, whatever it asserted."""
    try:
        yield proc
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def wait_until(predicate: Callable[[], bool], timeout: float, what: str) -> None:
    """pytest.fail, not TimeoutError, on timeout: domain_id() takes an OSError for a taken domain and retries."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(0.2)


def episodes_done(run_dir: Path) -> int:
    gaps = run_dir / "gaps.csv"
    return max(len(gaps.read_text().splitlines()) - 1, 0) if gaps.exists() else 0


def noise(run_dir: Path, out: Path) -> dict[str, list[str]]:
    """The lines of each node's log (this start's) and of npp-run's output that a stop must not leave."""
    logs = {role: run_dir / "logs" / f"{role}.log" for role in ROLES} | {"npp-run": out}
    found = {name: [line for line in path.read_text(errors="replace").splitlines() if NOISE.search(line)]
             for name, path in logs.items()}  # fmt: skip
    return {name: lines for name, lines in found.items() if lines}


@pytest.mark.long
def test_ctrl_c_a_certified_run_and_a_refusal_leave_clean_logs(tmp_path: Path, ros_domain: int) -> None:
    run_dir = tmp_path / "run"
    with domain_id() as domain:
        # 1. Ctrl-C in the terminal, mid-run.
        out = tmp_path / "interrupted.out"
        with ended_at_exit(npp_run(run_dir, int(domain), out=out)) as run:
            wait_until(lambda: episodes_done(run_dir) >= MID_RUN_EPISODES, START_TIMEOUT_S, "episodes under way")
            os.killpg(run.pid, signal.SIGINT)
            assert run.wait(RUN_TIMEOUT_S) == 130
        said = out.read_text()
        assert "interrupted; stopping the nodes" in said and "did not stop on SIGINT" not in said, said[-2000:]
        assert noise(run_dir, out) == {}

        # 2. Resumed to its certificate, and stopped by npp-run.
        out = tmp_path / "certified.out"
        with ended_at_exit(npp_run(run_dir, int(domain), out=out)) as run:
            assert run.wait(RUN_TIMEOUT_S) == 0, out.read_text()[-2000:]
        said = out.read_text()
        assert "[certificate] condition (i)" in said and "did not stop on SIGINT" not in said
        assert noise(run_dir, out) == {}

        # 3. Refused: the folder holds another plant's run.
        out = tmp_path / "refused.out"
        with ended_at_exit(npp_run(run_dir, int(domain), "--seed", "1", out=out)) as run:
            assert run.wait(RUN_TIMEOUT_S) == 1, out.read_text()[-2000:]
        said = out.read_text()
        assert "npp-supervisor exited with code 1" in said and "belongs to another run" in said, said[-2000:]
        assert "did not stop on SIGINT" not in said
        left = noise(run_dir, out)
        refusal = left.pop("supervisor", [])
        assert len(refusal) == 1 and "[ERROR]" in refusal[0] and "Algorithm 1 stopped: " in refusal[0], refusal
        assert left == {"npp-run": [line for line in said.splitlines() if "npp-supervisor exited with code 1" in line]}


HANGING_NODE = """
import sys, threading
import npp_ros_graph.runtime.node as runtime
from rclpy.node import Node

class HangsInTeardown(Node):
    def __init__(self):
        super().__init__("npp_hangs_in_teardown")
        self.create_timer(0.1, lambda: print("spinning", flush=True))

    def destroy_node(self):  # a DDS teardown that never returns, as one did under load
        threading.Event().wait()

runtime.TEARDOWN_S = 2.0
sys.exit(runtime.run_node(HangsInTeardown))
"""


def after_one_sigterm(script: str, ready: bytes) -> str:
    """What a node process started from ``script`` says, and that it exits with 0, after one SIGTERM sent once it
    printed ``ready``: all a node gets when npp-run is killed (its parent-death signal)."""
    command = [sys.executable, "-c", script]
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)
    with ended_at_exit(proc):
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == ready
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 0, out.decode()
    return out.decode()


def test_a_node_whose_teardown_hangs_leaves_after_its_grace(ros_domain: int) -> None:
    """One SIGTERM ends a node even when its ROS teardown hangs: run_node leaves after TEARDOWN_S, saying so,
    rather than stay on the domain."""
    out = after_one_sigterm(HANGING_NODE, b"spinning")
    assert "the ROS teardown did not finish within 2 s; leaving without it" in out, out


BLOCKED_NODE = """
import sys, threading
import npp_ros_graph.runtime.node as runtime
from rclpy.node import Node

class BlocksInACallback(Node):
    def __init__(self):
        super().__init__("npp_blocks_in_a_callback")
        self.create_timer(0.1, self.block)

    def block(self):  # a callback that never returns (a deadlock): the spin loop never sees the stop request
        print("blocked", flush=True)
        threading.Event().wait()

runtime.STOP_BOUND_S = 2.0
sys.exit(runtime.run_node(BlocksInACallback))
"""


def test_a_node_whose_callback_never_returns_leaves_after_its_bound(ros_domain: int) -> None:
    """One SIGTERM ends a node whose main thread never comes back to its spin loop: the stop watch leaves
    STOP_BOUND_S after the signal, saying so, rather than stay on the domain."""
    out = after_one_sigterm(BLOCKED_NODE, b"blocked")
    assert "still running 2 s after SIGTERM; leaving without it" in out, out
