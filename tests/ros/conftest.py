"""Harness for integration tests with real node processes over real DDS.

- Every test session gets its own ROS_DOMAIN_ID (domain_coordinator) and localhost-only discovery,
  set in os.environ so that child processes inherit it: concurrent sessions on one machine never
  see each other's nodes.
- `launch("npp-sim", {"horizon": 20})` starts a node as its own OS process with its output in a
  log file; teardown stops it with SIGINT (then SIGKILL) and prints the log tail if the test failed.
  `launch_module` does the same for processes shared by a whole test module.
- All of a session's nodes share its domain: two graphs alive at once (e.g. a module's shared graph
  and a test's own nodes) must be told apart with a namespace: launch(..., namespace="/iso") and
  ros_client(..., namespace="/iso").
- `ros_client("name")` is an rclpy node in the test process with one persistent executor;
  `wait_for(future_or_predicate, timeout)` drives it with spin_once until done (never
  spin_until_future_complete in a loop, never rclpy.spin_once(node): with the rclpy this project
  installs, both slow down call after call over a long test).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import tomllib
from collections.abc import Callable, Iterator, Mapping
from contextlib import suppress
from pathlib import Path
from typing import IO, Any

import pytest
import rclpy
from domain_coordinator import domain_id
from rclpy.client import Client
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rclpy.task import Future

from npp_ros_graph.transport.topics import SERVICE_QOS

REPO = Path(__file__).resolve().parents[2]
STOP_TIMEOUT_S = 10.0
LOG_TAIL_LINES = 60


def _console_scripts() -> dict[str, str]:
    """npp-sim -> npp_ros_graph.nodes.sim:main, from pyproject (the one source of truth)."""
    with open(REPO / "pyproject.toml", "rb") as fh:
        return dict(tomllib.load(fh)["project"].get("scripts", {}))


CONSOLE_SCRIPTS = _console_scripts()


# --------------------------------------------------------------------------- session: domain, rclpy
@pytest.hookimpl(hookwrapper=True, tryfirst=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Iterator[None]:
    """Remember each phase's report on the item, so teardown knows whether the test failed."""
    outcome = yield
    report = outcome.get_result()
    setattr(item, f"rep_{report.when}", report)


def _test_failed(item: pytest.Item) -> bool:
    return any(getattr(getattr(item, f"rep_{when}", None), "failed", False) for when in ("setup", "call"))


@pytest.fixture(scope="session", autouse=True)
def ros_domain(tmp_path_factory: pytest.TempPathFactory) -> Iterator[int]:
    """A free ROS_DOMAIN_ID for this session, localhost discovery, ROS logs in a temp folder."""
    overrides = {
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "ROS_LOG_DIR": str(tmp_path_factory.mktemp("ros-log")),
        "PYTHONUNBUFFERED": "1",
        SESSION_MARK: f"{os.getpid()}-{time.time_ns()}",
    }
    keys = ["ROS_DOMAIN_ID", "ROS_STATIC_PEERS", *overrides]
    saved = {key: os.environ.get(key) for key in keys}
    with domain_id() as domain:
        os.environ.update(overrides, ROS_DOMAIN_ID=str(domain))
        os.environ.pop("ROS_STATIC_PEERS", None)
        assert_confined(os.environ, int(domain))
        try:
            yield int(domain)
        finally:
            for key, value in saved.items():
                if value is None:
                    os.environ.pop(key, None)
                else:
                    os.environ[key] = value


SESSION_MARK = "NPP_TEST_SESSION"  # in the environment of every process a session starts: what outlives a module
LINGER_S = 20.0  # a module's processes still stopping after its teardown get this long to go


def _session_processes(mark: str) -> dict[int, str]:
    """pid -> command line of every npp_ros process (a node, npp-run, a tool) this session started, still running."""
    needle = f"{SESSION_MARK}={mark}".encode()
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            command = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
            carries_mark = needle in (entry / "environ").read_bytes().split(b"\0")
        except OSError:  # gone, or not ours to read
            continue
        if carries_mark and ("npp_ros_graph" in command or "/npp-" in command):
            found[int(entry.name)] = command
    return found


@pytest.fixture(scope="module", autouse=True)
def no_process_outlives_its_module(ros_domain: int) -> Iterator[None]:
    """A module leaves no node behind: one still running after the module's teardown is another graph on the
    session's domain for every later module (they refuse to start beside it, or take its answers). Each is
    named in this module's teardown error, and killed, so that the modules after it run as they would alone."""
    yield
    mark = os.environ[SESSION_MARK]
    deadline = time.monotonic() + LINGER_S
    left = _session_processes(mark)
    while left and time.monotonic() < deadline:
        time.sleep(0.5)
        left = _session_processes(mark)
    for pid in left:
        with suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    assert not left, "still running after the module's teardown: " + "; ".join(f"pid {p}: {c}" for p, c in left.items())


def assert_confined(env: Mapping[str, str], domain: int) -> None:
    """Every ROS participant a test creates runs on the session's domain with localhost-only discovery."""
    assert env.get("ROS_DOMAIN_ID") == str(domain), f"ROS_DOMAIN_ID {env.get('ROS_DOMAIN_ID')!r}, expected {domain}"
    assert env.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "LOCALHOST", "discovery must stay on this machine"
    assert "ROS_STATIC_PEERS" not in env, "no static peers: nothing outside this machine is contacted"


@pytest.fixture(scope="session")
def ros_context(ros_domain: int) -> Iterator[None]:
    """rclpy.init once per session, after the domain is set (Jazzy: init returns None, no `with`)."""
    assert_confined(os.environ, ros_domain)
    rclpy.init()
    try:
        yield
    finally:
        rclpy.try_shutdown()


# --------------------------------------------------------------------------- node processes
def _ros_value(value: Any) -> str:
    """A Python value as a `-p name:=value` literal that keeps its type."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)  # always has a '.' or an exponent: stays a double
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_ros_value(v) for v in value) + "]"
    return str(value)


def node_command(target: str, params: dict[str, Any] | None = None, namespace: str = "") -> list[str]:
    """The argv that runs a console script (npp-sim) or a module (npp_ros_graph.nodes.sim) with parameters."""
    if target in CONSOLE_SCRIPTS:
        module, func = CONSOLE_SCRIPTS[target].split(":")
        code = f"import sys; sys.argv[0] = {target!r}; from {module} import {func}; sys.exit({func}())"
        cmd = [sys.executable, "-c", code]
    else:
        cmd = [sys.executable, "-m", target]
    if params or namespace:
        cmd.append("--ros-args")
        if namespace:
            cmd += ["-r", f"__ns:={namespace}"]
        for name, value in (params or {}).items():
            cmd += ["-p", f"{name}:={_ros_value(value)}"]
    return cmd


def _default_sigint() -> None:
    """In the child: a pytest run as a background job ignores SIGINT, and children inherit that."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


class Launcher:
    """Starts node processes and stops every one of them, whatever the test did."""

    def __init__(self, log_dir: Path, failed: Callable[[], bool], domain: int) -> None:
        self.log_dir = log_dir
        self.failed = failed
        self.domain = domain
        self.procs: list[tuple[subprocess.Popen[bytes], Path, IO[bytes]]] = []

    def __call__(
        self,
        target: str,
        params: dict[str, Any] | None = None,
        namespace: str = "",
        domain: int | None = None,
        extra_env: dict[str, str] | None = None,
    ) -> subprocess.Popen[bytes]:
        """Start `target` (console script or module); `namespace` isolates it from other graphs, `domain`
        (another free id from domain_coordinator) puts it on another ROS_DOMAIN_ID, still localhost-only;
        `extra_env` adds to the environment (a run's NPP_RUN_KEY)."""
        label = target.rsplit(".", 1)[-1]
        log = self.log_dir / f"{len(self.procs):02d}-{label}.log"
        env = {**os.environ, **(extra_env or {})}
        if domain is not None:
            env["ROS_DOMAIN_ID"] = str(domain)
        assert_confined(env, self.domain if domain is None else domain)
        fh = open(log, "wb")  # closed in stop_all
        proc = subprocess.Popen(
            node_command(target, params, namespace),
            stdout=fh,
            stderr=subprocess.STDOUT,
            cwd=REPO,
            env=env,
            preexec_fn=_default_sigint,
        )
        self.procs.append((proc, log, fh))
        return proc

    def log(self, proc: subprocess.Popen[bytes]) -> str:
        for p, path, _ in self.procs:
            if p is proc:
                return path.read_text(errors="replace")
        raise KeyError(f"process {proc.pid} was not started by this launcher")

    def assert_alive(self, proc: subprocess.Popen[bytes]) -> None:
        if proc.poll() is not None:
            pytest.fail(f"node process {proc.args!r} exited with {proc.returncode}:\n{self._tail(self.log(proc))}")

    def stop(self, proc: subprocess.Popen[bytes], timeout: float = STOP_TIMEOUT_S) -> int:
        """SIGINT (the node's clean shutdown path), then SIGKILL if it does not exit in time."""
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout)
        return proc.returncode

    def stop_all(self) -> None:
        for proc, _, _ in self.procs:
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)  # all at once: they shut down in parallel
        for proc, _, fh in self.procs:
            self.stop(proc)
            fh.close()
        if self.failed():
            for proc, path, _ in self.procs:
                print(f"\n----- {' '.join(map(str, proc.args[-6:]))} (exit {proc.returncode}), log {path}")
                print(self._tail(path.read_text(errors="replace")))

    @staticmethod
    def _tail(text: str) -> str:
        return "\n".join(text.splitlines()[-LOG_TAIL_LINES:])


@pytest.fixture
def launch(ros_domain: int, tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[Launcher]:
    """launch(target, params) -> Popen, one process per call; all stopped at teardown."""
    launcher = Launcher(tmp_path, lambda: _test_failed(request.node), ros_domain)
    try:
        yield launcher
    finally:
        launcher.stop_all()


@pytest.fixture(scope="module")
def launch_module(
    ros_domain: int, tmp_path_factory: pytest.TempPathFactory, request: pytest.FixtureRequest
) -> Iterator[Launcher]:
    """Like `launch`, but the processes live for the whole test module (logs shown if any test failed)."""
    failures_before = request.session.testsfailed
    launcher = Launcher(
        tmp_path_factory.mktemp("nodes"), lambda: request.session.testsfailed > failures_before, ros_domain
    )
    try:
        yield launcher
    finally:
        launcher.stop_all()


# --------------------------------------------------------------------------- client nodes in the test
class RosClient:
    """A node in the test process with its own persistent executor, driven only by wait_for."""

    def __init__(self, name: str, namespace: str = "") -> None:
        self.node: Node = rclpy.create_node(name, namespace=namespace)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)

    def wait_for(self, what: Future | Callable[[], bool], timeout: float = 30.0, label: str = "") -> Any:
        """Spin until the future is done (its result is returned) or the predicate holds."""
        done = what.done if isinstance(what, Future) else what
        deadline = time.monotonic() + timeout
        while not done():
            if time.monotonic() > deadline:
                raise TimeoutError(f"timed out after {timeout:.0f} s waiting for {label or what}")
            self.executor.spin_once(timeout_sec=0.05)
        if isinstance(what, Future):
            return what.result()
        return True

    def client(self, srv_type: Any, name: str, timeout: float = 30.0) -> Client:
        """A service client, returned once the service is reachable.

        Its response queue is as deep as the services' request queue: with the default (KEEP_LAST 10), a
        client with more than 10 requests in flight that is slow to spin loses responses silently.
        """
        client = self.node.create_client(srv_type, name, qos_profile=SERVICE_QOS)
        self.wait_for(client.service_is_ready, timeout, f"service {client.srv_name}")
        return client

    def call(self, client: Client, request: Any, timeout: float = 30.0, attempt_timeout: float = 5.0) -> Any:
        """Call and wait; re-send if no answer comes within attempt_timeout (for idempotent requests).

        Fast DDS drops a response whose reader the server has not matched yet ("failed to send
        response (timeout)"), which happens to a fresh client's first requests under load.
        """
        deadline = time.monotonic() + timeout
        while True:
            future = client.call_async(request)
            attempt = min(attempt_timeout, max(deadline - time.monotonic(), 0.0))
            try:
                return self.wait_for(future, attempt, f"a response from {client.srv_name}")
            except TimeoutError:
                client.remove_pending_request(future)
                if time.monotonic() >= deadline:
                    raise TimeoutError(f"no response from {client.srv_name} within {timeout:.0f} s") from None

    def collect(self, msg_type: Any, topic: str, qos: QoSProfile) -> list[Any]:
        """Subscribe and return the list every arriving message is appended to."""
        inbox: list[Any] = []
        self.node.create_subscription(msg_type, topic, inbox.append, qos)
        return inbox

    def close(self) -> None:
        self.executor.remove_node(self.node)
        self.node.destroy_node()
        self.executor.shutdown()


def _client_factory() -> tuple[Callable[..., RosClient], Callable[[], None]]:
    clients: list[RosClient] = []

    def make(name: str = "test_client", namespace: str = "") -> RosClient:
        clients.append(RosClient(name, namespace))
        return clients[-1]

    def close_all() -> None:
        for client in clients:
            client.close()

    return make, close_all


@pytest.fixture
def ros_client(ros_context: None) -> Iterator[Callable[..., RosClient]]:
    """Factory of RosClient nodes, make(name, namespace=""); all destroyed at teardown."""
    make, close_all = _client_factory()
    try:
        yield make
    finally:
        close_all()


@pytest.fixture(scope="module")
def ros_client_module(ros_context: None) -> Iterator[Callable[..., RosClient]]:
    """Like `ros_client` for clients shared by a test module: discovery is paid once, not per test."""
    make, close_all = _client_factory()
    try:
        yield make
    finally:
        close_all()


def pytest_configure(config: pytest.Config) -> None:
    # rclpy's type support imports lark, which imports the deprecated sre_* modules: not ours to fix.
    for module in ("sre_parse", "sre_constants"):
        config.addinivalue_line("filterwarnings", f"ignore:module '{module}' is deprecated:DeprecationWarning")
