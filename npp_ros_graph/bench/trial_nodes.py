"""npp-trial's own node and the npp-robot it starts, for the command (bench/trial.py) and its ``--outside`` phase
(bench/trial_outside.py).

TrialNode is this process's side of an episode: npp-deploy's lifecycle client, the robot's joint states from s0 on
(every one kept: the trial replays them all) with the effort of each step, and on a reach s0's target, sent to
npp-deploy's target topic until the episode ends. spawn_robot starts npp-robot holding s0 until its first command;
wait_for_s0 waits until this node sees it hold s0. log is npp-trial's progress line on stderr.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np
from geometry_msgs.msg import Point, PointStamped
from lifecycle_msgs.srv import ChangeState
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from npp_ros.deployment.gate import Deployment
from npp_ros.deployment.joints import JointLayout
from npp_ros.tasks.uncertainty import Robot
from npp_ros_graph.bench.ros_loop import spawn, wait_for
from npp_ros_graph.transport.topics import CONTROL_QOS, JOINT_STATES

TARGET, TARGET_FRAME = "/npp_deploy/target", "world"  # npp-deploy's target_topic and target_frame defaults
TARGET_PERIOD_S = 0.1  # a reach's target, sent again this often (npp-deploy takes the newest)
FIRST_TRIAL_EPISODE = 10**6  # s0 of episodes no run draws: fresh for the policy
START_TIMEOUT_S = 120.0  # a robot process importing rclpy and MuJoCo on a busy machine
# Every joint state of an episode is kept: the trial replays them all.
KEEP_ALL = QoSProfile(depth=100_000, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)


def log(text: str) -> None:
    sys.stderr.write(f"npp-trial: {text}\n")
    sys.stderr.flush()


class TrialNode(Node):
    """This process's side: npp-deploy's lifecycle client, and the robot's joint states of one episode."""

    def __init__(self, layout: JointLayout) -> None:
        super().__init__("npp_trial")
        self.change = self.create_client(ChangeState, "/npp_deploy/change_state")
        self.layout = layout
        self.s0 = np.zeros(0)
        self.raws: list[np.ndarray] = []  # [qpos, qvel] from s0 on
        self.efforts: list[np.ndarray] = []  # efforts[k]: the command applied in step k
        self.create_subscription(JointState, JOINT_STATES, self.on_state, KEEP_ALL)
        self.target: PointStamped | None = None  # a reach: s0's target, sent to npp-deploy until the episode ends
        if layout.target is not None:
            self.target_pub = self.create_publisher(PointStamped, TARGET, CONTROL_QOS)
            self.create_timer(TARGET_PERIOD_S, self.send_target)

    def expect(self, s0: np.ndarray) -> None:
        """A new episode from s0: what came before is dropped; a reach aims at s0's target."""
        self.s0, self.raws, self.efforts = s0, [], []
        if self.layout.target is not None and s0.size:
            self.layout.aim_as(s0)  # the robot measures no target: its states hold s0's, as the task stores them
            point = self.layout.target.point(self.layout.aimed)
            self.target = PointStamped(point=Point(x=float(point[0]), y=float(point[1]), z=float(point[2])))
            self.target.header.frame_id = TARGET_FRAME
            self.send_target()
        elif not s0.size:
            self.target = None

    def send_target(self) -> None:
        if self.target is not None:
            self.target.header.stamp = self.get_clock().now().to_msg()
            self.target_pub.publish(self.target)

    def on_state(self, msg: JointState) -> None:
        """The robot publishes s0 while it waits for its first command; the episode starts with the
        last of those, and each message after it is the state after a step and that step's effort."""
        if self.s0.size == 0:
            return
        raw = self.layout.state(msg.name, msg.position, msg.velocity)
        if not self.efforts and np.array_equal(raw, self.s0):
            self.raws = [raw]
            return
        if not self.raws:
            return  # a message of the last episode's robot
        where = [list(msg.name).index(name) for name in self.layout.command_joints]
        self.raws.append(raw)
        self.efforts.append(np.array([msg.effort[i] for i in where]))


def ros_args(params: dict[str, str]) -> list[str]:
    return [arg for name, value in params.items() for arg in ("-p", f"{name}:={value}")]


def spawn_robot(deployment: Deployment, s0: np.ndarray, robot: Robot | None, extra: dict[str, str],
                env: dict[str, str], log_path: Path) -> Any:  # fmt: skip
    """npp-robot holding ``s0`` until its first command, as ``robot`` (None: the task's model), with ``extra``
    parameters."""
    params = {"task": deployment.task.name, "seed": str(deployment.metadata.seed),
              "initial_state": ",".join(repr(float(x)) for x in s0), "start_on_command": "true"}  # fmt: skip
    if robot is not None:
        params["robot"] = f"'{robot.record()}'"  # a YAML string: the record's JSON braces would read as a mapping
    return spawn(["npp_ros_graph.nodes.robot", "--ros-args", *ros_args(params | extra)], env, log_path)


def wait_for_s0(executor: SingleThreadedExecutor, node: TrialNode, episode: int, logs: Path) -> None:
    """npp-deploy is inactive while the robot starts: this node sees the robot hold s0 before any command."""
    if not wait_for(executor, lambda: len(node.raws) > 0, START_TIMEOUT_S):
        raise RuntimeError(f"no joint state at episode {episode}'s s0 within {START_TIMEOUT_S:.0f} s; see {logs}")
