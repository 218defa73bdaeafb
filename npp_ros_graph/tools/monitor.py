"""npp-monitor: prints the gap, episode and certificate topics live (there is no ros2 CLI here), or those of a
bag recorded by npp-record (--bag), in the same lines.

Given the run's key (NPP_RUN_KEY), it prints the reports of the run that the run's supervisor runs, and
no other's: not a replayed bag's, not another run's under the same key (npp_ros_graph/runtime/reports.py);
it names each run it leaves out on stderr. Without the key it prints every report, and says that they are
not verified, and which run they name, whenever that run changes.

While nothing arrives (no graph yet, another ROS domain, a finished run) it says on stderr what it waits
for and where it listens (ROS_DOMAIN_ID, discovery range), with the npp nodes and publishers it sees:
first after a few seconds, then periodically."""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
import time
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray

from npp_ros.certificate.certifier import QUANTITY, Certificate
from npp_ros.run.progress import checked_text
from npp_ros.run.records import EpisodeOutcome, GapRecord
from npp_ros_graph.client import GraphClient
from npp_ros_graph.runtime.diagnostics import DIAGNOSTICS, health_lines
from npp_ros_graph.runtime.node import leave_if_teardown_hangs
from npp_ros_graph.runtime.reports import UNVERIFIED
from npp_ros_graph.transport.convert import recorded_records
from npp_ros_graph.transport.topics import CERTIFICATE, EPISODE, GAP, PLANT

TOPICS = {"gap": GAP, "episode": EPISODE, "health": DIAGNOSTICS.lstrip("/")}  # --topics; the certificate always
FIRST_NOTICE_S = 5.0  # silence before the first "waiting for" line: discovery on one machine takes < 1 s
NOTICE_EVERY_S = 30.0  # then once per this much further silence
TEARDOWN_S = 20.0  # from the exit's start (the certificate, or the loop's end) to leaving without the ROS teardown


def gap_line(gap: GapRecord) -> str:
    """One episode: the gap its certification mode checked against epsilon, and the current test's streak. Episodes
    are counted from 1, as npp-learn's lines and the certificate's count them (the run file's index is from 0)."""
    mark = "ORACLE" if gap.oracle_called else "quiet"
    checked = checked_text(gap.checked_gap, gap.epsilon, gap.certify, gap.certify or "gap")
    return (
        f"[gap]     episode {gap.episode + 1:5d}  {checked}  {mark:<6} "
        f"|D| {gap.dataset_size:8d}  oracle calls {gap.oracle_calls:4d}  "
        f"test {gap.test} streak {gap.quiet_episodes}/{gap.required}"
    )


def episode_line(outcome: EpisodeOutcome) -> str:
    ret = "-" if outcome.policy_return is None else f"{outcome.policy_return:.2f}"
    expert = "-" if outcome.expert_value is None else f"{outcome.expert_value:.2f}"
    return (
        f"[episode] episode {outcome.episode + 1:5d}  return {ret:>8}  V*(s0) {expert:>8}  "
        f"V_lb(s0) {outcome.v_lb:.2f}  steps {outcome.steps}"
    )


def certificate_line(certificate: Certificate) -> str:
    """The certificate as a user must read it: what was checked, on which test, resting on what."""
    c, spec, lipschitz = certificate, certificate.spec, certificate.spec.lipschitz
    proven = "proven" if c.proven else "NOT proven (it rests on a step that does not hold here)"
    indent = "\n              "
    return (
        f"[certificate] condition ({spec.condition}), epsilon {spec.epsilon:g}, p {spec.p:g}, delta {spec.delta:g}, "
        f"L {lipschitz.value:g} ({lipschitz.source}, margin {lipschitz.margin:g}), episodes {c.episodes}, "
        f"oracle calls {c.oracle_calls}, |D| {c.dataset_size}"
        f"{indent}certify={spec.certify}: checked {QUANTITY[spec.certify]}; test {c.test}, delta spent "
        f"{c.delta_spent:.3g}; {proven}"
        f"{indent}{c.statement}" + "".join(f"{indent}assumes: {text}" for text in c.assumptions)
    )


def report_line(report: GapRecord | EpisodeOutcome | Certificate) -> str:
    """A report's line, as npp-monitor prints it live and from a bag."""
    if isinstance(report, GapRecord):
        return gap_line(report)
    return episode_line(report) if isinstance(report, EpisodeOutcome) else certificate_line(report)


class Monitor:
    """npp-monitor's lines, from a GraphClient that follows the live run (new reports only, as they come)."""

    def __init__(self, topics: set[str], exit_on_certificate: bool, ros_args: list[str]) -> None:
        self.exit_on_certificate = exit_on_certificate
        self.certified = threading.Event()
        self.leaving: threading.Timer | None = None
        self.topics = [TOPICS[name] for name in TOPICS if name in topics] + [CERTIFICATE]
        self.last_message = self.last_notice = time.monotonic()
        self.notices = 0
        self.unverified_run: str | None = None  # the run the unverified reports shown last name
        self._health_shown: dict[str, str] = {}  # each node's /diagnostics line, printed when it changes
        self.client = GraphClient(name="npp_monitor", past_reports=False, ros_args=ros_args)
        self.client.on_notice(lambda line: say(f"npp-monitor: {line}"))
        if "gap" in topics:
            self.client.on_gap(self.show)
        if "episode" in topics:
            self.client.on_episode(self.show)
        self.client.on_certificate(self.show)
        if "health" in topics:
            self.client.on_health(self.on_diagnostics)
        self.client.every(1.0, self.notice_if_silent)

    def show(self, report: GapRecord | EpisodeOutcome | Certificate) -> None:
        """A report to print (RunReports: this run's, or any while unverified, then marked so).

        Unverified, a line says so whenever the run the reports name changes, and the certificate says it
        too; the report lines themselves stay as `--bag` prints them.
        """
        self.last_message = time.monotonic()
        mark = self.client.mark(report)
        if mark:
            run = self.client.named_run(report)[:12] or "none"
            if run != self.unverified_run:
                self.unverified_run = run
                print(f"[reports] {UNVERIFIED}: the reports below name run {run}; any run on the domain, or a "
                      "replayed bag, may have sent them", flush=True)  # fmt: skip
        if isinstance(report, Certificate):
            print(certificate_line(report) + (f"\n              {mark}" if mark else ""), flush=True)
            self.certified.set()
            if self.exit_on_certificate:  # from here on, the exit is due
                self.start_leaving()
            return
        print(report_line(report), flush=True)

    def on_diagnostics(self, msg: DiagnosticArray) -> None:
        for line in health_lines(msg, self._health_shown):
            self.last_message = time.monotonic()
            print(line, flush=True)

    def start_leaving(self) -> None:
        """The exit's countdown (see leave_if_teardown_hangs), started once."""
        if self.leaving is None:
            self.leaving = leave_if_teardown_hangs("npp-monitor", TEARDOWN_S)

    def notice_if_silent(self) -> None:
        """A silent monitor looks like a hung one: after a while say what it waits for, and where."""
        now = time.monotonic()
        wait = FIRST_NOTICE_S if self.notices == 0 else NOTICE_EVERY_S
        if now - max(self.last_message, self.last_notice) < wait:
            return
        self.notices += 1
        self.last_notice = now
        print(f"npp-monitor: {self.waiting_line(now - self.last_message)}", file=sys.stderr, flush=True)

    def waiting_line(self, silent_s: float) -> str:
        client = self.client
        publishers = ", ".join(f"/{t} {client.count_publishers(t)}" for t in self.topics)
        nodes = sorted(f"{ns.rstrip('/')}/{n}" for n, ns in client.graph_nodes() if n.startswith("npp_"))
        others = [n for n in nodes if n != "/npp_monitor"]
        seen = ", ".join(others) if others else "none (no graph on this domain, or not discoverable from here)"
        unverified = "" if self.client.verified else f"Reports will be shown {UNVERIFIED}"
        held = self.client.reports_of_run.waiting() or unverified
        return (
            f"nothing received for {silent_s:.0f} s; waiting for {', '.join('/' + t for t in self.topics)} "
            f"on {listening_on()}. Publishers: {publishers}. npp nodes seen: {seen}" + (f". {held}" if held else "")
        )


def say(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def listening_on() -> str:
    """The domain and discovery range this process listens on: the usual reasons a graph is not seen."""
    domain = os.environ.get("ROS_DOMAIN_ID") or "0 (ROS_DOMAIN_ID unset)"
    scope = os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") or "SUBNET (unset; npp-run uses LOCALHOST)"
    peers = os.environ.get("ROS_STATIC_PEERS")
    return f"ROS_DOMAIN_ID {domain}, discovery {scope}" + (f", static peers {peers}" if peers else "")


def topic_names(text: str) -> set[str]:
    """--topics as a set of known names; an unknown one is refused with the known ones."""
    names = {name.strip() for name in text.split(",") if name.strip()} - {"certificate"}
    unknown = sorted(names - TOPICS.keys())
    if unknown:
        raise argparse.ArgumentTypeError(
            f"unknown topic {', '.join(map(repr, unknown))}; known: {', '.join(TOPICS)} "
            "(the certificate is always shown)"
        )
    return names


def print_bag(bag: str, topics: set[str]) -> int:
    """A recorded run, line for line as it was printed live: the bag's messages (decoded by the bag's own message
    definitions) read as the records a live client gives, its plant description naming the certificate's task."""
    from npp_ros_graph.tools.bag import BagError, read_messages

    shown = [name for name in (GAP, EPISODE) if name.rsplit("/", 1)[-1] in topics] + [CERTIFICATE]
    try:
        messages = ((message.msgtype, message.msg) for message in read_messages(Path(bag), [*shown, PLANT]))
        for record in recorded_records(messages):
            if isinstance(record, (GapRecord, EpisodeOutcome, Certificate)):
                print(report_line(record), flush=True)
    except BagError as exc:
        print(f"npp-monitor: {exc}", file=sys.stderr)
        return 2
    return 0


def main(argv: list[str] | None = None) -> int:
    args_in = list(sys.argv[1:] if argv is None else argv)
    ros_args = args_in[args_in.index("--ros-args") :] if "--ros-args" in args_in else []
    own = args_in[: len(args_in) - len(ros_args)]
    ap = argparse.ArgumentParser(prog="npp-monitor", description=__doc__)
    ap.add_argument(
        "--topics", default="gap,episode", type=topic_names,
        help="comma-separated: gap, episode, health (/diagnostics; certificate is always shown)",
    )  # fmt: skip
    ap.add_argument("--exit-on-certificate", action="store_true", help="exit once a certificate has been printed")
    ap.add_argument("--bag", metavar="PATH", help="print a bag recorded by npp-record instead of the live topics")
    args = ap.parse_args(own)
    if args.bag:
        return print_bag(args.bag, args.topics)
    # Ctrl-C and SIGTERM stop it, the client leaving in order, even when started in the background (where
    # SIGINT comes in ignored).
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    monitor: Monitor | None = None
    try:
        monitor = Monitor(args.topics, args.exit_on_certificate, ros_args)
        while not (args.exit_on_certificate and monitor.certified.is_set()):
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        if monitor is not None:
            monitor.start_leaving()
            monitor.client.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
