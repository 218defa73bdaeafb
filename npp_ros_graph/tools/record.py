"""npp-record: records every /npp topic of a running graph into a rosbag2 bag in MCAP storage.

The graph's own topics (topics.py) are subscribed at start with the types and QoS their
publishers use, so a node that starts later is recorded from its first message even when that
message comes before discovery would have found the topic (a first GapReport, say). Any other
topic under npp/ is found in the graph (its type too) every --discover-every seconds. Each topic is subscribed with the
QoS its publishers offer (latched topics as TRANSIENT_LOCAL, so their last value is recorded even
when it was published before the recorder started), and messages are written as the raw CDR bytes
that came off the wire. The bag is flushed every --flush-every seconds: a recorder that is killed,
even with SIGKILL, leaves a bag that rosbags and any MCAP reader open, holding every message that
arrived before the last flush. Ctrl-C or SIGTERM closes the bag with its indexes.

The bag carries the message definitions of every topic (npp_interfaces included), so a reader needs
nothing from this project to decode it: e.g. rosbags' AnyReader, or `npp-monitor --bag BAG`.
"""

from __future__ import annotations

import argparse
import importlib
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from rclpy.topic_endpoint_info import TopicEndpointInfo
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

from npp_ros_graph.tools.bag import BagError, BagWriter, TopicInfo, repair
from npp_ros_graph.transport import topics

# The graph's topics with the type and QoS their publishers use (the nodes' create_publisher calls);
# they are subscribed at start. Every other topic under the same npp/ prefix is recorded when found.
GRAPH_TOPICS: dict[str, tuple[str, QoSProfile]] = {
    topics.STATE: ("sensor_msgs/msg/JointState", topics.CONTROL_QOS),
    topics.ACTION: ("sensor_msgs/msg/JointState", topics.CONTROL_QOS),
    topics.GAP: ("npp_interfaces/msg/GapReport", topics.REPORT_HISTORY_QOS),
    topics.EPISODE: ("npp_interfaces/msg/EpisodeResult", topics.REPORT_HISTORY_QOS),
    topics.CERTIFICATE: ("npp_interfaces/msg/Certificate", topics.LATCHED_QOS),
    topics.PLANT: ("npp_interfaces/msg/PlantDescription", topics.LATCHED_QOS),
    topics.ROLLOUT_DONE: ("npp_interfaces/msg/EpisodeResult", topics.REPORT_QOS),
    topics.DATASET_TOPIC: ("npp_interfaces/msg/Trajectory", topics.REPORT_QOS),
    topics.POLICY_STATUS: ("std_msgs/msg/UInt32", topics.LATCHED_QOS),
    topics.POLICY_DROPPED: ("std_msgs/msg/UInt64", topics.REPORT_QOS),
}
KNOWN_TOPICS = tuple(GRAPH_TOPICS)
PREFIX = "npp"
# Deep enough that a burst (a dataset republished to a restarted policy) is not cut short by the queue.
RECORD_DEPTH = 1000


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="npp-record",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="topics of the graph: " + ", ".join(KNOWN_TOPICS) + "\n"
        "ROS arguments follow --ros-args, e.g. `npp-record -o run.bag --ros-args -r __ns:=/robot1`.",
    )
    ap.add_argument("-o", "--output", type=Path, default=None, help="new bag folder (default: npp_bag_DATE-TIME)")
    ap.add_argument("--flush-every", type=float, default=1.0, metavar="S", help="seconds between flushes (default 1)")
    ap.add_argument(
        "--discover-every", type=float, default=0.25, metavar="S", help="seconds between looks for new topics"
    )
    ap.add_argument(
        "--exclude", action="append", default=[], metavar="TOPIC",
        help="a topic not to record, e.g. npp/state (repeatable)",
    )  # fmt: skip
    ap.add_argument("--no-compress", action="store_true", help="write chunks uncompressed (default: zstd)")
    ap.add_argument(
        "--repair", type=Path, default=None, metavar="BAG",
        help="close a bag whose recorder was killed in the middle of a flush, keeping every complete record",
    )  # fmt: skip
    return ap


def split_ros_args(argv: list[str]) -> tuple[list[str], list[str]]:
    """(own arguments, ['--ros-args', ...])."""
    if "--ros-args" not in argv:
        return argv, []
    at = argv.index("--ros-args")
    return argv[:at], argv[at:]


def message_class(msgtype: str) -> Any:
    """npp_interfaces/msg/GapReport -> the generated Python class."""
    package, kind, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{package}.{kind}"), name)


def _duration(value: Any) -> QosTime:
    ns = int(getattr(value, "nanoseconds", 0))
    return QosTime(ns // 10**9, ns % 10**9)


def offered_qos(q: QoSProfile) -> Qos:
    """A publisher's QoS as rosbag2 records it (rclpy's and rosbag2's policy numbers are the same)."""
    return Qos(
        history=QosHistory(int(q.history)),
        depth=int(q.depth),
        reliability=QosReliability(int(q.reliability)),
        durability=QosDurability(int(q.durability)),
        deadline=_duration(q.deadline),
        lifespan=_duration(q.lifespan),
        liveliness=QosLiveliness(int(q.liveliness)),
        liveliness_lease_duration=_duration(q.liveliness_lease_duration),
        avoid_ros_namespace_conventions=bool(q.avoid_ros_namespace_conventions),
    )


def subscription_qos(offered: list[Qos]) -> QoSProfile:
    """What matches every publisher, as rosbag2 chooses it: reliable only if all are, transient local
    (latched) only if all are; a deep queue so that the recorder does not drop what it is offered."""
    reliable = all(q.reliability == QosReliability.RELIABLE for q in offered)
    latched = all(q.durability == QosDurability.TRANSIENT_LOCAL for q in offered)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=RECORD_DEPTH,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


def type_hash(infos: list[TopicEndpointInfo]) -> str:
    for info in infos:
        h = info.topic_type_hash
        if getattr(h, "version", -1) == 1:
            return f"RIHS01_{bytes(h.value).hex()}"
    return ""


def next_bag_dir(run_dir: Path) -> Path:
    """RUN_DIR/bag, or bag-2, bag-3, ... when a resumed run already recorded one."""
    candidate, k = run_dir / "bag", 1
    while candidate.exists():
        k += 1
        candidate = run_dir / f"bag-{k}"
    return candidate


def start_recorder(
    run_dir: Path, env: dict[str, str], setup: Callable[[], None], timeout: float = 60.0
) -> subprocess.Popen[bytes]:
    """npp-run --record: npp-record as a process writing RUN_DIR/bag (log in RUN_DIR/logs/record.log),
    returned once its bag exists, so that the nodes started next are recorded from their first message.
    ``setup`` runs in the child before exec (npp-run's: the child dies with npp-run)."""
    bag = next_bag_dir(run_dir)
    log = (run_dir / "logs" / "record.log").open("ab")
    proc = subprocess.Popen(
        [sys.executable, "-m", "npp_ros_graph.tools.record", "--output", str(bag)],
        stdout=log, stderr=subprocess.STDOUT, env=env, preexec_fn=setup,
    )  # fmt: skip
    deadline = time.monotonic() + timeout
    while not (bag / "metadata.yaml").exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.5)  # the node itself starts right after the bag
    print(f"npp-run: recording into {bag}", file=sys.stderr)
    return proc


class RecorderNode(Node):
    """Subscribes raw to every topic under npp/ as it appears and writes what arrives into the bag."""

    def __init__(self, bag: BagWriter, exclude: list[str], flush_s: float, discover_s: float) -> None:
        super().__init__("npp_record")
        self.bag = bag
        self.prefix = self.resolve_topic_name(PREFIX) + "/"  # "/npp/", or "/robot1/npp/" in a namespace
        self.exclude = {self.resolve_topic_name(t.strip("/")) for t in exclude}
        self.recorded: dict[str, TopicInfo] = {}
        self._refused: set[str] = set()
        self._last_log_ns = 0
        for relative, (msgtype, qos) in GRAPH_TOPICS.items():
            name = self.resolve_topic_name(relative)
            if name in self.exclude:
                self._refuse(name, "excluded on the command line")
            else:
                self.record(name, msgtype, [offered_qos(qos)])
        self.discover()
        self.create_timer(discover_s, self.discover)
        self.create_timer(flush_s, self.flush)

    def discover(self) -> None:
        for name, types in self.get_topic_names_and_types():
            if name in self.recorded or name in self._refused or not name.startswith(self.prefix):
                continue
            if name in self.exclude:
                self._refuse(name, "excluded on the command line")
                continue
            if len(types) != 1:
                self._refuse(name, f"it carries several types ({', '.join(types)})")
                continue
            publishers = self.get_publishers_info_by_topic(name)
            if publishers:  # until one appears, its QoS is unknown; it is looked at again next time
                self.record(name, types[0], [offered_qos(p.qos_profile) for p in publishers], type_hash(publishers))

    def _refuse(self, name: str, why: str) -> None:
        self._refused.add(name)
        self.get_logger().warning(f"not recording {name}: {why}")

    def record(self, name: str, msgtype: str, offered: list[Qos], hash_: str = "") -> None:
        try:
            cls = message_class(msgtype)
            topic = self.bag.add_topic(name, msgtype, offered, hash_)
        except (BagError, ImportError, AttributeError, ValueError) as exc:
            self._refuse(name, str(exc))
            return
        qos = subscription_qos(offered)

        def on_message(raw: bytes, info: Any) -> None:
            # Log time: when the message arrived, but never before the last one written. Callbacks of
            # different topics run in the executor's order, not in arrival order, and a reader of a
            # bag whose recorder was killed (no index) needs the log times in the order of the file.
            received = max(int(info.get("received_timestamp", 0)) or time.time_ns(), self._last_log_ns)
            self._last_log_ns = received
            self.bag.write(topic, raw, received, int(info.get("source_timestamp", 0)) or received)

        self.create_subscription(cls, name, on_message, qos, raw=True)
        self.recorded[name] = topic
        self.get_logger().info(
            f"recording {name} ({msgtype}, {qos.reliability.name.lower()}, {qos.durability.name.lower()})"
        )

    def flush(self) -> None:
        self.bag.flush()


def main(argv: list[str] | None = None) -> int:
    own, ros_args = split_ros_args(list(sys.argv[1:] if argv is None else argv))
    args = parser().parse_args(own)
    if args.repair is not None:
        try:
            print(f"npp-record: {repair(args.repair)}")
        except (BagError, OSError) as exc:
            print(f"npp-record: cannot repair {args.repair}: {exc}", file=sys.stderr)
            return 2
        return 0
    if args.flush_every <= 0 or args.discover_every <= 0:
        print("npp-record: --flush-every and --discover-every must be positive", file=sys.stderr)
        return 2
    output = args.output or Path(datetime.now().strftime("npp_bag_%Y_%m_%d-%H_%M_%S"))
    try:
        bag = BagWriter(output, compress=not args.no_compress)
    except (BagError, OSError) as exc:
        print(f"npp-record: {exc}", file=sys.stderr)
        return 2

    # Our own handlers: a stop request lets the recorder take in what has already arrived, then close.
    stop: list[int] = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, _frame: stop.append(signum))
    rclpy.init(args=["npp-record", *ros_args], signal_handler_options=SignalHandlerOptions.NO)
    node: RecorderNode | None = None
    executor = SingleThreadedExecutor()
    try:
        node = RecorderNode(bag, args.exclude, args.flush_every, args.discover_every)
        executor.add_node(node)
        print(f"npp-record: recording every topic under {node.prefix} into {output}", file=sys.stderr, flush=True)
        while not stop:
            executor.spin_once(timeout_sec=0.1)
        drain_until = time.monotonic() + 0.5
        while time.monotonic() < drain_until:
            executor.spin_once(timeout_sec=0.05)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        bag.close()
        print(
            f"npp-record: {bag.message_count} messages on {len(bag.topics)} topics in {output}",
            file=sys.stderr,
            flush=True,
        )
        topics.release(executor, node)
    return 0


if __name__ == "__main__":
    sys.exit(main())
