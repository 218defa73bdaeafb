"""npp-replay: publishes a recorded bag back onto a ROS domain, so a live npp-monitor or npp-dashboard shows it.

Every topic is published with the QoS it was recorded with (latched topics stay latched: a monitor
started after the replay still gets their last value while npp-replay lingers), as the raw bytes the
bag holds, in recorded order and at the recorded pace divided by --rate. Run it on a domain where the
recorded graph is not running (--ros-args and ROS_DOMAIN_ID choose it), or both would be mixed.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosbags.interfaces import Qos, QosDurability, QosReliability

from npp_ros_graph.runtime.node import release
from npp_ros_graph.tools.bag import BagError, open_reader, read_messages
from npp_ros_graph.tools.record import message_class, split_ros_args


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="npp-replay", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("bag", type=Path, help="bag folder written by npp-record (or any rosbag2 MCAP bag)")
    ap.add_argument("--rate", type=float, default=1.0, help="pace factor: 2 = twice as fast; 0 = no pauses")
    ap.add_argument("--topics", default="", help="comma-separated topics to replay, e.g. npp/gap,npp/certificate")
    ap.add_argument(
        "--wait-for", action="append", default=[], metavar="TOPIC",
        help="before publishing, wait until this topic has a subscriber (repeatable)",
    )  # fmt: skip
    ap.add_argument("--wait-timeout", type=float, default=60.0, metavar="S", help="how long --wait-for waits")
    ap.add_argument("--delay", type=float, default=1.0, metavar="S", help="discovery time before the first message")
    ap.add_argument(
        "--linger", type=float, default=2.0, metavar="S",
        help="keep offering latched topics this long after the last message ('inf': until Ctrl-C)",
    )  # fmt: skip
    return ap


def publisher_qos(offered: list[Qos]) -> QoSProfile:
    """The recorded publishers' QoS: reliable and latched when they all were."""
    reliable = all(q.reliability == QosReliability.RELIABLE for q in offered) if offered else True
    latched = bool(offered) and all(q.durability == QosDurability.TRANSIENT_LOCAL for q in offered)
    depth = max([q.depth for q in offered], default=0)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=max(depth, 1) if latched else max(depth, 100),
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


class ReplayNode(Node):
    """One publisher per recorded topic, with the recorded QoS."""

    def __init__(self, topics: dict[str, tuple[str, list[Qos]]]) -> None:
        super().__init__("npp_replay")
        self.publishers_by_topic: dict[str, Publisher] = {}
        for name, (msgtype, offered) in topics.items():
            self.publishers_by_topic[name] = self.create_publisher(message_class(msgtype), name, publisher_qos(offered))


def bag_topics(bag: Path, wanted: list[str]) -> dict[str, tuple[str, list[Qos]]]:
    suffixes = tuple("/" + w.strip("/") for w in wanted)
    reader = open_reader(bag)
    try:
        return {
            c.topic: (c.msgtype, list(c.ext.offered_qos_profiles))  # type: ignore[union-attr]
            for c in reader.connections
            if not suffixes or c.topic.endswith(suffixes)
        }
    finally:
        reader.close()


def main(argv: list[str] | None = None) -> int:
    own, ros_args = split_ros_args(list(sys.argv[1:] if argv is None else argv))
    args = parser().parse_args(own)
    if args.rate < 0 or not math.isfinite(args.rate):
        print("npp-replay: --rate must be a finite number >= 0", file=sys.stderr)
        return 2
    wanted = [t for t in args.topics.split(",") if t]
    try:
        topics = bag_topics(args.bag, wanted)
    except BagError as exc:
        print(f"npp-replay: {exc}", file=sys.stderr)
        return 2
    if not topics:
        print(f"npp-replay: {args.bag} holds none of the topics {wanted}", file=sys.stderr)
        return 2

    rclpy.init(args=["npp-replay", *ros_args])
    node: ReplayNode | None = None
    executor = SingleThreadedExecutor()
    published = 0
    try:
        node = ReplayNode(topics)
        executor.add_node(node)

        def pause(seconds: float) -> None:
            until = time.monotonic() + seconds
            while (left := until - time.monotonic()) > 0:
                executor.spin_once(timeout_sec=min(left, 0.1))

        for name in args.wait_for:
            resolved = node.resolve_topic_name(name.strip("/"))
            publisher = node.publishers_by_topic.get(resolved)
            if publisher is None:
                print(f"npp-replay: --wait-for {name}: the bag has no topic {resolved}", file=sys.stderr)
                return 2
            deadline = time.monotonic() + args.wait_timeout
            while publisher.get_subscription_count() == 0:
                if time.monotonic() > deadline:
                    print(f"npp-replay: no subscriber on {resolved} within {args.wait_timeout:g} s", file=sys.stderr)
                    return 1
                executor.spin_once(timeout_sec=0.1)
        pause(args.delay)
        print(f"npp-replay: publishing {len(topics)} topics from {args.bag}", file=sys.stderr, flush=True)
        start_wall, start_bag = time.monotonic(), None
        for message in read_messages(args.bag, topics=list(topics), decode=False):
            if start_bag is None:
                start_bag = message.log_ns
            if args.rate > 0:
                pause(start_wall + (message.log_ns - start_bag) / 1e9 / args.rate - time.monotonic())
            elif published % 100 == 0:
                executor.spin_once(timeout_sec=0.0)
            node.publishers_by_topic[message.topic].publish(message.raw)
            published += 1
        print(
            f"npp-replay: published {published} messages in {time.monotonic() - start_wall:.1f} s",
            file=sys.stderr,
            flush=True,
        )
        if math.isinf(args.linger):
            executor.spin()
        else:
            pause(args.linger)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except BagError as exc:
        print(f"npp-replay: {exc}", file=sys.stderr)
        return 2
    finally:
        release(executor, node)
    return 0


if __name__ == "__main__":
    sys.exit(main())
