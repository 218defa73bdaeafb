"""The robot's model as the robot publishes it: its MJCF on robot_description_topic (latched, as robot_state_publisher
publishes its URDF), configure's wait for it, and the fingerprint the gate checks, with where that came from (the
operator's robot_model_fingerprint overrides it)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import rclpy
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from std_msgs.msg import String

from npp_ros.deployment.robot_model import DescriptionError, described_fingerprint
from npp_ros.deployment.state import wall_time
from npp_ros_graph.nodes.deploy.settings import DeploySettings
from npp_ros_graph.runtime.node import publishers_of, stop_requested
from npp_ros_graph.transport.topics import LATCHED_QOS

WAIT_SLICE_S = 0.1  # configure's wait for the description looks again at least this often (and for a stop)


@dataclass(frozen=True)
class Description:
    """The robot's latest MJCF on robot_description_topic: its text, who published it and when."""

    text: str
    publishers: str
    at: str


class RobotDescription:
    """What the robot published of its model on ``topic`` (robot_description_topic, read-only: the node's from its
    start), and what configure's last wait for it saw.

    It gets what it uses: the node, for its graph (the subscription, who publishes, the context a wait needs) and its
    logger, and the node's handler of each description (``on_message``, which compares it with the model
    configured), through which a description that configure's wait takes goes too.
    """

    def __init__(self, node: Node, topic: str, on_message: Callable[[String], None]) -> None:
        self.node, self.topic, self.on_message = node, topic, on_message
        self.latest: Description | None = None
        self.waited = ""  # what configure's last wait for the description saw, for its refusal
        # From the start, not at configure: the description is latched, and configure must find it there.
        self.subscription = node.create_subscription(String, topic, on_message, LATCHED_QOS)

    @property
    def source(self) -> str:
        """Where a fingerprint of the robot's own description comes from, in words."""
        return f"the MJCF the robot published on {self.topic}"

    def received(self, msg: String) -> Description:
        """A description came: the latest from now on, logged."""
        self.latest = Description(msg.data, publishers_of(self.node, self.topic), wall_time())
        self.node.get_logger().info(
            f"robot description received on {self.topic} ({len(msg.data)} characters, from {self.latest.publishers})"
        )
        return self.latest

    def wait(self, settings: DeploySettings) -> None:
        """Wait up to description_timeout for the robot's latched description when configure needs it.

        A node started just before configure may not have discovered the robot yet (0.3-0.9 s here). This runs
        in the executor's one thread, so the description cannot come through on_message meanwhile: the
        wait is on the subscription itself (a wait set of its own, looked at again every WAIT_SLICE_S), and a
        description that comes is taken from it and handed to on_message, as the executor would.
        """
        self.waited = ""
        if self.latest is not None or settings.robot_model_fingerprint.strip():
            return
        node, topic, subscription = self.node, self.topic, self.subscription
        started = time.monotonic()
        seen = 0
        wait_set = _rclpy.WaitSet(1, 0, 0, 0, 0, 0, node.context.handle)
        waited = False
        while True:
            seen = max(seen, node.count_publishers(topic))
            with subscription.handle:
                taken = subscription.handle.take_message(subscription.msg_type, subscription.raw)
            if taken is not None:
                self.on_message(taken[0])
                if waited:  # one already there (not yet handed over by the executor) is not news
                    node.get_logger().info(
                        f"configure waited {time.monotonic() - started:.2f} s for the robot's description"
                    )
                return
            left = started + settings.description_timeout - time.monotonic()
            if left <= 0 or stop_requested() or not rclpy.ok():
                break
            with subscription.handle:
                wait_set.clear_entities()
                wait_set.add_subscription(subscription.handle)
                wait_set.wait(int(min(left, WAIT_SLICE_S) * 1e9))
            waited = True
        publishers = "no publisher" if seen == 0 else f"{seen} publisher{'s' if seen > 1 else ''}"
        self.waited = (
            f"waited {time.monotonic() - started:.1f} s (description_timeout {settings.description_timeout:g}); "
            f"{publishers} of it seen"
        )

    def fingerprint(self, settings: DeploySettings) -> tuple[str, str]:
        """The fingerprint the gate checks and where it came from: the operator's parameter if given, else the
        robot's own description; ("", why) when there is neither (the gate then refuses)."""
        topic, description = self.topic, self.latest
        described = ""
        if description is not None:
            try:
                described = described_fingerprint(settings.run_dir, description.text) or ""
            except DescriptionError as exc:
                if not settings.robot_model_fingerprint.strip():
                    raise DescriptionError(f"the robot's description on {topic}: {exc}") from None
                self.node.get_logger().warning(f"the robot's description on {topic} is not used: {exc}")
        explicit = settings.robot_model_fingerprint.strip()
        if explicit:
            if described and described != explicit:
                self.node.get_logger().warning(
                    f"robot_model_fingerprint {explicit[:12]}... overrides the fingerprint of the robot's own "
                    f"description on {topic} ({described[:12]}...)"
                )
            return explicit, "the robot_model_fingerprint parameter"
        if description is None:
            waited = f" ({self.waited})" if self.waited else ""
            return "", (
                f"nowhere: no robot description was received on {topic}{waited} and robot_model_fingerprint is empty"
            )
        return described, self.source

    def describe(self) -> str:
        """The latest description in words, as /diagnostics shows it."""
        description = self.latest
        if description is None:
            return f"none received on {self.topic}"
        return f"{len(description.text)} characters from {description.publishers}, received {description.at}"
