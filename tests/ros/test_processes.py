"""npp-run and npp-monitor as users met them: processes that outlive npp-run, a node that refuses to start,
a second npp-run on the same folder or the same domain, and a monitor that waits in silence.

Each npp-run here gets its own ROS_DOMAIN_ID (domain_coordinator), so a graph from one test is never
seen by the next. Waits are generous: the machine may be busy."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from domain_coordinator import domain_id
from graph import alive, children

from npp_ros_graph.graph.description import NODES as GRAPH_NODES
from npp_ros_graph.graph.description import ROLES
from npp_ros_graph.tools.run import SECOND_GRAPH_WINDOW_S

START_TIMEOUT_S = 180.0  # four Python processes importing rclpy and MuJoCo on a shared 2-core machine
GONE_TIMEOUT_S = 30.0  # the children get SIGTERM at once; a loaded machine may take a while to run them
NODES = ROLES  # the graph's four nodes, in the order npp-run starts them


def npp_run(run_dir: Path, domain: int, *extra: str, log: Path, sigint_ignored: bool = False) -> subprocess.Popen[str]:
    """npp-run on its own domain; episodes never certify (tiny epsilon), so it runs until stopped.

    ``sigint_ignored``: started as a script's background job starts it, with SIGINT ignored."""
    command = [
        sys.executable, "-m", "npp_ros_graph.tools.run", "--run-dir", str(run_dir), "--domain-id", str(domain),
        "--horizon", "50", "--epsilon", "0.001", "--max-episodes", "100000", *extra,
    ]  # fmt: skip
    ignore = (lambda: signal.signal(signal.SIGINT, signal.SIG_IGN)) if sigint_ignored else None
    return subprocess.Popen(command, stdout=log.open("w"), stderr=subprocess.STDOUT, text=True, preexec_fn=ignore)


@contextmanager
def stopped_at_exit(proc: subprocess.Popen[str]) -> Iterator[subprocess.Popen[str]]:
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(60)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def wait_until(predicate: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(0.2)


def node_children(parent: int) -> dict[str, int]:
    """The node processes npp-run started: name -> pid."""
    return children(parent, {name: GRAPH_NODES[name].module for name in NODES})


def nodes_up(run_dir: Path, parent: int) -> dict[str, int]:
    """The four children once each has written past npp-run's header line (rclpy up, node created)."""
    children: dict[str, int] = {}

    def up() -> bool:
        children.update(node_children(parent))
        logs = [run_dir / "logs" / f"{name}.log" for name in NODES]
        return len(children) == 4 and all(p.exists() and len(p.read_text().splitlines()) >= 2 for p in logs)

    wait_until(up, START_TIMEOUT_S, "the four nodes to start")
    return children


# ----------------------------------------------------------------------------- 1. children die with npp-run
# SIGHUP takes the same path as SIGTERM (npp-run forwards both): it runs with the long tests.
@pytest.mark.parametrize(
    "signum", [signal.SIGKILL, pytest.param(signal.SIGHUP, marks=pytest.mark.long), signal.SIGTERM]
)
def test_nodes_die_with_npp_run(tmp_path: Path, ros_domain: int, signum: signal.Signals) -> None:
    run_dir, out = tmp_path / "run", tmp_path / "npp-run.out"
    with domain_id() as domain, stopped_at_exit(npp_run(run_dir, int(domain), log=out)) as run:
        children = nodes_up(run_dir, run.pid)
        os.kill(run.pid, signum)
        code = run.wait(60)
        start = time.monotonic()
        all_end(children, "the nodes to end")
        print(f"\n{signum.name}: npp-run exited {code}; its 4 nodes gone {time.monotonic() - start:.1f} s later")
    assert code == -signum if signum == signal.SIGKILL else code == 128 + signum
    if signum != signal.SIGKILL:
        assert f"{signum.name} received; stopping the nodes" in out.read_text()


def test_sigint_stops_npp_run_started_with_sigint_ignored(tmp_path: Path, ros_domain: int) -> None:
    """A script's background job starts npp-run with SIGINT ignored; Ctrl-C or kill -INT still stops it all."""
    run_dir, out = tmp_path / "run", tmp_path / "npp-run.out"
    with domain_id() as domain, stopped_at_exit(npp_run(run_dir, int(domain), log=out, sigint_ignored=True)) as run:
        children = nodes_up(run_dir, run.pid)
        run.send_signal(signal.SIGINT)
        code = run.wait(120)
        all_end(children, "the nodes to end")
    assert code == 130
    assert "interrupted; stopping the nodes" in out.read_text()


def test_recorder_and_dashboard_die_with_a_killed_npp_run(tmp_path: Path, ros_domain: int) -> None:
    """npp-run --record --dashboard, SIGKILLed: the recorder and the dashboard end with the nodes."""
    run_dir, out = tmp_path / "run", tmp_path / "npp-run.out"
    with domain_id() as domain, stopped_at_exit(npp_run(run_dir, int(domain), "--record", "--dashboard", "0",
                                                        log=out)) as run:  # fmt: skip
        children = nodes_up(run_dir, run.pid)
        extras = {name: pid for name, pid in tool_children(run.pid).items()}
        assert set(extras) == {"record", "dashboard"}, extras
        os.kill(run.pid, signal.SIGKILL)
        run.wait(60)
        everyone = {**children, **extras}
        all_end(everyone, "every child to end")


def all_end(pids: dict[str, int], what: str) -> None:
    """Waits until every process has ended; never leaves one behind, even when the wait fails."""
    try:
        wait_until(lambda: not any(alive(pid) for pid in pids.values()), GONE_TIMEOUT_S, what)
    finally:
        for pid in pids.values():
            if alive(pid):
                os.kill(pid, signal.SIGKILL)


def tool_children(parent: int) -> dict[str, int]:
    """The recorder and the dashboard npp-run started: name -> pid."""
    return children(parent, {name: f"npp_ros_graph.tools.{name}" for name in ("record", "dashboard")})


# ----------------------------------------------------------------------------- 2. a node that refuses
@pytest.mark.long
def test_a_refusing_node_is_named_with_its_reason_and_each_start_has_its_log(tmp_path: Path, ros_domain: int) -> None:
    """npp-run checks the run's settings before any node starts; what only a node can judge (here, whether the
    task's expert computes an analytic L) is refused by that node, which npp-run names with its reason and log."""
    run_dir = tmp_path / "run"
    with domain_id() as domain:
        first = subprocess.run(
            [sys.executable, "-m", "npp_ros_graph.tools.run", "--run-dir", str(run_dir), "--domain-id",
             str(domain), "--task", "pendulum_swingup", "--lipschitz", "analytic"],
            capture_output=True, text=True, timeout=600,
        )  # fmt: skip
        second = subprocess.run(
            [sys.executable, "-m", "npp_ros_graph.tools.run", "--run-dir", str(run_dir), "--domain-id",
             str(domain), "--task", "cartpole_swingup", "--lipschitz", "analytic", "--epsilon", "130"],
            capture_output=True, text=True, timeout=600,
        )  # fmt: skip
        before = subprocess.run(
            [sys.executable, "-m", "npp_ros_graph.tools.run", "--run-dir", str(run_dir), "--domain-id",
             str(domain), "--epsilon", "-1"],
            capture_output=True, text=True, timeout=600,
        )  # fmt: skip
    print("\n" + first.stderr.strip().splitlines()[-1] + "\n" + second.stderr.strip().splitlines()[-1])
    assert first.returncode == 1 and second.returncode == 1
    for run, task in ((first, "pendulum_swingup"), (second, "cartpole_swingup")):
        assert "npp-run: npp-supervisor exited with code 1" in run.stderr
        assert f"L = 'analytic' is not available for {task}" in run.stderr
        assert f"(log: {run_dir / 'logs' / 'supervisor.log'})" in run.stderr
    # A setting npp-run can judge is refused before any node starts, and no node log is written for it.
    assert before.returncode == 2 and "epsilon must be finite and > 0, got -1.0; not starting" in before.stderr
    # Each start has its own log: the second start's is supervisor.log, the first's is kept as supervisor.1.log.
    logs = run_dir / "logs"
    assert "not available for pendulum_swingup" in (logs / "supervisor.1.log").read_text()
    assert "pendulum_swingup" not in (logs / "supervisor.log").read_text()
    assert "not available for cartpole_swingup" in (logs / "supervisor.log").read_text()
    for name in NODES:
        header = (logs / f"{name}.log").read_text().splitlines()[0]
        assert header.startswith("==== npp-run: this start of the node at ") and ": pid " in header


# ----------------------------------------------------------------------------- 3. a second npp-run
@pytest.mark.long
def test_a_second_npp_run_is_refused_before_starting_nodes(tmp_path: Path, ros_domain: int) -> None:
    run_dir, out = tmp_path / "run", tmp_path / "first.out"
    first_started = time.monotonic()
    with domain_id() as domain, stopped_at_exit(npp_run(run_dir, int(domain), log=out)) as first:
        nodes_up(run_dir, first.pid)
        lock = run_dir / "run.lock"
        wait_until(lambda: lock.exists() and lock.read_text().strip() != "", START_TIMEOUT_S, "the supervisor's lock")
        holder = int(lock.read_text().split()[0])
        sim_log = (run_dir / "logs" / "sim.log").read_text()

        # Same folder, another domain: the folder's writer lock refuses it before any node starts.
        with domain_id() as other:
            started = time.monotonic()
            same_folder = subprocess.run(
                [sys.executable, "-m", "npp_ros_graph.tools.run", "--run-dir", str(run_dir), "--domain-id",
                 str(other), "--horizon", "50"],
                capture_output=True, text=True, timeout=600,
            )  # fmt: skip
            took = time.monotonic() - started
        print(f"\nsame folder ({took:.1f} s): {same_folder.stderr.strip()}")
        assert same_folder.returncode == 2
        assert f"{run_dir} is in use by pid {holder} (" in same_folder.stderr
        assert f"(its npp-run: pid {first.pid}, " in same_folder.stderr
        assert "started sim" not in same_folder.stderr
        assert not (run_dir / "logs" / "sim.1.log").exists()  # no node of the second run ever started
        assert (run_dir / "logs" / "sim.log").read_text().startswith(sim_log)

        # Same domain, another folder: the other graph's sim and supervisor are seen and named. The first run is
        # past the window in which a second graph stops it, so however slow discovery is on a loaded machine
        # (the second may start its nodes before it sees the first, and then stops), the first goes on.
        wait_until(lambda: time.monotonic() - first_started > SECOND_GRAPH_WINDOW_S, 120, "the first run's window")
        started = time.monotonic()
        same_domain = subprocess.run(
            [sys.executable, "-m", "npp_ros_graph.tools.run", "--run-dir", str(tmp_path / "other"), "--domain-id",
             str(domain), "--horizon", "50"],
            capture_output=True, text=True, timeout=600,
        )  # fmt: skip
        took = time.monotonic() - started
        print(f"same domain ({took:.1f} s): {same_domain.stderr.strip().splitlines()[-1]}")
        assert same_domain.returncode == 2
        assert f"another graph is running on ROS_DOMAIN_ID {domain}" in same_domain.stderr
        # Named by whichever of the first graph's sim and supervisor discovery showed within its window.
        assert any(
            f"/npp/{topic} is published by /npp_{node}" in same_domain.stderr
            for topic, node in (("sim/plant", "sim"), ("gap", "supervisor"))
        ), same_domain.stderr
        assert "give this run its own domain (--domain-id N)" in same_domain.stderr
        # The first run goes on untouched.
        assert first.poll() is None, out.read_text()
        first.send_signal(signal.SIGINT)
        assert first.wait(120) == 130
    assert "stopping. Two graphs" not in out.read_text()  # at most a warning, if the second started its nodes


# ----------------------------------------------------------------------------- 4. npp-monitor
def test_monitor_says_what_it_waits_for_and_where(tmp_path: Path, ros_domain: int) -> None:
    err = tmp_path / "monitor.err"
    with domain_id() as empty:
        env = dict(os.environ, ROS_DOMAIN_ID=str(empty))
        monitor = subprocess.Popen(
            [sys.executable, "-m", "npp_ros_graph.tools.monitor"], stdout=subprocess.PIPE, stderr=err.open("w"), env=env
        )
        with stopped_at_exit(monitor):  # type: ignore[arg-type]
            wait_until(lambda: "npp-monitor: nothing received" in err.read_text(), 120, "the monitor's notice")
    line = err.read_text().splitlines()[0]
    print("\n" + line)
    assert f"waiting for /npp/gap, /npp/episode, /npp/certificate on ROS_DOMAIN_ID {empty}, discovery LOCALHOST" in line
    assert "Publishers: /npp/gap 0, /npp/episode 0, /npp/certificate 0" in line
    assert "npp nodes seen: none" in line


def test_monitor_refuses_unknown_topics_naming_the_known_ones() -> None:
    run = subprocess.run(
        [sys.executable, "-m", "npp_ros_graph.tools.monitor", "--topics", "gap,gaps"], capture_output=True, text=True,
        timeout=120,
    )  # fmt: skip
    assert run.returncode == 2
    assert "argument --topics: unknown topic 'gaps'; known: gap, episode" in run.stderr


# ----------------------------------------------------------------------------- 6. a stopped node is named
@pytest.mark.long
def test_a_stopped_node_is_named_within_seconds(tmp_path: Path, ros_domain: int) -> None:
    run_dir, out = tmp_path / "run", tmp_path / "npp-run.out"
    with domain_id() as domain, stopped_at_exit(npp_run(run_dir, int(domain), log=out)) as run:
        supervisor = nodes_up(run_dir, run.pid)["supervisor"]
        wait_until(lambda: "| oracle calls" in out.read_text(), START_TIMEOUT_S, "the first progress line")
        os.kill(supervisor, signal.SIGSTOP)
        stopped = time.monotonic()
        try:
            wait_until(lambda: f"npp-supervisor (pid {supervisor}) is stopped" in out.read_text(), 60, "the notice")
            named_after = time.monotonic() - stopped
            time.sleep(max(0.0, 10.0 - named_after))
        finally:
            os.kill(supervisor, signal.SIGCONT)
        wait_until(lambda: f"npp-supervisor (pid {supervisor}) runs again" in out.read_text(), 60, "the resumption")
        print(f"\nthe stopped supervisor was named {named_after:.1f} s after SIGSTOP")
        assert run.poll() is None
    assert f"(kill -CONT {supervisor} resumes it)" in out.read_text()


def test_a_viewer_whose_ros_teardown_hangs_leaves_on_time_and_says_so() -> None:
    """npp-monitor's guard: a teardown that never returns (here a sleep) does not keep the terminal."""
    code = (
        "import time; from npp_ros_graph.runtime.node import leave_if_teardown_hangs; "
        "leave_if_teardown_hangs('npp-monitor', 0.5, 0); print('certificate shown', flush=True); time.sleep(600)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout == "certificate shown\n"
    assert "npp-monitor: the ROS teardown did not finish within 0.5 s; leaving without it" in done.stderr
