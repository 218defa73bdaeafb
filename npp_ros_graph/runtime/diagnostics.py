"""/diagnostics for every npp_ros node: what it is doing, its backlog or dropped input, its last error.

ROS 2 tools (rqt_robot_monitor, diagnostic_aggregator, `ros2 topic echo /diagnostics`) read
diagnostic_msgs/DiagnosticArray on the absolute topic /diagnostics, one DiagnosticStatus per
component. A node hands :class:`DiagnosticsReporter` a function that returns its :class:`Health`;
the reporter publishes it once per period (and at once on :meth:`DiagnosticsReporter.publish`),
named by the node's full name, so one line in a node's constructor is all it takes.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

from npp_ros.deployment.state import Status

DIAGNOSTICS = "/diagnostics"
DIAGNOSTICS_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
OK, WARN, ERROR = (int.from_bytes(level, "little") for level in (DiagnosticStatus.OK, DiagnosticStatus.WARN,
                                                                  DiagnosticStatus.ERROR))  # fmt: skip
LEVEL_NAMES = {OK: "OK", WARN: "WARN", ERROR: "ERROR"}


@dataclass(frozen=True)
class Health:
    """One node's state in words: ``doing`` is the status message, ``values`` its counters (backlog,
    dropped or refused input...), ``error`` the last problem it met ("" for none)."""

    doing: str
    values: Mapping[str, object] = field(default_factory=dict)
    level: int = OK
    error: str = ""


def health_of_state(status: Status) -> Health:
    """The Health of a core status (npp_ros.deployment.state: npp-deploy's), whose levels are these numbers."""
    return Health(status.doing, status.values, int(status.level), status.error)


def status_of(name: str, health: Health, hardware_id: str = "") -> DiagnosticStatus:
    """A DiagnosticStatus for one node's health; the last error, if any, is one of its values."""
    level = max(health.level, WARN) if health.error and health.level == OK else health.level
    values = [KeyValue(key=str(k), value=str(v)) for k, v in health.values.items()]
    if health.error:
        values.append(KeyValue(key="last error", value=health.error))
    return DiagnosticStatus(
        level=bytes([level]), name=name, message=health.doing, hardware_id=hardware_id, values=values
    )


def health_of(status: DiagnosticStatus) -> Health:
    """The Health a DiagnosticStatus carries (npp-monitor and npp-deploy-ctl read it back)."""
    values = {kv.key: kv.value for kv in status.values}
    error = str(values.pop("last error", ""))
    level = status.level if isinstance(status.level, int) else int.from_bytes(status.level, "little")
    return Health(status.message, values, level, error)


def health_lines(msg: DiagnosticArray, shown: dict[str, str]) -> list[str]:
    """npp-monitor's lines for the statuses whose level or message changed since ``shown`` (updated here)."""
    lines = []
    for status in msg.status:
        health = health_of(status)
        line = f"[health]  {status.name:<22} {LEVEL_NAMES.get(health.level, str(health.level)):<5}  {health.doing}"
        if health.error:
            line += f"  (last error: {health.error})"
        if shown.get(status.name) != line:
            shown[status.name] = line
            lines.append(line)
    return lines


class DiagnosticsReporter:
    """Publishes ``report()`` on /diagnostics every ``period`` seconds, and on demand."""

    def __init__(self, node: Node, report: Callable[[], Health], period: float = 1.0, hardware_id: str = "") -> None:
        self.node, self.report, self.hardware_id = node, report, hardware_id
        self.name = node.get_fully_qualified_name()
        self.pub = node.create_publisher(DiagnosticArray, DIAGNOSTICS, DIAGNOSTICS_QOS)
        self.timer = node.create_timer(period, self.publish)

    def publish(self) -> None:
        if not self.node.context.ok():
            return  # shutting down: nobody to tell
        try:
            health = self.report()
        except Exception as exc:  # a report must never take its node down
            health = Health("cannot report its state", level=ERROR, error=f"{type(exc).__name__}: {exc}")
        msg = DiagnosticArray(status=[status_of(self.name, health, self.hardware_id)])
        msg.header.stamp = self.node.get_clock().now().to_msg()
        self.pub.publish(msg)
