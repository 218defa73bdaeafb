"""npp-identify on a bag: the joint states and commands a ros2_control robot's topics carry, as an MCAP bag holds them,
identify the robot exactly as the in-process recording they were written from does."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from rclpy.serialization import serialize_message
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from npp_ros.identification.excitation import multisine
from npp_ros.identification.fit import identify
from npp_ros.identification.recording import Recording, record_motion
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.uncertainty import Robot
from npp_ros_graph.tools.bag import BagWriter, qos_entry
from npp_ros_graph.tools.identify import main as npp_identify
from npp_ros_graph.transport.convert import stamp


def write_bag(folder: Path, recording: Recording, dt: float, joint_state: Callable[[np.ndarray], JointState]) -> int:
    """A robot's recording as its ros2_control topics carry it, in an MCAP bag: ``joint_state`` makes each state's
    message; each command follows its state by 3 ms. Returns the last state's log time (ns)."""
    bag = BagWriter(folder)
    qos = [qos_entry(reliable=False, transient_local=False, depth=1)]
    states = bag.add_topic("/joint_states", "sensor_msgs/msg/JointState", qos)
    commands = bag.add_topic("/forward_effort_controller/commands", "std_msgs/msg/Float64MultiArray", qos)
    start = 1_700_000_000 * 10**9
    at = start
    for t, (state, command) in enumerate(zip(recording.states, recording.commands, strict=True)):
        at = start + round(t * dt * 1e9)
        msg = joint_state(state)
        msg.header.stamp = stamp(at)
        bag.write(states, serialize_message(msg), at)
        bag.write(commands, serialize_message(Float64MultiArray(data=[float(c) for c in command])), at + 3_000_000)
    bag.write(commands, serialize_message(Float64MultiArray(data=[1.0, 2.0, 3.0])), at + 4_000_000)  # wrong size
    bag.close()
    return at


def test_a_bag_of_joint_states_and_commands_identifies_the_robot(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    task = get_task("pendulum_swingup")
    plant = task.make_plant(0)
    robot = Robot((("mass", "pole", 1.1), ("gear", "torque", 0.9), ("damping", "hinge", 1.3)), 1, 1e-3, 2)
    excitation = multisine(plant, 3.0)
    recording = record_motion(plant, robot, lambda x: np.array([0.6 * np.sign(x[1])]), [math.pi, 0.0],
                              excitation.steps, excitation.apply)  # fmt: skip
    # another joint first, and no effort (an empty sequence, which rosbags alone does not decode); a command of the
    # wrong size at the end, which a robot ignores too
    write_bag(tmp_path / "robot", recording, plant.dt,
              lambda x: JointState(name=["wheel", "hinge"], position=[0.0, x[0]], velocity=[0.0, x[1]]))  # fmt: skip
    assert npp_identify([str(tmp_path / "robot"), "--task", "pendulum_swingup", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)["identification"]
    direct = identify(task, recording).record()
    assert out["delay"] == direct["delay"] == 1 and out["transitions"] == direct["transitions"]
    for got, want in zip(out["combinations"], direct["combinations"], strict=True):
        assert got["label"] == want["label"] and got["value"] == pytest.approx(want["value"], rel=1e-9)
    assert out["verdict"] == "inside"
    assert npp_identify([str(tmp_path / "robot"), "--task", "pendulum_swingup", "--command-topic", "/other"]) == 2
    assert "0 commands on /other" in capsys.readouterr().err


def test_a_reach_whose_state_holds_a_target_is_identified_from_its_joints_alone(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A robot measures its own joints, never the target a task's state holds (npp-robot leaves the target joints out
    of /joint_states): a bag of such a robot identifies it as its in-process recording does."""
    reach = str(Path(__file__).resolve().parents[1] / "fixtures" / "point_reach" / "task.toml")
    task = get_task(reach)
    plant = task.make_plant(0)
    robot = Robot((("mass", "mass", 1.4), ("damping", "mass_x", 0.8), ("damping", "mass_y", 1.2)))
    excitation = multisine(plant, 2.0)
    s0 = np.array([0.02, -0.01, 0.05, 0.03, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # mass x, y; target x, y, z; then rates
    recording = record_motion(plant, robot, lambda x: np.zeros(2), s0, excitation.steps, excitation.apply)

    def mass_joints(x: np.ndarray) -> JointState:  # the mass's joints only, in another order: no target joint
        return JointState(name=["mass_y", "mass_x"], position=[x[1], x[0]], velocity=[x[6], x[5]])

    write_bag(tmp_path / "robot", recording, plant.dt, mass_joints)
    assert npp_identify([str(tmp_path / "robot"), "--task", reach, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)["identification"]
    direct = identify(task, recording).record()
    for got, want in zip(out["combinations"], direct["combinations"], strict=True):
        assert got["label"] == want["label"] and got["value"] == pytest.approx(want["value"], rel=1e-6)
    assert out["verdict"] == direct["verdict"] == "inside"
