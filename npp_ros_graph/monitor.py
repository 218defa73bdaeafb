"""npp-monitor: prints the gap, episode and certificate topics live (there is no ros2 CLI here), or those of a
bag recorded by npp-record (--bag), in the same lines."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import rclpy
from npp_interfaces.msg import Certificate, EpisodeResult, GapReport
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node

from npp_ros_graph.common import CERTIFICATE, EPISODE, GAP, LATCHED_QOS, REPORT_QOS


def gap_line(msg: GapReport) -> str:
    gap = "inf" if math.isinf(msg.gap) else f"{msg.gap:.2f}"
    mark = "ORACLE" if msg.oracle_called else "quiet"
    return (
        f"[gap]     episode {msg.episode:5d}  gap {gap:>8} / eps {msg.epsilon:g}  {mark:<6} "
        f"|D| {msg.dataset_size:8d}  oracle calls {msg.oracle_calls:4d}  "
        f"quiet {msg.quiet_episodes}/{msg.quiet_required}"
    )


def episode_line(msg: EpisodeResult) -> str:
    ret = "-" if math.isnan(msg.policy_return) else f"{msg.policy_return:.2f}"
    expert = f"{msg.expert_value:.2f}" if msg.expert_value_known else "-"
    return (
        f"[episode] episode {msg.episode:5d}  return {ret:>8}  V*(s0) {expert:>8}  "
        f"V_lb(s0) {msg.v_lb:.2f}  steps {msg.steps}"
    )


def certificate_line(msg: Certificate) -> str:
    return (
        f"[certificate] condition ({msg.condition}), epsilon {msg.epsilon:g}, p {msg.p:g}, delta {msg.delta:g}, "
        f"L {msg.lipschitz:g} ({msg.lipschitz_source}), episodes {msg.episodes}, oracle calls {msg.oracle_calls}, "
        f"|D| {msg.dataset_size}\n              {msg.statement}"
    )


class MonitorNode(Node):
    def __init__(self, topics: set[str], exit_on_certificate: bool) -> None:
        super().__init__("npp_monitor")
        self.exit_on_certificate = exit_on_certificate
        self.certified = False
        if "gap" in topics:
            self.create_subscription(GapReport, GAP, lambda m: self.show(gap_line(m)), REPORT_QOS)
        if "episode" in topics:
            self.create_subscription(EpisodeResult, EPISODE, lambda m: self.show(episode_line(m)), REPORT_QOS)
        self.create_subscription(Certificate, CERTIFICATE, self.on_certificate, LATCHED_QOS)

    @staticmethod
    def show(line: str) -> None:
        print(line, flush=True)

    def on_certificate(self, msg: Certificate) -> None:
        self.show(certificate_line(msg))
        self.certified = True


def print_bag(bag: str, topics: set[str]) -> int:
    """A recorded run, line for line as it was printed live (the bag's own message definitions decode it)."""
    from npp_ros_graph.bag import BagError, read_messages

    lines = {GAP: gap_line, EPISODE: episode_line, CERTIFICATE: certificate_line}
    shown = [name for name in lines if name == CERTIFICATE or name.rsplit("/", 1)[-1] in topics]
    try:
        for message in read_messages(Path(bag), shown):
            name = next(n for n in shown if message.topic.endswith("/" + n))
            print(lines[name](message.msg), flush=True)
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
        "--topics", default="gap,episode", help="comma-separated: gap, episode (certificate is always shown)"
    )
    ap.add_argument("--exit-on-certificate", action="store_true", help="exit once a certificate has been printed")
    ap.add_argument("--bag", metavar="PATH", help="print a bag recorded by npp-record instead of the live topics")
    args = ap.parse_args(own)
    if args.bag:
        return print_bag(args.bag, set(args.topics.split(",")))
    rclpy.init(args=["npp-monitor", *ros_args])
    node = MonitorNode(set(args.topics.split(",")), args.exit_on_certificate)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        while rclpy.ok() and not (args.exit_on_certificate and node.certified):
            executor.spin_once(timeout_sec=0.2)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
