"""The model monitor on MuJoCo robots drawn inside the certified set and built outside it (no ROS): its false alarms
inside and how many transitions it takes to say a robot is outside. Run with -s to see the figures:

    .venv/bin/python -m pytest tests/test_model_monitor.py -s -p no:xdist

Everything here is computed, not timed: the robots, their s0 and their commands come from fixed seeds."""

from __future__ import annotations

import numpy as np
import pytest

from npp_ros.deployment.model_monitor import ModelMonitor, hull_distance
from npp_ros.tasks.registry import get_task
from npp_ros.tasks.uncertainty import Robot, RobotEffects, UncertaintySet, as_robot, model_elements

STEPS = 200


def detection(task_name: str, robots: UncertaintySet, robot: Robot, episode: int, monitor: ModelMonitor) -> int | None:
    """The first transition at which the monitor says the robot is outside (None: never in STEPS), with random
    commands across the actuators' range, each sent as the robot applies it (after its delay)."""
    task = get_task(task_name)
    plant = task.make_plant(0)
    rng = np.random.default_rng(episode)
    effects = RobotEffects(robot, plant.action_dim)
    monitor.restart()
    monitor.recent.clear()
    low, high = np.maximum(plant.action_low, -1.0), np.minimum(plant.action_high, 1.0)
    with as_robot(plant, robot):
        plant.reset(task.initial_state(0, episode))
        for step in range(STEPS):
            action = rng.uniform(low, high)
            raw = plant.raw_state() if hasattr(plant, "raw_state") else plant.state()
            monitor.observe(effects.observe(raw), action)
            if monitor.outside:
                return step
            plant.step(effects.command(action))
    return None


def every(kind: str, parameter: str, factor: float, task_name: str) -> Robot:
    names = model_elements(get_task(task_name).make_plant(0).physics.model)[kind]
    return Robot(tuple((parameter, name, factor) for name in names))


@pytest.mark.parametrize("task_name", ["pendulum_swingup", "cartpole_swingup"])
def test_no_false_alarm_inside_the_set_and_robots_outside_it_are_found(task_name: str) -> None:
    task = get_task(task_name)
    plant = task.make_plant(0)
    robots = task.uncertainty.resolved(plant.physics.model)
    monitor = ModelMonitor.of_plant(plant, robots)
    inside = [detection(task_name, robots, robots.draw(0, e), e, monitor) for e in range(10)]
    exceeded = f"{monitor.exceeded} of {monitor.checked} transitions exceeded"
    print(f"\n{task_name}: {len(monitor.corners)} corners; inside the set, 10 drawn robots x {STEPS} steps: "
          f"{sum(x is not None for x in inside)} alarms, {exceeded}")  # fmt: skip
    assert inside == [None] * 10, inside
    outside = {
        "gear x2.5": every("actuator", "gear", 2.5, task_name),
        "gear x0.4": every("actuator", "gear", 0.4, task_name),
        "mass x4": every("body", "mass", 4.0, task_name),
        "damping x5": every("joint", "damping", 5.0, task_name),
        "delay 3": Robot((), action_delay=3),
    }
    found = {}
    for label, robot in outside.items():
        assert robots.contains(robot), label
        found[label] = [detection(task_name, robots, robot, e, monitor) for e in range(5)]
        times = [x for x in found[label] if x is not None]
        median = f"median {int(np.median(times))} transitions" if times else "never"
        print(f"  outside, {label}: found in {len(times)} of 5 episodes of {STEPS} steps, {median} ({found[label]})")
    assert all(x is not None for x in found["gear x2.5"]), found  # far outside: found every time
    assert sum(x is not None for x in found["delay 3"]) >= 3, found


def test_the_hull_distance_is_zero_inside_and_the_gap_outside() -> None:
    square = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    assert hull_distance(square, np.array([0.3, 0.6])) < 1e-9
    assert hull_distance(square, np.array([2.0, 0.5])) == pytest.approx(1.0, abs=1e-6)


def test_only_consecutive_states_are_checked_and_the_exact_model_explains_itself() -> None:
    task = get_task("lqr_2_1")
    plant = task.make_plant(0)
    robots = UncertaintySet()
    monitor = ModelMonitor.of_plant(plant, robots, window=3)
    plant.reset(task.initial_state(0, 0))
    previous = None
    for step in range(5):
        action = np.array([0.5 * (-1) ** step])
        check = monitor.observe(plant.state(), action)
        assert (check is None) == (step < 2)  # a chain needs delay + late + 1 = 2 commands before a check
        if check is not None:
            assert not check.exceeds and check.error < 1e-9 and check.delay == 0, check
        plant.step(action)
        previous = check
    assert previous is not None and not monitor.outside and "0 of the last 3" in monitor.summary()
    monitor.restart()
    assert monitor.observe(plant.state(), np.zeros(1)) is None
