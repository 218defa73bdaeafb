"""The gate under model uncertainty: a robot's description inside the certified set is accepted and named, one
outside is refused naming the parameter, the element, the robot's value and the range; an exact-model run still
needs the exact model. No ROS: the comparison is the core's (npp_ros.deployment.robot_set)."""

from __future__ import annotations

import copy
import re
from pathlib import Path

import pytest
from deploy_runs import FINGERPRINT, SEED, TASK, make_run, with_robots

from npp_ros.deployment.gate import Acceptance, GateRefusal, load_deployment
from npp_ros.deployment.robot_model import DescriptionError, mjcf_fingerprint, model_mjcf
from npp_ros.deployment.robot_set import compiled, match_model, robot_mjcf
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.uncertainty import ModelParameters, Robot, model_elements


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("robot-set")
    exact = make_run(root / "exact")
    return exact, with_robots(root / "robots")


def described(robot: Robot, task: str = TASK) -> str:
    text = robot_mjcf(get_task(task).make_plant(SEED), robot)
    assert text is not None
    return text


@pytest.mark.parametrize("task", ["pendulum_swingup", "cartpole_swingup", "acrobot_swingup", "lqr_2_1"])
def test_a_robots_mjcf_compiles_to_the_model_the_robot_makes_of_the_plant(task: str) -> None:
    plant = get_task(task).make_plant(SEED)
    elements = model_elements(plant.physics.model)
    robot = Robot((("mass", elements["body"][-1], 1.1), ("gear", elements["actuator"][0], 0.9),
                   ("damping", elements["joint"][0], 1.3)))  # fmt: skip
    applied = copy.deepcopy(plant.physics.model.ptr)
    ModelParameters(applied).apply(robot)
    twin = copy.copy(plant)
    twin.physics = type("P", (), {"model": applied})()
    assert mjcf_fingerprint(plant, described(robot, task)) == twin.model_sha256()


def test_a_description_inside_the_set_is_accepted_and_named(runs) -> None:
    _, robots = runs
    inside = Robot((("mass", "body_1", 1.15), ("gear", "motor_0", 0.85)))
    deployment = load_deployment(robots, Acceptance(robot_description=described(inside)))
    assert (
        deployment.robot
        == "the nominal model with mass of body_1 x1.15, gear of motor_0 x0.85, inside the certified set "
        "(whose certificate is an average over the set)"
    )
    assert "robot: the nominal model with mass of body_1 x1.15" in deployment.describe()
    nominal = load_deployment(robots, Acceptance(robot_description=described(Robot())))
    assert nominal.robot == "the nominal model, inside the certified set (whose certificate is an average over the set)"
    # The certified fingerprint alone places the nominal model in the set, as the operator's parameter gives it.
    assert load_deployment(robots, Acceptance(model_fingerprint=FINGERPRINT)).robot.startswith("the nominal model")


def test_a_description_outside_the_set_is_refused_naming_the_parameter_element_value_and_range(runs) -> None:
    _, robots = runs
    outside = Robot((("mass", "body_0", 1.3), ("gear", "motor_0", 0.9)))
    with pytest.raises(GateRefusal) as refused:
        load_deployment(robots, Acceptance(robot_description=described(outside)))
    assert "lies outside the certified set" in str(refused.value)
    reason = (
        "mass of body body_0: the robot's 5.44543 kg is x1.3 the certified 4.18879 kg, outside the certified range "
    )
    assert reason + "x[0.8, 1.2]" in str(refused.value), refused.value
    assert "gear" not in str(refused.value)  # 0.9 lies inside its range
    # What the set leaves alone must stay the certified model's: lqr's stiffness is drawn from the seed.
    other = model_mjcf(get_task(TASK).make_plant(SEED + 1))
    assert other is not None
    with pytest.raises(GateRefusal, match=r"jnt_stiffness differs from the certified model's \(entry \d"):
        load_deployment(robots, Acceptance(robot_description=other))
    with pytest.raises(GateRefusal, match="does not compile"):
        load_deployment(robots, Acceptance(robot_description="<mujoco><worldbody><body>"))
    # A fingerprint other than the certified one cannot place a robot in the set.
    with pytest.raises(GateRefusal, match="give the robot's MJCF"):
        load_deployment(robots, Acceptance(model_fingerprint="0" * 64))


def test_an_exact_model_certificate_still_needs_the_exact_model(runs) -> None:
    exact, _ = runs
    inside = described(Robot((("mass", "body_1", 1.01),)))
    with pytest.raises(GateRefusal, match="is not the certified one"):
        load_deployment(exact, Acceptance(model_fingerprint=mjcf_fingerprint(get_task(TASK).make_plant(SEED), inside),
                                          robot_description=inside))  # fmt: skip
    assert load_deployment(exact, Acceptance(model_fingerprint=FINGERPRINT)).robot == ""


def test_structure_is_compared_exactly_and_an_inertia_not_scaled_with_its_mass_is_refused() -> None:
    task = get_task("pendulum_swingup")
    plant = task.make_plant(0)
    nominal = plant.physics.model
    text = described(Robot((("damping", "hinge", 1.2),)), "pendulum_swingup")
    renamed = compiled(text.replace('name="hinge"', 'name="knee"').replace('joint="hinge"', 'joint="knee"'))
    match = match_model(nominal, renamed, task.uncertainty)
    assert not match.inside and "its joints are knee, the certified model's hinge" in match.reasons[0]
    heavier = described(Robot((("mass", "pole", 1.1),)), "pendulum_swingup")
    skewed = compiled(re.sub(r'diaginertia="[^"]*"', 'diaginertia="0.01 0.01 0.01"', heavier))
    assert any("inertia of body pole" in reason for reason in match_model(nominal, skewed, task.uncertainty).reasons)
    assert match_model(nominal, compiled(text), task.uncertainty).inside
    with pytest.raises(DescriptionError):
        compiled("not xml")
