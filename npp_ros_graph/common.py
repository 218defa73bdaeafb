"""What every npp_ros node shares: QoS, topic names, parameter declaration, conversions, main().

Nodes convert messages to core types, call the core, and publish; nothing here does math.
"""

from __future__ import annotations

import sys
import time
from array import array
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import rclpy
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from npp_ros.dataset import DatasetError, Trajectory

# Topic and service names, relative so that the usual namespacing and remapping apply.
STATE = "npp/state"
ACTION = "npp/action"
GAP = "npp/gap"
EPISODE = "npp/episode"
CERTIFICATE = "npp/certificate"
EXPERT_SERVICE = "npp/expert/trajectory"
PLANT = "npp/sim/plant"
RESET_SERVICE = "npp/sim/reset"
ROLLOUT_DONE = "npp/sim/rollout"
DATASET_TOPIC = "npp/dataset/trajectory"
DATASET_SERVICE = "npp/dataset/get"
POLICY_STATUS = "npp/policy/trajectories"
POLICY_DROPPED = "npp/policy/dropped_states"

# Service refusals that say "ask again": a caller retries these within its deadline; any other refusal
# (a bad request, a foreign plant) is final for that request.
BUSY = "busy:"
NOT_READY = "not ready:"

# Lockstep control: every state and action matters, so reliable with a short queue.
CONTROL_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
# Reports a monitor may read late: reliable, deeper queue.
REPORT_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
# Requests queue while one is served; rclpy's default service queue (KEEP_LAST 10) silently drops
# the oldest when more than 10 clients' requests are pending, so services keep a deep one.
SERVICE_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
# Latched: late joiners get the last value (both ends must use it).
LATCHED_QOS = QoSProfile(
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
    history=HistoryPolicy.KEEP_LAST,
)


def declare(node: Node, name: str, default: Any, description: str, *, read_only: bool = True) -> Any:
    """Declare a parameter with its descriptor and return its value."""
    descriptor = ParameterDescriptor(description=description, read_only=read_only)
    return node.declare_parameter(name, default, descriptor).value


def declare_all(node: Node, params: Sequence[tuple[str, Any, str]]) -> dict[str, Any]:
    """Declare every parameter; a value of the wrong type (gamma:=1 for a float) is a StartupError."""
    try:
        return {name: declare(node, name, default, description) for name, default, description in params}
    except ParameterException as exc:
        raise StartupError(
            f"{exc} (types follow the defaults: {', '.join(f'{n}={d!r}' for n, d, _ in params)})"
        ) from None


def float64_array(values: Any) -> array[float]:
    """A float64 array.array: the fast path of rosidl's sequence setters."""
    out = array("d")
    out.frombytes(np.ascontiguousarray(values, dtype=np.float64).tobytes())
    return out


def parameter_help(params: Sequence[tuple[str, Any, str]]) -> str:
    lines = ["parameters (--ros-args -p name:=value):"]
    lines += [f"  {name:<18} {description} (default: {default!r})" for name, default, description in params]
    return "\n".join(lines)


def trajectory_arrays(states: Sequence[float], actions: Sequence[float], values: Sequence[float],
                      state_dim: int, action_dim: int) -> Trajectory:  # fmt: skip
    """Row-major message arrays -> a validated core Trajectory (raises DatasetError)."""
    steps = len(values)
    s = np.asarray(states, dtype=np.float64)
    a = np.asarray(actions, dtype=np.float64)
    if state_dim <= 0 or action_dim <= 0 or s.size != steps * state_dim or a.size != steps * action_dim:
        raise DatasetError(
            f"trajectory arrays do not fit: {steps} values, {s.size} state entries (state_dim {state_dim}), "
            f"{a.size} action entries (action_dim {action_dim})"
        )
    return Trajectory.validated(s.reshape(steps, state_dim), a.reshape(steps, action_dim), values)


def run_node(factory: Callable[[], Node], argv: Sequence[str] | None = None, usage: str = "") -> int:
    """The Jazzy idiom: init, spin, and on Ctrl-C or external shutdown destroy and try_shutdown."""
    args = list(sys.argv if argv is None else argv)
    if any(a in ("-h", "--help") for a in args[1:]) and "--ros-args" not in args:
        print(usage)
        return 0
    rclpy.init(args=args)
    node: Node | None = None
    executor = SingleThreadedExecutor()
    try:
        node = factory()
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except StartupError as exc:
        print(f"{args[0]}: {exc}", file=sys.stderr)
        return 2
    finally:
        try:
            if node is not None:
                node.destroy_node()
            rclpy.try_shutdown()
        except KeyboardInterrupt:  # a second Ctrl-C while shutting down
            pass
    return int(getattr(node, "exit_code", 0))


class ThrottledWarnings:
    """At most one warning per kind and second, with a count of what was suppressed: a flood of bad
    input must show up in the log without drowning it."""

    def __init__(self, node: Node, every_s: float = 1.0) -> None:
        self.node, self.every_s = node, every_s
        self._last: dict[str, tuple[float, int]] = {}
        self.counts: dict[str, int] = {}

    def __call__(self, kind: str, message: str) -> None:
        self.counts[kind] = self.counts.get(kind, 0) + 1
        now = time.monotonic()
        last, suppressed = self._last.get(kind, (-float("inf"), 0))
        if now - last < self.every_s:
            self._last[kind] = (last, suppressed + 1)
            return
        extra = f" ({suppressed} more like it suppressed)" if suppressed else ""
        self.node.get_logger().warning(message + extra)
        self._last[kind] = (now, 0)


class StartupError(RuntimeError):
    """A node refuses to start; the message says why."""
