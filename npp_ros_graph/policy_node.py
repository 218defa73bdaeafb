"""npp-policy: answers every plant state with the greedy NPP action from the current dataset.

The dataset arrives trajectory by trajectory on /npp/dataset/trajectory; on start, after a
restart, or when it sees a gap in the trajectory indices, the node catches up through the
supervisor's /npp/dataset/get service, so nothing else needs restarting. With no data it says
so and publishes nothing: it never invents an action.

States are answered by a worker thread from a one-state mailbox: the executor keeps taking
states off the wire while an action is computed, and a state overtaken by a newer one before it
was answered is dropped (counted on /npp/policy/dropped_states and in the log). Under a state
stream faster than the policy, it answers the newest state and never builds a queue.
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass

import numpy as np
from builtin_interfaces.msg import Time
from npp_interfaces.msg import PlantDescription
from npp_interfaces.msg import Trajectory as TrajectoryMsg
from npp_interfaces.srv import GetTrajectories
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import UInt32, UInt64

from npp_ros.bounds import NonparametricPolicy
from npp_ros.dataset import Dataset, DatasetError
from npp_ros_graph.common import (
    ACTION,
    CONTROL_QOS,
    DATASET_SERVICE,
    DATASET_TOPIC,
    LATCHED_QOS,
    PLANT,
    POLICY_DROPPED,
    POLICY_STATUS,
    REPORT_QOS,
    STATE,
    ThrottledWarnings,
    run_node,
)
from npp_ros_graph.convert import action_to_joint_state, state_from_joint_state, trajectory_from_msg
from npp_ros_graph.parameters import declare_settings

CATCH_UP_TIMEOUT_S = 5.0  # a catch-up request unanswered this long is withdrawn and sent again
REPORT_EVERY_S = 1.0

USAGE = f"""npp-policy: greedy NPP actions for every state (ROS 2 node "npp_policy").

subscribes  /{STATE} (sensor_msgs/JointState), /{PLANT} (latched), /{DATASET_TOPIC}
publishes   /{ACTION} (sensor_msgs/JointState: effort = action, stamp = the answered state's)
            /{POLICY_STATUS} (std_msgs/UInt32, latched: trajectories held)
            /{POLICY_DROPPED} (std_msgs/UInt64: states dropped so far because a newer one arrived
            before they were answered; published when it changes, at most every {REPORT_EVERY_S:g} s)
calls       /{DATASET_SERVICE} to catch up with the supervisor's dataset
parameters  none: L and the data come from the supervisor, the plant from the sim

A state with wrong joint names or counts, or non-finite values, is refused with a log line.
"""


@dataclass(frozen=True)
class PolicySettings:
    """None: L and the data come from the supervisor, the plant from the sim (a stray -p is refused)."""


class PolicyNode(Node):
    def __init__(self) -> None:
        super().__init__("npp_policy")
        declare_settings(self, (), PolicySettings)
        self.plant: PlantDescription | None = None
        self.dataset: Dataset | None = None
        self.policy: NonparametricPolicy | None = None
        self._catch_up_future = None
        self._catch_up_sent = 0.0
        self._catch_up_needed = True
        # The answer thread reads the dataset while the executor appends to it: one lock for both.
        self._data_lock = threading.Lock()
        self._mailbox: tuple[np.ndarray, Time] | None = None
        self._mail = threading.Condition()
        self._closing = False
        self.dropped = 0  # states overtaken by a newer one before they were answered
        self.answered = 0
        self._dropped_reported = 0
        self._warn = ThrottledWarnings(self)
        self.action_pub = self.create_publisher(JointState, ACTION, CONTROL_QOS)
        self.status_pub = self.create_publisher(UInt32, POLICY_STATUS, LATCHED_QOS)
        self.dropped_pub = self.create_publisher(UInt64, POLICY_DROPPED, REPORT_QOS)
        self.create_subscription(PlantDescription, PLANT, self.on_plant, LATCHED_QOS)
        self.create_subscription(TrajectoryMsg, DATASET_TOPIC, self.on_trajectory, REPORT_QOS)
        self.create_subscription(JointState, STATE, self.on_state, CONTROL_QOS)
        self.dataset_client = self.create_client(GetTrajectories, DATASET_SERVICE)
        self.create_timer(0.5, self.maybe_catch_up)
        self.create_timer(REPORT_EVERY_S, self.report_dropped)
        self._answerer = threading.Thread(target=self._answer_loop, name="npp-policy-answers", daemon=True)
        self._answerer.start()

    # ---------------------------------------------------------------- dataset
    def on_plant(self, msg: PlantDescription) -> None:
        if self.plant is not None and (msg.task, msg.seed) != (self.plant.task, self.plant.seed):
            self.get_logger().error(f"plant changed from {self.plant.task} to {msg.task}; restart the policy")
            return
        if self.plant is None:
            self.plant = msg
            self.dataset = Dataset(msg.state_dim, msg.action_dim)
            self.get_logger().info(f"plant {msg.task} seed {msg.seed}; catching up with the dataset")

    def on_trajectory(self, msg: TrajectoryMsg) -> None:
        if self.dataset is None or self.policy is None:
            self._catch_up_needed = True
            return
        held = self.dataset.num_trajectories
        if msg.index < held:
            return  # already have it (catch-up and topic overlap)
        if msg.index > held:
            self._catch_up_needed = True  # missed some: fetch them in order
            return
        self._append(msg)

    def _append(self, msg: TrajectoryMsg) -> bool:
        assert self.dataset is not None
        try:
            _, traj = trajectory_from_msg(msg)
            with self._data_lock:
                self.dataset.append(traj)
        except DatasetError as exc:
            self.get_logger().error(f"trajectory {msg.index} refused: {exc}")
            return False
        self.status_pub.publish(UInt32(data=self.dataset.num_trajectories))
        return True

    def maybe_catch_up(self) -> None:
        pending = self._catch_up_future
        if pending is not None:
            # A supervisor killed mid-request, or a response Fast DDS dropped before it matched this
            # (new) client, never answers: withdraw the request and ask again, or catch-up stalls forever.
            if time.monotonic() - self._catch_up_sent < CATCH_UP_TIMEOUT_S:
                return
            self.dataset_client.remove_pending_request(pending)
            self._catch_up_future = None
            self.get_logger().warning(f"no catch-up answer within {CATCH_UP_TIMEOUT_S:g} s; asking again")
        if self.dataset is None or not self._catch_up_needed:
            return
        if not self.dataset_client.service_is_ready():
            self.get_logger().info("waiting for the supervisor's dataset service", throttle_duration_sec=10.0)
            return
        request = GetTrajectories.Request(start=self.dataset.num_trajectories, max_count=50)
        self._catch_up_sent = time.monotonic()
        self._catch_up_future = future = self.dataset_client.call_async(request)
        future.add_done_callback(self.on_catch_up)

    def on_catch_up(self, future) -> None:
        if future is not self._catch_up_future:
            return  # a withdrawn request answered late
        self._catch_up_future = None
        response = future.result()
        if response is None or not response.success:
            self.get_logger().warning(f"catch-up failed: {getattr(response, 'message', 'no response')}")
            return
        if self.policy is None:
            assert self.dataset is not None
            with self._data_lock:
                self.policy = NonparametricPolicy(self.dataset, response.lipschitz)
            self.get_logger().info(f"acting greedily with L = {response.lipschitz:g} ({response.lipschitz_source})")
        for msg in response.trajectories:
            if msg.index == self.dataset.num_trajectories and not self._append(msg):
                break
        self._catch_up_needed = self.dataset.num_trajectories < response.total
        self.status_pub.publish(UInt32(data=self.dataset.num_trajectories))
        if not self._catch_up_needed:
            self.get_logger().info(f"holding {self.dataset.num_trajectories} trajectories ({len(self.dataset)} points)")

    # ---------------------------------------------------------------- acting
    def on_state(self, msg: JointState) -> None:
        """Executor side: validate and leave the state in the mailbox; an unanswered older one is dropped."""
        try:
            state = self._state(msg)
        except ValueError as exc:
            problem = str(exc)
            self._warn(problem.split(":")[0], f"state refused: {problem}")
            return
        with self._mail:
            if self._mailbox is not None:
                self.dropped += 1
            self._mailbox = (state, msg.header.stamp)
            self._mail.notify()

    def _state(self, msg: JointState) -> np.ndarray:
        """The state a message carries, if the policy can answer it; else a ValueError saying why not."""
        plant = self.plant
        if plant is None:
            raise ValueError("no plant description yet: cannot read states")
        if self.policy is None or self.dataset is None or len(self.dataset) == 0:
            raise ValueError("no data yet: the policy has no action to give")
        return state_from_joint_state(msg, plant.joint_names)

    def _answer_loop(self) -> None:
        """Answer thread: always the newest state; whatever arrived meanwhile replaced it.

        When no state waits it brings the search index up to date with newly appended data, so
        index builds and merges (seconds at 10^6 points) happen between episodes, not inside a
        control step.
        """
        while True:
            with self._mail:
                ready = self._mail.wait_for(lambda: self._mailbox is not None or self._closing, timeout=0.1)
                if self._closing:
                    return
                if not ready:
                    msg = None
                else:
                    msg, self._mailbox = self._mailbox, None
            if msg is None:
                self._warm_index()
                continue
            try:
                self._answer(*msg)
            except Exception as exc:  # the answer thread must outlive any single bad state
                self.get_logger().error(f"could not answer a state: {type(exc).__name__}: {exc}")

    def _warm_index(self) -> None:
        policy = self.policy
        if policy is None or policy.index is None:
            return
        with self._data_lock:
            policy.index.sync()

    def _answer(self, state: np.ndarray, stamp: Time) -> None:
        assert self.policy is not None and self.plant is not None
        with self._data_lock:
            action = self.policy.act(state)
        self.action_pub.publish(action_to_joint_state(action, self.plant.actuated_joint_names, stamp))
        self.answered += 1

    def report_dropped(self) -> None:
        dropped = self.dropped
        if dropped == self._dropped_reported:
            return
        self.dropped_pub.publish(UInt64(data=dropped))
        self.get_logger().warning(
            f"dropped {dropped - self._dropped_reported} stale states in the last {REPORT_EVERY_S:g} s "
            f"({dropped} in all, {self.answered} answered): states arrive faster than the policy answers; "
            "each was overtaken by a newer one"
        )
        self._dropped_reported = dropped

    def destroy_node(self) -> None:
        with self._mail:
            self._closing = True
            self._mail.notify()
        self._answerer.join(timeout=5.0)
        super().destroy_node()


def main(argv: list[str] | None = None) -> int:
    return run_node(PolicyNode, argv, USAGE)


if __name__ == "__main__":
    sys.exit(main())
