"""npp-identify on a bag: the robot's joint states and commands read from a rosbag2 MCAP bag, then identified.

The bag's two topics become the core's :class:`~npp_ros.identification.recording.Recording` here, in one place
(:func:`recording_from_bag`): each sensor_msgs/JointState assembled in the task's joint order by name
(npp_ros.deployment.joints, as npp-deploy reads them), each std_msgs/Float64MultiArray command put in the task's
actuator order, the two streams aligned on the bag's log times (the command in force when the robot next stepped),
and the rows kept on the states' own stamps. A reach's target (a task file's ``state.target``) is no joint a robot
measures: its entries are 0 in the recording, which changes no prediction (the loader checks that the target's body
moves nothing and nothing moves it). Everything else is the core's npp-identify (npp_ros.cli.identify).
Reading a bag needs no running ROS graph; the two messages are decoded by rclpy, as a live subscriber decodes them
(rosbags refuses a JointState whose effort is empty as rclpy writes it).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from npp_ros.cli import identify as core
from npp_ros.deployment.joints import JointLayout, NoTarget, parse_names
from npp_ros.identification.recording import Recording
from npp_ros.tasks.registry import Plant
from npp_ros_graph.tools.bag import BagError, read_messages
from npp_ros_graph.transport.topics import FORWARD_COMMANDS, JOINT_STATES


def recording_from_bag(
    folder: Path, plant: Plant, joint_states_topic: str = JOINT_STATES, command_topic: str = FORWARD_COMMANDS,
    command_joints: Sequence[str] = (),
) -> Recording:  # fmt: skip
    """The robot's motion in a bag folder as a Recording of ``plant``'s task (raw [qpos, qvel] and actions)."""
    layout = JointLayout.of_plant(plant, tuple(command_joints))
    wanted = (joint_states_topic.strip("/"), command_topic.strip("/"))
    state_times, stamps, states, command_times, commands = [], [], [], [], []
    try:
        for message in read_messages(folder, wanted, decode=False):
            if message.topic.strip("/").endswith(wanted[0]):
                msg = deserialize_message(message.raw, JointState)
                state_times.append(message.log_ns * 1e-9)
                stamps.append(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)
                try:
                    state = layout.state(list(msg.name), list(msg.position), list(msg.velocity))
                except NoTarget as no_target:  # a reach's target is no joint of the robot and moves nothing
                    state = no_target.raw
                states.append(state)
            else:
                data = np.asarray(deserialize_message(message.raw, Float64MultiArray).data, dtype=np.float64)
                if len(data) != len(layout.command_joints) or not np.isfinite(data).all():
                    continue  # a robot ignores such a command too
                command_times.append(message.log_ns * 1e-9)
                commands.append(layout.action(data))
    except BagError as exc:
        raise ValueError(str(exc)) from None
    if len(states) < 2 or not commands:
        raise ValueError(
            f"{folder} holds {len(states)} states on {joint_states_topic} and {len(commands)} commands on "
            f"{command_topic}: a recording needs both (name others with --joint-states-topic and --command-topic)"
        )
    return Recording.from_streams(
        np.array(state_times), np.array(states), np.array(command_times), np.array(commands), np.array(stamps)
    )


def read(source: Path, plant: Plant, args: argparse.Namespace) -> Recording:
    """npp-identify's reader: an .npz recording as the core reads it, any other path as a bag folder."""
    if source.suffix == ".npz":
        return Recording.load(source)
    return recording_from_bag(
        source, plant, args.joint_states_topic, args.command_topic, parse_names(args.command_joints)
    )


def main(argv: Sequence[str] | None = None) -> int:
    return core.main(argv, reader=read, bag_topics=(JOINT_STATES, FORWARD_COMMANDS))


if __name__ == "__main__":
    sys.exit(main())
