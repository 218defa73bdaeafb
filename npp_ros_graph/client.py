"""GraphClient: the four-node graph from Python, as npp-run, npp-monitor and npp-dashboard use it.

A script starts a graph (``GraphClient.start``: npp-run with the same options, so the same node
processes, logs, refusals and clean stops) or joins one already running (``GraphClient(domain_id=...)``),
asks its expert for a trajectory, follows the run's gaps, episodes, health and certificate as iterators,
callbacks or non-blocking looks (``latest``, ``done``), and stops it. What it gives is npp_ros's own, to its
iterators and its callbacks alike: the certificate is npp_ros.certificate.certifier.Certificate, a gap report
a GapRecord, an episode an EpisodeOutcome and the plant a PlantRecord (npp_ros.run.records), each converted
from its message once, as it arrives, in npp_ros_graph/transport/convert.py (the module that converts a
bag's messages too). ``start`` returns once the graph's sim describes its plant (latched, sealed under the
run's key).

Why it is shaped so: the client's node spins in a thread of its own (the synchros2 model the nodes
follow, npp_ros_graph/runtime/node.py), so every call here is synchronous with a timeout and safe from
the caller's thread, and nothing waits in a constructor. It has its own rclpy context on its own
domain: closing it never shuts down a context the caller uses. Reports are shown only when they are
this run's (npp_ros_graph/runtime/reports.py): given the run's key, the reports of the run the live
supervisor runs; without it, every report on the domain, which ``mark`` says is not verified. It asks
the expert through the contract an expert of any process serves (npp_ros_graph/transport/expert_api.py),
and checks each answer under the run's seal as the supervisor does.
"""

from __future__ import annotations

import ctypes
import itertools
import os
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from contextlib import suppress
from pathlib import Path
from typing import IO, Any, TypeVar

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from npp_interfaces.msg import Certificate as CertificateMsg
from npp_interfaces.msg import EpisodeResult, GapReport, PlantDescription
from npp_interfaces.srv import ExpertTrajectory
from rclpy.context import Context
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions

from npp_ros.certificate.certifier import Certificate
from npp_ros.policy.dataset import Trajectory
from npp_ros.run.records import EpisodeOutcome, GapRecord, PlantRecord
from npp_ros.run.request import RunRequest
from npp_ros.tasks.sources import short_name
from npp_ros_graph.graph.description import run_options
from npp_ros_graph.graph.npp_run_options import option_names
from npp_ros_graph.runtime.diagnostics import DIAGNOSTICS, DIAGNOSTICS_QOS, Health, health_of
from npp_ros_graph.runtime.node import publishers_of, release
from npp_ros_graph.runtime.reports import RunReports, report_origin, unverified_mark
from npp_ros_graph.transport.convert import (
    certificate_of_run,
    episode_from_msg,
    float64_array,
    gap_from_msg,
    plant_from_msg,
    trajectory_from_response,
)
from npp_ros_graph.transport.expert_api import BUSY, EXPERT_SERVICE, NOT_READY, PLANT_QOS, PLANT_TOPIC, SERVICE_QOS
from npp_ros_graph.transport.message_seal import KEY_ENV, RunSeal, SealError
from npp_ros_graph.transport.topics import CERTIFICATE, EPISODE, GAP, LATCHED_READER_QOS, REPORT_HISTORY_QOS, REPORT_QOS

Message = GapReport | EpisodeResult | CertificateMsg  # a report as the supervisor sends it
Report = GapRecord | EpisodeOutcome | Certificate  # the same, as npp_ros reads it
R = TypeVar("R", GapRecord, EpisodeOutcome)

SPIN_S = 0.2  # the client's thread checks this often whether it is asked to close
KEPT_REPORTS = 10_000  # reports an iterator may still read after they arrived (a run's last 5,000 episodes)
START_TIMEOUT_S = 60.0  # npp-run listens 2 s for another graph, then starts the nodes: well within this
STOP_GRACE_S = 60.0  # npp-run gives each node this long for its ordered teardown (one took over 15 s at load 15-20)
STOP_TIMEOUT_S = STOP_GRACE_S + 15.0  # npp-run's own stop: its nodes' grace, then its own teardown
ATTEMPT_S = 5.0  # an unanswered expert request is sent again (Fast DDS drops a new client's first responses)
START_OPTIONS = ("task", "seed", "run_dir", "domain_id")  # npp-run's options that start() takes by name
LAUNCHER = "npp_ros_graph.tools.run"
_CLIENTS = itertools.count(1)  # numbers the default node names of a process's clients


class GraphError(RuntimeError):
    """The graph refused to start, stopped without what was asked of it, or its expert refused an answer."""


def default_run_dir(task: str, seed: int) -> Path:
    """Where npp-run keeps a run it is given no folder for: runs/graph-TASK-seedSEED."""
    return Path("runs") / f"graph-{short_name(task)}-seed{seed}"


def npp_run_argv(task: str, seed: int, run_dir: Path, domain_id: int | None, options: dict[str, Any]) -> list[str]:
    """npp-run's command line for a run: each option as its flag (horizon=50: --horizon 50; record=True: --record).

    npp-run's own parser reads it, so an unknown option or a bad value is refused as npp-run refuses it.
    """
    argv = [sys.executable, "-m", LAUNCHER, "--task", task, "--seed", str(seed), "--run-dir", str(run_dir)]
    if domain_id is not None:
        argv += ["--domain-id", str(domain_id)]
    for name, value in options.items():
        flag = "--" + name.replace("_", "-")
        if value is True:
            argv.append(flag)
        elif value is not False and value is not None:
            argv += [flag, *(map(str, value) if isinstance(value, (list, tuple)) else [str(value)])]
    return argv


_PR_SET_PDEATHSIG = 1
_prctl: Callable[..., int] | None = None


def _load_prctl() -> None:
    """Loaded in the parent itself: a child between fork and exec must not load libraries."""
    global _prctl
    if _prctl is None and sys.platform.startswith("linux"):
        _prctl = ctypes.CDLL(None, use_errno=True).prctl


def child_setup(parent: int) -> Callable[[], None]:
    """What each child runs before exec: it dies with its parent (npp-run, or a script's GraphClient).

    SIGINT is restored (started from a background job, a child would inherit an ignored SIGINT and
    never stop). PR_SET_PDEATHSIG has the kernel send SIGTERM to the child when the parent dies, even by
    SIGKILL, which no handler can catch; the child turns SIGTERM into a clean shutdown. If the parent
    died before the call, the child is already orphaned and stops itself.
    """
    _load_prctl()

    def setup() -> None:
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        if _prctl is not None:
            _prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
            if os.getppid() != parent:
                os.kill(os.getpid(), signal.SIGTERM)

    return setup


class GraphClient:
    """One run's graph, seen from Python: its reports, health, plant and expert; started here or joined.

    Callbacks (``on_gap`` and the others) run on the client's thread, in arrival order, and must not
    block; iterators (``reports``, ``gaps``, ``episodes``) and the waiting calls run on the caller's.
    """

    def __init__(
        self,
        *,
        domain_id: int | None = None,
        key: str | None = None,
        name: str = "",
        namespace: str = "",
        past_reports: bool = True,
        ros_args: Sequence[str] = (),
    ) -> None:
        """Join the graph on ``domain_id`` (None: ROS_DOMAIN_ID's) and ``namespace``; returns at once.

        ``key``: the run's key (None: NPP_RUN_KEY's; without one, reports are not verified).
        ``past_reports``: also the episodes the supervisor reported before this client joined (it keeps
        its last 1,000); False: new ones only, as npp-monitor prints them.
        ``name``: the client's node name ("": npp_graph_client_PID_N, one of its own for each client).
        ``ros_args``: ROS arguments for the client's node (e.g. ``["--ros-args", "-r", "__ns:=/robot1"]``).
        """
        name = name or f"npp_graph_client_{os.getpid()}_{next(_CLIENTS)}"
        self.seal = RunSeal.from_environment() if key is None else RunSeal.from_environment({KEY_ENV: key})
        self.context = Context()
        rclpy.init(
            args=[name, *ros_args], context=self.context, domain_id=domain_id,
            signal_handler_options=SignalHandlerOptions.NO,  # the caller's signals stay the caller's
        )  # fmt: skip
        self.node = rclpy.create_node(name, namespace=namespace or None, context=self.context)
        self._cond = threading.Condition()
        self._kept: deque[Report] = deque(maxlen=KEPT_REPORTS)
        self._named: dict[int, str] = {}  # the run each kept report names, by the report's id (see ``mark``)
        self._received = 0  # reports received so far; the kept ones are the last len(_kept) of them
        self._certificate: Certificate | None = None
        self._unplanted: CertificateMsg | None = None  # a certificate that came before the plant that names its task
        self._plant: PlantRecord | None = None
        self._health: dict[str, Health] = {}
        self._callbacks: dict[type, list[Callable[[Any], None]]] = {}
        self._notices: list[Callable[[str], None]] = []
        self._process: subprocess.Popen[bytes] | None = None
        self._output: threading.Thread | None = None
        self._last_lines: deque[str] = deque(maxlen=20)  # npp-run's last output, for the reason it gives up
        self.log: Path | None = None  # npp-run's own output, for a graph started here
        self.reports_of_run = RunReports(self.node, self._on_report, self._on_notice, seal=self.seal)
        report_qos = REPORT_HISTORY_QOS if past_reports else REPORT_QOS
        self.node.create_subscription(GapReport, GAP, self.reports_of_run.take, report_qos)
        self.node.create_subscription(EpisodeResult, EPISODE, self.reports_of_run.take, report_qos)
        self.node.create_subscription(CertificateMsg, CERTIFICATE, self.reports_of_run.take, LATCHED_READER_QOS)
        self.node.create_subscription(PlantDescription, PLANT_TOPIC, self._on_plant, PLANT_QOS)
        self.node.create_subscription(DiagnosticArray, DIAGNOSTICS, self._on_diagnostics, DIAGNOSTICS_QOS)
        self._expert = self.node.create_client(ExpertTrajectory, EXPERT_SERVICE, qos_profile=SERVICE_QOS)
        self._closing = threading.Event()
        self._executor = SingleThreadedExecutor(context=self.context)
        self._executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, name=f"{name} executor", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------------- start and stop
    @classmethod
    def start(
        cls,
        task: str | RunRequest = "lqr_2_1",
        *,
        seed: int | None = None,
        run_dir: Path | str | None = None,
        domain_id: int | None = None,
        key: str | None = None,
        timeout: float = START_TIMEOUT_S,
        **options: Any,
    ) -> GraphClient:
        """Start a run's graph with npp-run and follow it; returns once its sim describes its plant.

        ``options`` are npp-run's (horizon=50, epsilon=10, max_episodes=200, policy="open-loop", record=True...);
        a name npp-run does not know is a TypeError, before any process starts.
        ``key``: the run's key, which a client that joins the run needs (None: NPP_RUN_KEY's, else a fresh one
        that only this client and the nodes know). npp-run's own output goes to RUN_DIR/logs/npp-run.log.
        Raises GraphError with npp-run's reason when it refuses (a run folder in use, another graph on the
        domain, a bad option). Like npp-run, it sets ROS_AUTOMATIC_DISCOVERY_RANGE to LOCALHOST where unset.
        """
        takes = option_names() - set(START_OPTIONS)
        unknown = sorted(set(options) - takes)
        if unknown:
            raise TypeError(
                f"GraphClient.start() got options npp-run does not know: {', '.join(unknown)} "
                f"(its options: {', '.join(sorted(takes))})"
            )
        if isinstance(task, RunRequest):  # a whole request: its settings are npp-run's options, under those named
            given = {name: value for name, value in run_options(task).items() if name not in ("task", "seed")}
            options = {**given, **options}
            task, seed = task.task, task.seed if seed is None else seed
        seed = 0 if seed is None else seed
        folder = Path(run_dir) if run_dir is not None else default_run_dir(task, seed)
        folder = folder.resolve()
        key = key or os.environ.get(KEY_ENV) or RunSeal.new_key()
        env = {**os.environ, KEY_ENV: key}
        env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")  # as npp-run starts its nodes
        os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")  # and the client, which joins them
        client = cls(domain_id=domain_id, key=key)
        try:
            client._launch(npp_run_argv(task, seed, folder, domain_id, options), env, folder, timeout)
        except BaseException:
            client.stop()
            raise
        return client

    def _launch(self, argv: list[str], env: dict[str, str], run_dir: Path, timeout: float) -> None:
        (run_dir / "logs").mkdir(parents=True, exist_ok=True)
        self.log = run_dir / "logs" / "npp-run.log"
        self._process = subprocess.Popen(
            argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env, preexec_fn=child_setup(os.getpid())
        )
        self._output = threading.Thread(target=self._copy_output, args=(self._process.stdout, self.log), daemon=True)
        self._output.start()
        # Ready when the graph says so: its sim's latched plant description, under the run's key.
        with self._cond:
            if not self._cond.wait_for(lambda: self._plant is not None or not self.running, timeout):
                raise TimeoutError(f"the graph's sim described no plant within {timeout:g} s (log: {self.log})")
        if not self.running:
            raise GraphError(f"npp-run did not start the graph: {self._reason()} (log: {self.log})")

    def _copy_output(self, stream: IO[bytes], log: Path) -> None:
        """npp-run's output into its log, line by line (its last lines kept for a refusal's reason); notes when
        npp-run ended."""
        with log.open("ab") as out:
            for raw in stream:
                out.write(raw)
                out.flush()
                line = raw.decode(errors="replace").strip()
                if line:
                    self._last_lines.append(line)
        if self._process is not None:
            self._process.wait()
        with self._cond:
            self._cond.notify_all()  # iterators waiting for reports learn that the graph is gone

    def _reason(self) -> str:
        lines = [line for line in self._last_lines if line.startswith("npp-run:")] or list(self._last_lines)
        return lines[-1].removeprefix("npp-run: ") if lines else "no output"

    @property
    def running(self) -> bool:
        """Whether the graph this client started still runs (npp-run stops it once certified); True when joined."""
        return self._process is None or (self._process.poll() is None and not self._output_done())

    def _output_done(self) -> bool:
        return self._output is not None and not self._output.is_alive()

    def stop(self, timeout: float = STOP_TIMEOUT_S) -> int | None:
        """Stop the graph this client started, as Ctrl-C stops npp-run (its nodes in order, the run kept in its
        folder), then close the client; npp-run's exit code (0 once certified), None for a joined graph.

        A joined graph is left running: only the process that started it stops it.
        """
        code = None
        if self._process is not None:
            deadline = time.monotonic() + timeout
            if self._certificate is not None:  # certified: npp-run stops its nodes itself, and a signal would cut it
                with suppress(subprocess.TimeoutExpired):
                    self._process.wait(timeout)
            if self._process.poll() is None:
                self._process.send_signal(signal.SIGINT)
            try:
                code = self._process.wait(max(deadline - time.monotonic(), 1.0))
            except subprocess.TimeoutExpired:
                self._process.kill()
                code = self._process.wait()
            if self._output is not None:
                self._output.join(timeout)
        self.close()
        return code

    def close(self) -> None:
        """Leave the graph: the client's thread ends, then its node and context go (release's order)."""
        if self._closing.is_set():
            return
        self._closing.set()
        self._thread.join()
        release(self._executor, self.node)

    def __enter__(self) -> GraphClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _spin(self) -> None:
        try:
            while self.context.ok() and not self._closing.is_set():
                self._executor.spin_once(timeout_sec=SPIN_S)
        except ExternalShutdownException:
            pass

    # ------------------------------------------------------------------------- callbacks
    # A callback is added on the client's thread, which delivers every record: those received before it was
    # added (the kept reports, the plant) are handed to it first, so that it misses and repeats none.
    def on_gap(self, callback: Callable[[GapRecord], None]) -> None:
        """Call ``callback`` with each of this run's gap reports (one per episode) as a GapRecord, on the client's
        thread: the records ``gaps()`` gives."""
        self._add(GapRecord, callback)

    def on_episode(self, callback: Callable[[EpisodeOutcome], None]) -> None:
        """Call ``callback`` with each of this run's episode outcomes (EpisodeOutcome), on the client's thread."""
        self._add(EpisodeOutcome, callback)

    def on_certificate(self, callback: Callable[[Certificate], None]) -> None:
        """Call ``callback`` with the run's certificate once it is issued, as npp_ros's Certificate (the one
        ``certificate()`` returns), on the client's thread."""
        self._add(Certificate, callback)

    def on_health(self, callback: Callable[[DiagnosticArray], None]) -> None:
        """Call ``callback`` with each /diagnostics message from now on (``health`` holds each node's latest)."""
        self._add(DiagnosticArray, callback)

    def on_plant(self, callback: Callable[[PlantRecord], None]) -> None:
        """Call ``callback`` with the plant the sim describes, as the PlantRecord ``plant()`` returns (this run's
        key's, when the client has a key)."""
        self._add(PlantRecord, callback)

    def on_notice(self, callback: Callable[[str], None]) -> None:
        """Call ``callback`` with a line for each other run whose reports are left out (see runtime/reports.py)."""
        self._notices.append(callback)

    def _add(self, kind: type, callback: Callable[[Any], None]) -> None:
        def add() -> None:
            earlier = [self._plant] if kind is PlantRecord and self._plant is not None else []
            earlier += [report for report in self._kept if isinstance(report, kind)]
            for item in earlier:
                self._deliver(callback, item)
            self._callbacks.setdefault(kind, []).append(callback)

        self._executor.create_task(add)

    def _call(self, item: Any) -> None:
        for callback in list(self._callbacks.get(type(item), ())):
            self._deliver(callback, item)

    def _deliver(self, callback: Callable[[Any], None], item: Any) -> None:
        try:
            callback(item)
        except Exception as exc:  # a caller's bug must not stop the client's thread
            self.node.get_logger().error(f"a {type(item).__name__} callback failed: {type(exc).__name__}: {exc}")

    def _on_report(self, msg: Message) -> None:
        """A report of the run (RunReports): converted once, here, into the record every caller gets."""
        if isinstance(msg, CertificateMsg) and self._plant is None:
            self._unplanted = msg  # its task is the one the plant names: converted once the sim describes it
            return
        try:
            report = self._record(msg)
        except ValueError as exc:  # no report of an npp_ros supervisor: every reader would refuse it
            self.node.get_logger().error(f"a {type(msg).__name__} left out: {exc}")
            return
        origin = report_origin(msg)
        with self._cond:
            if len(self._kept) == self._kept.maxlen:
                self._named.pop(id(self._kept[0]), None)
            self._kept.append(report)
            self._named[id(report)] = origin[1] if origin else ""
            self._received += 1
            if isinstance(report, Certificate):
                self._certificate = report
            self._cond.notify_all()
        self._call(report)

    def _on_notice(self, line: str) -> None:
        for callback in list(self._notices):
            callback(line)

    def _on_plant(self, msg: PlantDescription) -> None:
        if self.seal.private:
            try:
                self.seal.check(msg, "a plant description")
            except SealError:
                return  # another run's plant, under another key
        plant = plant_from_msg(msg)
        with self._cond:
            self._plant = plant
            self._cond.notify_all()
        self._call(plant)
        if self._unplanted is not None:
            certificate, self._unplanted = self._unplanted, None
            self._on_report(certificate)

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        with self._cond:
            for status in msg.status:
                self._health[status.name] = health_of(status)
        self._call(msg)

    # ------------------------------------------------------------------------- the graph around the run
    def every(self, period: float, callback: Callable[[], None]) -> None:
        """Call ``callback`` every ``period`` seconds on the client's thread (it must not block)."""
        self.node.create_timer(period, callback)

    def count_publishers(self, topic: str) -> int:
        """How many publishers of ``topic`` this client sees on its domain."""
        return self.node.count_publishers(topic)

    def publishers_of(self, topic: str) -> str:
        """Who publishes ``topic``, in words (their nodes' names)."""
        return publishers_of(self.node, topic)

    def graph_nodes(self) -> list[tuple[str, str]]:
        """Every node this client sees on its domain: (name, namespace), itself included."""
        return self.node.get_node_names_and_namespaces()

    @property
    def name(self) -> str:
        """The client's own node name."""
        return self.node.get_name()

    @property
    def namespace(self) -> str:
        return self.node.get_namespace()

    # ------------------------------------------------------------------------- what the run says
    @property
    def verified(self) -> bool:
        """Whether reports are checked as this run's (the client has the run's key)."""
        return self.reports_of_run.verified

    def mark(self, report: Report) -> str:
        """What a viewer adds to a report this client gave: "" when verified, else that it is not and the run it
        names (``named_run``)."""
        return "" if self.verified else unverified_mark(self.named_run(report))

    def named_run(self, report: Report) -> str:
        """The identity of the run a report this client gave names in its header ("": none, or a report it no
        longer keeps). Given the run's key, the client gives this run's reports only."""
        with self._cond:
            return self._named.get(id(report), "")

    def health(self) -> dict[str, Health]:
        """Each node's latest health from /diagnostics, by its full name (/npp_sim...)."""
        with self._cond:
            return dict(self._health)

    def plant(self, timeout: float = 30.0) -> PlantRecord:
        """The plant the sim describes (task, seed, horizon, dimensions...), once it is here."""
        return self._wait(lambda: self._plant, timeout, "the sim's plant description")

    def certificate(self, timeout: float = 600.0) -> Certificate:
        """The run's certificate, once issued, as npp_ros's Certificate; GraphError if the graph started here stops
        without one."""
        return self._wait(lambda: self._certificate, timeout, "the certificate")

    def done(self) -> bool:
        """Without waiting: whether the run is over here (certified, or the graph started here has stopped)."""
        with self._cond:
            return self._certificate is not None or not self.running

    def latest(self) -> Report | None:
        """Without waiting: the newest report of the run (a GapRecord, an EpisodeOutcome or the Certificate), or
        None before the first."""
        with self._cond:
            return self._kept[-1] if self._kept else None

    def _record(self, msg: Message) -> Report:
        """A report as npp_ros reads it (transport/convert.py); the certificate for the plant the sim describes."""
        if isinstance(msg, GapReport):
            return gap_from_msg(msg)
        if isinstance(msg, EpisodeResult):
            return episode_from_msg(msg)
        return certificate_of_run(msg, self._plant)

    def reports(self, timeout: float = 120.0) -> Iterator[Report]:
        """This run's reports in arrival order as npp_ros reads them (GapRecords, EpisodeOutcomes, the Certificate
        last), from the first this client kept; ends after the certificate, or when the graph started here has
        stopped.

        TimeoutError when nothing new comes for ``timeout`` seconds while the graph runs.
        """
        seen = 0
        while True:
            with self._cond:
                if not self._cond.wait_for(lambda seen=seen: self._received > seen or not self.running, timeout):
                    raise TimeoutError(f"no report of the run for {timeout:g} s")
                first = self._received - len(self._kept)  # older ones are no longer kept
                new = list(self._kept)[max(seen - first, 0) :]
                seen = self._received
                over = not new and not self.running
            for report in new:
                yield report
                if isinstance(report, Certificate):
                    return
            if over:
                return

    def gaps(self, timeout: float = 120.0) -> Iterator[GapRecord]:
        """This run's gap reports, one per episode (see ``reports``)."""
        return self._only(GapRecord, timeout)

    def episodes(self, timeout: float = 120.0) -> Iterator[EpisodeOutcome]:
        """This run's episode outcomes (see ``reports``)."""
        return self._only(EpisodeOutcome, timeout)

    def _only(self, kind: type[R], timeout: float) -> Iterator[R]:
        return (report for report in self.reports(timeout) if isinstance(report, kind))

    def _wait(self, get: Callable[[], Any], timeout: float, what: str) -> Any:
        with self._cond:
            if not self._cond.wait_for(lambda: get() is not None or not self.running, timeout):
                raise TimeoutError(f"no {what} within {timeout:g} s")
            value = get()
        if value is None:
            raise GraphError(f"the graph stopped without {what}: {self._reason()} (log: {self.log})")
        return value

    # ------------------------------------------------------------------------- the expert
    def ask_expert(self, state: Sequence[float], horizon: int = 0, timeout: float = 60.0) -> Trajectory:
        """The expert's trajectory from ``state`` over ``horizon`` steps (0: the run's horizon).

        The answer is checked like the supervisor checks it: sealed under the run's key for the plant the
        sim describes (GraphError otherwise, or when the expert refuses the request). An expert that is busy
        or not ready yet is asked again until ``timeout``.
        """
        deadline = time.monotonic() + timeout
        if not self._expert.wait_for_service(timeout_sec=timeout):
            raise TimeoutError(f"no expert serves /{EXPERT_SERVICE} within {timeout:g} s")
        request = ExpertTrajectory.Request(state=float64_array(state), horizon=horizon)
        while True:
            response = self._call_expert(request, deadline)
            if response.success or not response.message.startswith((BUSY, NOT_READY)):
                break
            time.sleep(min(0.5, max(deadline - time.monotonic(), 0.0)))
        if not response.success:
            raise GraphError(f"the expert refused the request: {response.message}")
        plant = self._plant
        if plant is not None and response.plant != plant.model_sha256:
            raise GraphError(f"the expert's answer is about another plant ({response.plant[:12]}), not the sim's")
        try:
            self.seal.for_plant(response.plant).check(response, "the expert's answer", answering=request)
        except SealError as exc:
            raise GraphError(str(exc)) from None
        return trajectory_from_response(response)

    def _call_expert(self, request: ExpertTrajectory.Request, deadline: float) -> ExpertTrajectory.Response:
        while True:
            answered = threading.Event()
            future = self._expert.call_async(request)
            future.add_done_callback(lambda _, answered=answered: answered.set())
            left = deadline - time.monotonic()
            if answered.wait(max(min(ATTEMPT_S, left), 0.0)) and future.result() is not None:
                return future.result()
            self._expert.remove_pending_request(future)
            if time.monotonic() >= deadline:
                raise TimeoutError(f"no answer from /{EXPERT_SERVICE} in time")
