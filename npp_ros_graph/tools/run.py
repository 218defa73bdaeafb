"""npp-run: starts sim, expert, policy and supervisor as four processes and follows the run.

Shows live progress from the /npp/gap topic in npp-learn's lines, prints the certificate, and stops all four
cleanly when the run is certified, when it runs out of episodes, on Ctrl-C, SIGTERM or SIGHUP,
or when a node dies (saying which, why, and where its log is); a node whose process is stopped
(SIGSTOP, a debugger) is named within seconds. The nodes die with npp-run even when it is
SIGKILLed. The run folder holds run.sqlite (dataset and episode log), gaps.csv, episodes.csv
and logs/<node>.log (the previous start's log kept as logs/<node>.1.log). Started again on the
same folder, the supervisor resumes the run.

Refused before any node starts: a run folder another writer holds (named with its pid and
command line), and another graph on the same ROS domain (its nodes named); one that appears
within the first seconds after the start stops this run with the same reason.
"""

from __future__ import annotations

import os
import re
import shlex
import signal
import subprocess
import sys
import threading
import time
from contextlib import suppress
from dataclasses import replace
from datetime import datetime
from pathlib import Path
from typing import IO

from diagnostic_msgs.msg import DiagnosticArray

from npp_ros.certificate.certifier import Certificate
from npp_ros.cli.args import run_request
from npp_ros.run.progress import progress_text
from npp_ros.run.records import GapRecord, RunFileError
from npp_ros.run.setup import run_file_notice
from npp_ros.run.store import RUN_FILE
from npp_ros.run.writer_lock import WriterLock
from npp_ros.tasks.registry import get_task
from npp_ros_graph.client import STOP_GRACE_S, GraphClient, child_setup, default_run_dir
from npp_ros_graph.graph.description import node_argv, request_parameters
from npp_ros_graph.graph.npp_run_options import parse_args
from npp_ros_graph.runtime.diagnostics import WARN, health_of
from npp_ros_graph.runtime.node import TEARDOWN_S, UNNAMED, leave_if_teardown_hangs, node_name
from npp_ros_graph.tools.dashboard import start_dashboard
from npp_ros_graph.tools.monitor import certificate_line
from npp_ros_graph.tools.record import start_recorder
from npp_ros_graph.transport.message_seal import KEY_ENV, RunSeal
from npp_ros_graph.transport.topics import GAP, PLANT

DISCOVERY_S = 2.0  # listened for before starting: discovery on one machine takes well under a second
NAMING_S = 5.0  # how long another graph's unnamed publisher is waited for, to be named in the refusal
SECOND_GRAPH_WINDOW_S = 30.0  # a second graph seen this soon after the start stops this run
GRAPH_TOPICS = (PLANT, GAP)  # one publisher each per graph: its sim and its supervisor
LOG_HEADER = "==== npp-run: this start of the node at"
STALL_NOTICE_S = 2.0  # a node stopped this long is named
STOP_NOTICE_S = 5.0  # a stop that takes longer names the node it waits for
TWO_GRAPHS = (
    "Two graphs on one domain answer each other's service calls (their seals keep their data apart, at the cost "
    "of retries): stop the other one, or give this run its own domain (--domain-id N)"
)


class Follower:
    """npp-run's view of its run, through a GraphClient: a progress line per gap report (npp-learn's, of the
    same record), the certificate that ends the run, and what a node waits for or failed at."""

    def __init__(self) -> None:
        self.last: GapRecord | None = None
        self.certificate: Certificate | None = None
        self.certified = threading.Event()
        # Only this run's reports: main() has set the run's key, and the run's supervisor names its run. Its past
        # ones too: the supervisor starts after this client, so every report it keeps is this run's, and one sent
        # before discovery matched this reader would be lost to a volatile one (a short run can end in its first
        # seconds, and npp-run would then wait for its last report forever).
        self.client = GraphClient(name="npp_run", past_reports=True)
        self.client.on_gap(self.on_gap)
        self.client.on_certificate(self.on_certificate)
        self.client.on_health(self.on_health)
        self.client.on_notice(lambda line: say(f"\nnpp-run: {line}"))
        self.tty = sys.stderr.isatty()
        self._printed = 0.0
        self._worried: dict[str, str] = {}  # node -> what it last warned of, while it does

    def on_health(self, msg: DiagnosticArray) -> None:
        """What a node waits for or failed at (/diagnostics WARN or ERROR), once, and when it is over."""
        for status in msg.status:
            health = health_of(status)
            if not status.name.startswith("/npp_"):
                continue
            if health.level >= WARN:
                text = health.doing + (f" (last error: {health.error})" if health.error else "")
                if self._worried.get(status.name) != text:
                    self._worried[status.name] = text
                    say(f"\nnpp-run: {status.name[1:].replace('_', '-', 1)}: {text}")
            elif self._worried.pop(status.name, None) is not None:
                say(f"\nnpp-run: {status.name[1:].replace('_', '-', 1)}: going on ({health.doing})")

    def on_certificate(self, certificate: Certificate) -> None:
        """The certificate of this run (RunReports), which ends it."""
        self.certificate = certificate
        self.certified.set()

    def on_gap(self, gap: GapRecord) -> None:
        """A gap report of this run (RunReports): its progress line, as npp-learn prints it."""
        self.last = gap
        now = time.monotonic()
        text = progress_text(gap)
        if self.tty:
            say("\r" + text.ljust(110), end="")
        elif now - self._printed > 2.0:
            say(text)
            self._printed = now

    def other_graph(self, ours: int) -> str | None:
        """Who else publishes a graph's one-per-graph topics (the sim's plant, the supervisor's gaps), or None.

        ``ours`` is how many of those publishers this run owns on each topic: 0 before its nodes start,
        1 after. Two graphs on one domain answer each other's service calls, so either is refused.
        """
        client = self.client
        named_by = time.monotonic() + NAMING_S
        while True:
            found = [
                f"/{topic} is published by {client.publishers_of(topic)}"
                for topic in GRAPH_TOPICS
                if client.count_publishers(topic) > ours
            ]
            # Discovery may show an endpoint before its node's name: wait a little to name who runs the other graph.
            if not any(UNNAMED in text for text in found) or time.monotonic() > named_by:
                break
            time.sleep(0.2)
        if not found:
            return None
        names = [node_name(ns, n) for n, ns in client.graph_nodes() if n.startswith("npp_")]
        seen = ", ".join(f"{n} x{names.count(n)}" if names.count(n) > 1 else n for n in sorted(set(names)))
        return f"{'; '.join(found)} (npp nodes on the domain: {seen})"


def say(text: str, end: str = "\n") -> None:
    """A line on stderr that never stops the shutdown: after a hang-up the terminal is gone (EIO)."""
    with suppress(OSError, ValueError):
        sys.stderr.write(text + end)
        sys.stderr.flush()


def where() -> str:
    """The domain and discovery range the graph runs on, as a user would check them."""
    domain = os.environ.get("ROS_DOMAIN_ID") or "0 (ROS_DOMAIN_ID unset)"
    return f"ROS_DOMAIN_ID {domain}, discovery {os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE', 'SUBNET')}"


# --------------------------------------------------------------------------- children die with npp-run
class Stopped(Exception):
    """SIGHUP (the terminal closed) or SIGTERM (kill, systemd, a job control): stop the nodes, then exit."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def _raise_stopped(signum: int, _frame: object) -> None:
    raise Stopped(signum)


def _ignore_further(signum: int, _frame: object) -> None:
    """While the nodes are being stopped, a second SIGHUP or SIGTERM must not cut the shutdown short."""


def stop_all(procs: dict[str, subprocess.Popen]) -> None:
    """SIGINT to every node still running, and SIGCONT, so that a paused one (SIGSTOP, a debugger) can take it;
    then up to STOP_GRACE_S for their ordered teardowns, saying which node is waited for; one still running
    after that is killed, named. A killed node loses nothing: the run file is written transaction by transaction."""
    for proc in procs.values():
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            proc.send_signal(signal.SIGCONT)
    start = time.monotonic()
    for name, proc in procs.items():
        with suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=max(start + STOP_NOTICE_S - time.monotonic(), 0.0))
        if proc.poll() is None:
            say(f"npp-run: waiting for {name} to stop (up to {STOP_GRACE_S:.0f} s)")
        try:
            proc.wait(timeout=max(start + STOP_GRACE_S - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            say(f"npp-run: {name} did not stop on SIGINT within {STOP_GRACE_S:.0f} s; killing it")
            proc.kill()
            proc.wait()


# --------------------------------------------------------------------------- logs and refusals
def open_log(run_dir: Path, name: str) -> IO[str]:
    """logs/NAME.log for this attempt; the previous attempt's log is kept as logs/NAME.1.log."""
    path = run_dir / "logs" / f"{name}.log"
    if path.exists() and path.stat().st_size > 0:
        path.replace(path.with_name(f"{name}.1.log"))
    return path.open("a")


_ERROR_LINE = re.compile(
    r"\[(ERROR|FATAL)\]"  # an rclpy log line
    r"|^[A-Za-z_][\w.]*(Error|Exception)\b"  # a traceback's last line
    r"|^(\S*/)?(npp-\w+|\w+\.py): "  # a refusal at start-up: "npp-sim: bad parameter: ..."
)

_OWN_NAME = re.compile(r"^(\S*/)?(npp-\w+|\w+\.py): ")  # npp-run names the node already


def reason_line(log: Path) -> str:
    """The line in a node's log that says why it stopped: its last error line, else its last line."""
    try:
        lines = [line.strip() for line in log.read_text(errors="replace").splitlines() if line.strip()]
    except OSError:
        return ""
    lines = [line for line in lines if not line.startswith(LOG_HEADER)]
    errors = [line for line in lines if _ERROR_LINE.search(line)]
    return _OWN_NAME.sub("", (errors or lines or [""])[-1])


def folder_in_use(run_dir: Path) -> str | None:
    """Why this run folder cannot take a writer now (another one holds it), or None.

    The run file's own writer lock (npp_ros.run.writer_lock) is taken and released at once: the check names
    the holder exactly as the supervisor would, but before any node starts.
    """
    try:
        WriterLock.acquire(run_dir / RUN_FILE).release()
    except RunFileError as exc:
        return f"{exc}{_started_by(run_dir / 'run.lock')}"
    return None


def _started_by(lock: Path) -> str:
    """' (its npp-run: pid N, npp-run ...)' for a lock holder that an npp-run started, else ''."""
    with suppress(OSError, ValueError, IndexError):
        pid = int(lock.read_text().split()[0])
        parent = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
        argv = Path(f"/proc/{parent}/cmdline").read_bytes().decode(errors="replace").split("\0")[:-1]
        if any("npp_ros_graph.tools.run" in a or a.endswith("npp-run") for a in argv[:3]):
            return f" (its npp-run: pid {parent}, {shlex.join(argv)[:200]})"
    return ""


# --------------------------------------------------------------------------- stalled nodes
class StallWatch:
    """Names a node whose process is stopped (SIGSTOP, Ctrl-Z, a debugger): the run waits for it in
    silence otherwise, and from the outside a stopped node looks like a slow one."""

    def __init__(self, procs: dict[str, subprocess.Popen]) -> None:
        self.procs = procs
        self.since: dict[str, float] = {}
        self.told: set[str] = set()

    def check(self, now: float) -> list[str]:
        lines = []
        for name, proc in self.procs.items():
            if _stopped(proc.pid):
                self.since.setdefault(name, now)
                if name not in self.told and now - self.since[name] >= STALL_NOTICE_S:
                    self.told.add(name)
                    lines.append(
                        f"npp-{name} (pid {proc.pid}) is stopped (SIGSTOP or a debugger); the run waits for it "
                        f"(kill -CONT {proc.pid} resumes it)"
                    )
            elif name in self.since:
                stopped_for = now - self.since.pop(name)
                if name in self.told:
                    self.told.discard(name)
                    lines.append(f"npp-{name} (pid {proc.pid}) runs again after about {stopped_for:.0f} s stopped")
        return lines


def _stopped(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] in ("T", "t")
    except (OSError, IndexError):
        return False


# --------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    args = parse_args(__doc__ or "", argv)
    try:  # the request's own checks, before any node: a node would refuse the same value in the same words
        request = run_request(args)
    except ValueError as exc:
        say(f"npp-run: {exc}; not starting")
        return 2
    request = replace(request, horizon=request.horizon or get_task(request.task).default_horizon)
    run_dir = (args.run_dir or default_run_dir(args.task, args.seed)).resolve()
    (run_dir / "logs").mkdir(parents=True, exist_ok=True)
    in_use = folder_in_use(run_dir)
    if in_use is not None:  # before any node: a second graph would only be refused by its supervisor
        say(f"npp-run: {in_use}; not starting")
        return 2
    env = dict(os.environ)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env[KEY_ENV] = env.get(KEY_ENV) or RunSeal.new_key()  # the run's seal: its nodes refuse what lacks it
    if args.domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(args.domain_id)
    os.environ.update({k: env[k] for k in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_DOMAIN_ID", KEY_ENV) if k in env})
    params = request_parameters(request, run_dir)  # every setting of the run, to the nodes that use it
    params["supervisor"]["rollouts"] = not args.no_rollouts
    for signum in (signal.SIGHUP, signal.SIGTERM):
        signal.signal(signum, _raise_stopped)
    # Started from a script's background job, npp-run inherits an ignored SIGINT, and Python then keeps it
    # ignored: Ctrl-C and `kill -INT` must stop the run all the same.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    procs: dict[str, subprocess.Popen] = {}
    extras: dict[str, subprocess.Popen] = {}  # started first and stopped last, so that they see the whole run
    follower: Follower | None = None
    code = 0
    try:
        # SIGINT stays Python's (KeyboardInterrupt); SIGTERM and SIGHUP raise Stopped.
        follower = Follower()
        time.sleep(DISCOVERY_S)  # time for discovery: is another graph on this domain?
        other = follower.other_graph(ours=0)
        if other is not None:
            say(f"npp-run: another graph is running on {where()}: {other}; not starting. {TWO_GRAPHS}")
            return 2
        setup = child_setup(os.getpid())  # every child, the recorder and the dashboard too, dies with npp-run
        if args.dashboard is not None:  # first: a port in use stops npp-run before any node started
            extras["dashboard"] = procs["dashboard"] = start_dashboard(run_dir, env, args.dashboard, setup)
        if args.record:
            extras["record"] = procs["record"] = start_recorder(run_dir, env, setup)
        for name, values in params.items():
            cmd = node_argv(name, values)
            with open_log(run_dir, name) as log:
                procs[name] = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env, preexec_fn=setup)
                log.write(f"{LOG_HEADER} {datetime.now().isoformat(timespec='seconds')}: pid {procs[name].pid}\n")
        say(f"npp-run: started sim, expert, policy, supervisor on {where()} (logs in {run_dir / 'logs'})")
        code = follow(follower, procs, run_dir, args.max_episodes)
    except KeyboardInterrupt:
        say("\nnpp-run: interrupted; stopping the nodes (the run resumes from its folder)")
        code = 130
    except Stopped as exc:
        say(f"\nnpp-run: {exc} received; stopping the nodes (the run resumes from its folder)")
        code = 128 + exc.signum
    finally:
        for signum in (signal.SIGHUP, signal.SIGTERM):
            signal.signal(signum, _ignore_further)
        if follower is not None:
            notice = run_file_notice(run_dir / RUN_FILE)  # the expert's failure, before the certificate
            if notice:
                say(("\n" if follower.tty else "") + "\n".join(f"npp-run: {line}" for line in notice))
            if follower.certificate is not None:
                with suppress(OSError):
                    print(("\n" if follower.tty else "") + certificate_line(follower.certificate))
                    print(f"run folder: {run_dir}")
        # The nodes first: a ROS teardown that hangs (a loaded machine's DDS) must never leave them running.
        stop_all({name: proc for name, proc in procs.items() if name not in extras})
        stop_all(extras)
        if follower is not None:
            leaving = leave_if_teardown_hangs("npp-run", TEARDOWN_S, code)
            follower.client.close()
            leaving.cancel()
    return code


def follow(follower: Follower, procs: dict[str, subprocess.Popen], run_dir: Path, max_episodes: int) -> int:
    """Watch until the certificate, the episode budget, a dead node or a second graph; the exit code."""
    started = time.monotonic()
    budget_reached_at: float | None = None
    checked = 0.0
    warned: str | None = None
    stalls = StallWatch(procs)
    while not follower.certified.wait(0.1):
        dead = {n: p.returncode for n, p in procs.items() if p.poll() is not None}
        if dead:
            for name, rc in dead.items():
                log = run_dir / "logs" / f"{name}.log"
                why = reason_line(log)
                say(f"\nnpp-run: npp-{name} exited with code {rc}" + (f": {why}" if why else "") + f" (log: {log})")
            return 1
        now = time.monotonic()
        if now - checked >= 1.0:
            checked = now
            for line in stalls.check(now):
                say(f"\nnpp-run: {line}")
            other = follower.other_graph(ours=1)
            if other is not None and now - started < SECOND_GRAPH_WINDOW_S:
                say(f"\nnpp-run: another graph is running on {where()}: {other}; stopping. {TWO_GRAPHS}")
                return 2
            if other is not None and other != warned:  # a newcomer after our start: it should stop itself
                say(f"\nnpp-run: WARNING another graph joined {where()}: {other}. {TWO_GRAPHS}")
            warned = other
        if follower.last is not None and follower.last.episode + 1 >= max_episodes:
            budget_reached_at = budget_reached_at or now
            if now - budget_reached_at > 5.0:
                say(f"\nnpp-run: NOT CERTIFIED within {max_episodes} episodes")
                return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
