"""npp-policy: answers every plant state with the greedy NPP action from the current dataset.

The dataset arrives trajectory by trajectory on /npp/dataset/trajectory; on start, after a
restart, or when it sees a gap in the trajectory indices, the node catches up through the
supervisor's /npp/dataset/get service, so nothing else needs restarting. With no data it says
so and publishes nothing: it never invents an action.
"""

from __future__ import annotations

import sys

import numpy as np
from npp_interfaces.msg import PlantDescription
from npp_interfaces.msg import Trajectory as TrajectoryMsg
from npp_interfaces.srv import GetTrajectories
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import UInt32

from nodes.common import (
    ACTION,
    CONTROL_QOS,
    DATASET_SERVICE,
    DATASET_TOPIC,
    LATCHED_QOS,
    PLANT,
    POLICY_STATUS,
    REPORT_QOS,
    STATE,
    run_node,
    trajectory_arrays,
)
from npp_ros.bounds import NonparametricPolicy
from npp_ros.dataset import Dataset, DatasetError

USAGE = f"""npp-policy: greedy NPP actions for every state (ROS 2 node "npp_policy").

subscribes  /{STATE} (sensor_msgs/JointState), /{PLANT} (latched), /{DATASET_TOPIC}
publishes   /{ACTION} (sensor_msgs/JointState: effort = action, stamp = the answered state's)
            /{POLICY_STATUS} (std_msgs/UInt32, latched: trajectories held)
calls       /{DATASET_SERVICE} to catch up with the supervisor's dataset
parameters  none: L and the data come from the supervisor, the plant from the sim
"""


class PolicyNode(Node):
    def __init__(self) -> None:
        super().__init__("npp_policy")
        self.plant: PlantDescription | None = None
        self.dataset: Dataset | None = None
        self.policy: NonparametricPolicy | None = None
        self.lipschitz: float | None = None
        self.pending: TrajectoryMsg | None = None
        self._catch_up_future = None
        self._catch_up_needed = True
        self.action_pub = self.create_publisher(JointState, ACTION, CONTROL_QOS)
        self.status_pub = self.create_publisher(UInt32, POLICY_STATUS, LATCHED_QOS)
        self.create_subscription(PlantDescription, PLANT, self.on_plant, LATCHED_QOS)
        self.create_subscription(TrajectoryMsg, DATASET_TOPIC, self.on_trajectory, REPORT_QOS)
        self.create_subscription(JointState, STATE, self.on_state, CONTROL_QOS)
        self.dataset_client = self.create_client(GetTrajectories, DATASET_SERVICE)
        self.create_timer(0.5, self.maybe_catch_up)

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
            traj = trajectory_arrays(msg.states, msg.actions, msg.values, msg.state_dim, msg.action_dim)
            self.dataset.append(traj)
        except DatasetError as exc:
            self.get_logger().error(f"trajectory {msg.index} refused: {exc}")
            return False
        self.status_pub.publish(UInt32(data=self.dataset.num_trajectories))
        return True

    def maybe_catch_up(self) -> None:
        if self.dataset is None or not self._catch_up_needed or self._catch_up_future is not None:
            return
        if not self.dataset_client.service_is_ready():
            self.get_logger().info("waiting for the supervisor's dataset service", throttle_duration_sec=10.0)
            return
        request = GetTrajectories.Request(start=self.dataset.num_trajectories, max_count=50)
        self._catch_up_future = self.dataset_client.call_async(request)
        self._catch_up_future.add_done_callback(self.on_catch_up)

    def on_catch_up(self, future) -> None:
        self._catch_up_future = None
        response = future.result()
        if response is None or not response.success:
            self.get_logger().warning(f"catch-up failed: {getattr(response, 'message', 'no response')}")
            return
        if self.policy is None:
            self.lipschitz = response.lipschitz
            assert self.dataset is not None
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
        if self.policy is None or self.dataset is None or len(self.dataset) == 0:
            self.get_logger().warning("no data yet: the policy has no action to give", throttle_duration_sec=5.0)
            return
        state = np.concatenate([np.asarray(msg.position, dtype=np.float64), np.asarray(msg.velocity)])
        try:
            action = self.policy.act(state)
        except DatasetError as exc:
            self.get_logger().warning(f"state refused: {exc}", throttle_duration_sec=5.0)
            return
        assert self.plant is not None
        out = JointState()
        out.header.stamp = msg.header.stamp
        out.name = list(self.plant.actuated_joint_names)
        out.effort = action.tolist()
        self.action_pub.publish(out)


def main(argv: list[str] | None = None) -> int:
    return run_node(PolicyNode, argv, USAGE)


if __name__ == "__main__":
    sys.exit(main())
