"""npp-dashboard: a web page that shows an npp run: live from the ROS topics, or a finished run folder or bag.

It shows the checked gap of every episode against epsilon, the quiet streak against the length the
current test requires, the dataset size, the oracle calls, the certificate once issued (statement,
checked quantity, test, confidence spent, assumptions, whether it is proven) and, live, which nodes
of the graph are alive. The page updates itself through server-sent events; it loads nothing from
outside this server.

It listens on 127.0.0.1 only, unless --host says otherwise. Live, it shows the episodes reported
after it started: `npp-run --dashboard` starts it before the nodes; for a run that is over, open its
folder (--run) or its bag (--bag). Live and given the run's key (NPP_RUN_KEY, as npp-run gives it), it
shows the reports of the run that the run's supervisor runs and no other's (a replayed bag's, another
run's under the same key: npp_ros_graph/runtime/reports.py); without the key, the page says that what it
shows is not verified.
"""

from __future__ import annotations

import argparse
import errno
import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib.resources import files
from pathlib import Path
from typing import Any

from npp_ros.certificate.certifier import Certificate
from npp_ros.run.records import GapRecord, PlantRecord

# Where the page's files are, and which names are served (nothing else is).
STATIC = files("npp_ros_graph.tools") / "static"
PAGES = {
    "/": ("index.html", "text/html; charset=utf-8"),
    "/index.html": ("index.html", "text/html; charset=utf-8"),
    "/dashboard.js": ("dashboard.js", "text/javascript; charset=utf-8"),
    "/dashboard.css": ("dashboard.css", "text/css; charset=utf-8"),
}
GRAPH_NODES = ("npp_sim", "npp_expert", "npp_policy", "npp_supervisor")
DEFAULT_PORT = 8765
HEARTBEAT_S = 10.0


def number(value: float) -> float | str | None:
    """JSON has no infinity: 'inf' and '-inf' as strings, NaN as null."""
    value = float(value)
    if math.isnan(value):
        return None
    if math.isinf(value):
        return "inf" if value > 0 else "-inf"
    return value


def episode_entry(gap: GapRecord) -> dict[str, Any]:
    """One episode's GapRecord (the graph's report, a bag's, or a run file's row read as one) as the page plots it."""
    return {
        "episode": gap.episode,
        "checked_gap": number(gap.checked_gap),
        "gap": number(gap.gap),
        "epsilon": number(gap.epsilon),
        "oracle_called": gap.oracle_called,
        "dataset_size": gap.dataset_size,
        "oracle_calls": gap.oracle_calls,
        "quiet": gap.quiet_episodes,
        "required": gap.required,
        "test": gap.test,
        "certify": gap.certify,
    }


CERTIFICATE_FIELDS = (
    "statement", "certify", "quantity", "value", "test", "delta_spent", "assumptions", "proven", "condition",
    "epsilon", "p", "delta", "lipschitz", "lipschitz_source", "episodes", "oracle_calls", "dataset_size",
)  # fmt: skip


def certificate_entry(certificate: Certificate) -> dict[str, Any]:
    """The run's Certificate (the graph's, a bag's or the run file's) in the page's terms: its record's fields."""
    record = certificate.record()
    entry: dict[str, Any] = {}
    for name in CERTIFICATE_FIELDS:
        value = record[name]
        if isinstance(value, float):
            value = number(value)
        elif not isinstance(value, (str, int, bool, type(None))):
            value = [str(v) for v in value]
        entry[name] = value
    return entry


def plant_entry(task: Any, seed: Any, horizon: Any) -> dict[str, Any]:
    """The run's plant in the page's terms: a PlantRecord's, or what the run file's metadata records of it."""
    return {"task": task, "seed": seed, "horizon": horizon}


class Hub:
    """The run as the page sees it, and the events that changed it; the HTTP threads read, one writer writes."""

    def __init__(self, source: str, mode: str) -> None:
        self.state: dict[str, Any] = {
            "source": source, "mode": mode, "plant": None, "episodes": [], "certificate": None, "nodes": None,
            "health": {},
        }  # fmt: skip
        self.events: list[tuple[int, str, Any]] = []
        self.cond = threading.Condition()
        self.closed = False

    def _emit(self, kind: str, data: Any) -> None:
        self.events.append((len(self.events) + 1, kind, data))
        self.cond.notify_all()

    def add_episode(self, entry: dict[str, Any]) -> None:
        """A new episode for the page; one it already shows (the supervisor's kept reports, delivered again after a
        re-match) is left out."""
        with self.cond:
            if entry in self.state["episodes"][-1000:]:
                return
            self.state["episodes"].append(entry)
            self._emit("episode", entry)

    def set(self, key: str, value: Any) -> None:
        with self.cond:
            if self.state.get(key) != value:
                self.state[key] = value
                self._emit(key, value)

    def snapshot(self) -> tuple[int, str]:
        with self.cond:
            return len(self.events), json.dumps(self.state)

    def after(self, seq: int, timeout: float) -> list[tuple[int, str, Any]]:
        with self.cond:
            self.cond.wait_for(lambda: len(self.events) > seq or self.closed, timeout)
            return self.events[seq:]

    def close(self) -> None:
        with self.cond:
            self.closed = True
            self.cond.notify_all()


# ----------------------------------------------------------------------------- sources
def load_run(folder: Path, hub: Hub) -> None:
    """A run folder (or its run.sqlite), read by the core's reader: every stored episode, each row as the GapRecord
    the supervisor reported for it, and the certificate if one was issued."""
    from npp_ros.run.read import read_run
    from npp_ros.run.records import RunFileError
    from npp_ros.tasks.task import UnknownTaskError

    try:
        run = read_run(folder)
    except (RunFileError, UnknownTaskError, OSError) as exc:
        raise SystemExit(f"npp-dashboard: cannot open the run {folder}: {exc}") from None
    meta, spec = run.metadata, run.spec
    hub.set("plant", plant_entry(meta.task, meta.seed, meta.horizon))
    for row in run.episodes:
        gap = GapRecord.of(row, epsilon=spec.epsilon, condition=spec.condition, certify=spec.certify)
        hub.add_episode(episode_entry(gap))
    if run.certificate is not None:
        hub.set("certificate", certificate_entry(run.certificate))


def load_bag(folder: Path, hub: Hub) -> None:
    """A bag recorded by npp-record: its gap reports, plant description and certificate, read as the records a live
    client gives."""
    from npp_ros_graph.tools.bag import BagError, read_messages
    from npp_ros_graph.transport.convert import recorded_records
    from npp_ros_graph.transport.topics import CERTIFICATE, GAP, PLANT

    try:
        messages = ((message.msgtype, message.msg) for message in read_messages(folder, [GAP, CERTIFICATE, PLANT]))
        for record in recorded_records(messages):
            if isinstance(record, GapRecord):
                hub.add_episode(episode_entry(record))
            elif isinstance(record, Certificate):
                hub.set("certificate", certificate_entry(record))
            else:
                hub.set("plant", plant_entry(record.task, record.seed, record.horizon))
    except BagError as exc:
        raise SystemExit(f"npp-dashboard: {exc}") from None


def follow_live(hub: Hub, ros_args: list[str], serve: Callable[[], None]) -> None:
    """Follow the run through a GraphClient and watch the graph's nodes until Ctrl-C."""
    from diagnostic_msgs.msg import DiagnosticArray

    from npp_ros_graph.client import GraphClient
    from npp_ros_graph.runtime.diagnostics import LEVEL_NAMES, health_of

    class Dashboard:
        """Feeds the hub: this run's gap reports (those the supervisor kept from before it joined too), the
        latched plant and certificate, the graph's node names and every node's health from /diagnostics."""

        def __init__(self) -> None:
            # Given NPP_RUN_KEY (npp-run --dashboard), only the reports of the run its supervisor runs.
            self.client = GraphClient(name="npp_dashboard", past_reports=True, ros_args=ros_args)
            self.client.on_notice(lambda line: print(f"npp-dashboard: {line}", flush=True))
            hub.set("verified", self.client.verified)
            if not self.client.verified:
                hub.set("source", f"{hub.state['source']}; reports not verified: no run key (NPP_RUN_KEY), so any "
                        "run on the domain, or a replayed bag, may have sent them")  # fmt: skip
            self.health: dict[str, dict[str, str]] = {}
            self.client.on_gap(lambda gap: hub.add_episode(episode_entry(gap)))
            self.client.on_certificate(self.on_certificate)
            self.client.on_plant(self.on_plant)
            self.client.on_health(self.on_diagnostics)
            self.client.every(1.0, self.look_at_nodes)
            self.look_at_nodes()

        def on_certificate(self, certificate: Certificate) -> None:
            """The run's certificate (any run's, marked so, while unverified)."""
            verified = self.client.mark(certificate) or "yes"
            hub.set("certificate", certificate_entry(certificate) | {"verified": verified})

        def on_plant(self, plant: PlantRecord) -> None:
            hub.set("plant", plant_entry(plant.task, plant.seed, plant.horizon))

        def on_diagnostics(self, msg: DiagnosticArray) -> None:
            """The newest status of each node, by its node name (a status is named by the node's full name)."""
            for status in msg.status:
                health = health_of(status)
                self.health[status.name.rsplit("/", 1)[-1]] = {
                    "level": LEVEL_NAMES.get(health.level, str(health.level)),
                    "doing": health.doing,
                    "error": health.error,
                }
            hub.set("health", dict(self.health))

        def look_at_nodes(self) -> None:
            client = self.client
            present = {name for name, namespace in client.graph_nodes() if namespace == client.namespace}
            others = sorted(n for n in present if n.startswith("npp_") and n not in GRAPH_NODES and n != client.name)
            nodes = [{"name": n, "alive": n in present, "role": "graph"} for n in GRAPH_NODES]
            nodes += [{"name": n, "alive": True, "role": "tool"} for n in others]
            hub.set("nodes", nodes)

    dashboard: Dashboard | None = None
    try:
        dashboard = Dashboard()
        serve()
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        if dashboard is not None:
            dashboard.client.close()


# ----------------------------------------------------------------------------- HTTP
def make_handler(hub: Hub, allowed_hosts: set[str] | None) -> type[BaseHTTPRequestHandler]:
    class Handler(BaseHTTPRequestHandler):
        """The page's three files, /state.json (the whole state) and /events (server-sent events)."""

        server_version = "npp-dashboard"

        def log_message(self, format: str, *args: Any) -> None:
            """Quiet: a page that reconnects must not fill the terminal."""

        def _headers(self, status: HTTPStatus, content_type: str, length: int | None = None) -> None:
            self.send_response(status)
            self.send_header("Content-Type", content_type)
            self.send_header("Cache-Control", "no-store")
            self.send_header("X-Content-Type-Options", "nosniff")
            self.send_header(
                "Content-Security-Policy", "default-src 'self'; img-src 'self' data:; frame-ancestors 'none'"
            )
            if length is not None:
                self.send_header("Content-Length", str(length))
            self.end_headers()

        def _send(self, status: HTTPStatus, content_type: str, body: bytes) -> None:
            self._headers(status, content_type, len(body))
            self.wfile.write(body)

        def do_GET(self) -> None:
            # A page of another site that resolves its own name to 127.0.0.1 is not served (DNS rebinding).
            if allowed_hosts is not None and self.headers.get("Host", "") not in allowed_hosts:
                self._send(HTTPStatus.FORBIDDEN, "text/plain", b"unknown Host\n")
                return
            path = self.path.split("?", 1)[0]
            if path in PAGES:
                name, content_type = PAGES[path]
                self._send(HTTPStatus.OK, content_type, (STATIC / name).read_bytes())
            elif path == "/state.json":
                self._send(HTTPStatus.OK, "application/json", hub.snapshot()[1].encode())
            elif path == "/events":
                self.stream()
            else:
                self._send(HTTPStatus.NOT_FOUND, "text/plain", b"not found\n")

        def stream(self) -> None:
            self._headers(HTTPStatus.OK, "text/event-stream")
            try:
                seq, state = hub.snapshot()
                self.wfile.write(f"event: snapshot\ndata: {state}\n\n".encode())
                self.wfile.flush()
                while not hub.closed:
                    events = hub.after(seq, HEARTBEAT_S)
                    chunks = [f"event: {kind}\ndata: {json.dumps(data)}\n\n" for _, kind, data in events]
                    self.wfile.write(("".join(chunks) or ": still here\n\n").encode())
                    self.wfile.flush()
                    seq += len(events)
            except (BrokenPipeError, ConnectionResetError):
                pass  # the page was closed

    return Handler


def allowed(host: str, port: int) -> set[str] | None:
    """Host headers a local page sends; None (no check) when the user opened the server to others."""
    if host not in ("127.0.0.1", "localhost", "::1"):
        return None
    return {f"{name}:{port}" for name in ("127.0.0.1", "localhost", "[::1]")}


def start_server(hub: Hub, host: str, port: int) -> tuple[ThreadingHTTPServer, str]:
    """Bind, then serve in a daemon thread; the refusal says why a port cannot be used."""
    try:
        server = ThreadingHTTPServer((host, port), make_handler(hub, None))
    except OSError as exc:
        why = "is in use; choose another with --port" if exc.errno == errno.EADDRINUSE else f"cannot be used: {exc}"
        raise SystemExit(f"npp-dashboard: port {port} on {host} {why}") from None
    server.daemon_threads = True
    bound = server.server_address[1]
    server.RequestHandlerClass = make_handler(hub, allowed(host, bound))
    threading.Thread(target=server.serve_forever, name="http", daemon=True).start()
    return server, f"http://{'127.0.0.1' if host == '0.0.0.0' else host}:{bound}/"


def start_dashboard(
    run_dir: Path, env: dict[str, str], port: int, setup: Callable[[], None]
) -> subprocess.Popen[bytes]:
    """npp-run --dashboard: npp-dashboard as a process (log in RUN_DIR/logs/dashboard.log), started before the
    nodes so that it shows every episode; returns once it serves. ``setup`` runs in the child before exec
    (npp-run's: the child dies with npp-run)."""
    log_path = run_dir / "logs" / "dashboard.log"
    log = log_path.open("ab")
    start = log_path.stat().st_size
    proc = subprocess.Popen(
        [sys.executable, "-m", "npp_ros_graph.tools.dashboard", "--port", str(port)],
        stdout=log, stderr=subprocess.STDOUT, env=env, preexec_fn=setup,
    )  # fmt: skip
    deadline = time.monotonic() + 60
    url = ""
    while proc.poll() is None and time.monotonic() < deadline and not url:
        text = log_path.read_bytes()[start:].decode(errors="replace")
        url = next((w for w in text.split() if w.startswith("http://")), "")
        time.sleep(0.1)
    if not url:
        proc.kill()
        proc.wait()
        said = log_path.read_bytes()[start:].decode(errors="replace").strip().splitlines()
        raise SystemExit(f"npp-run: the dashboard did not start: {said[-1] if said else 'no output'} (see {log_path})")
    print(
        f"npp-run: dashboard at {url} (it stops with the run; `npp-dashboard --run {run_dir}` shows it afterwards)",
        file=sys.stderr,
    )
    return proc


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="npp-dashboard",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Live, ROS arguments follow --ros-args (e.g. -r __ns:=/robot1); the domain is ROS_DOMAIN_ID's.",
    )
    ap.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"port (default {DEFAULT_PORT}; 0: any free one)")
    ap.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1: this machine only)")
    source = ap.add_mutually_exclusive_group()
    source.add_argument("--run", type=Path, metavar="DIR", help="show a run folder (its run.sqlite)")
    source.add_argument("--bag", type=Path, metavar="DIR", help="show a bag recorded by npp-record")
    return ap


def main(argv: list[str] | None = None) -> int:
    from npp_ros_graph.tools.record import split_ros_args

    own, ros_args = split_ros_args(list(sys.argv[1:] if argv is None else argv))
    args = parser().parse_args(own)
    if not 0 <= args.port <= 65535:
        print(f"npp-dashboard: --port {args.port} is not a port number (0-65535)", file=sys.stderr)
        return 2
    try:
        if args.run is not None:
            hub = Hub(f"run folder {args.run.resolve()}", "run")
            load_run(args.run, hub)
        elif args.bag is not None:
            hub = Hub(f"bag {args.bag.resolve()}", "bag")
            load_bag(args.bag, hub)
        else:
            hub = Hub(f"live, ROS domain {os.environ.get('ROS_DOMAIN_ID', '0')}", "live")
        server, url = start_server(hub, args.host, args.port)
    except SystemExit as exc:
        print(exc, file=sys.stderr)
        return 2
    if args.host not in ("127.0.0.1", "localhost", "::1"):
        print(f"npp-dashboard: listening on {args.host}: other machines can open this page", file=sys.stderr)

    # Stop on Ctrl-C and SIGTERM even when started in the background (where SIGINT comes in ignored).
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.default_int_handler)

    def announce() -> None:
        print(f"npp-dashboard: serving {url} ({hub.state['source']})", file=sys.stderr, flush=True)

    try:
        if hub.state["mode"] == "live":
            follow_live(hub, ros_args, announce)
        else:
            announce()
            while True:
                time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        hub.close()
        server.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
