"""dm_control point_mass's reward written as a task file: a control term over several actuators is the mean of their
tolerances, and a term's floor lifts it as dm_control's (4 + small_control) / 5 does."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from dm_control.utils.rewards import tolerance

from npp_ros.tasks.registry import get_task
from npp_ros.tasks.task_file.loader import TaskFileError, load_task_file

MODEL = """<mujoco model="point_mass_like">
  <option timestep="0.02"/>
  <worldbody>
    <site name="target" pos="0.1 -0.05 0.01" size=".015"/>
    <body name="mass">
      <joint name="root_x" type="slide" axis="1 0 0" damping="1"/>
      <joint name="root_y" type="slide" axis="0 1 0" damping="1"/>
      <geom type="sphere" size=".01" mass=".3"/>
      <site name="mass" size=".01"/>
    </body>
  </worldbody>
  <actuator>
    <motor name="t1" joint="root_x" gear=".1" ctrlrange="-1 1" ctrllimited="true"/>
    <motor name="t2" joint="root_y" gear=".1" ctrlrange="-1 1" ctrllimited="true"/>
  </actuator>
</mujoco>
"""

TASK = """model = "point_mass.xml"
horizon = 50
epsilon = 1.0

[state]
joints = ["root_x", "root_y"]

[rho]
root_x = { position = [-0.2, 0.2] }
root_y = { position = [-0.2, 0.2] }

[reward]
combine = "product"
[[reward.terms]]                  # near_target: within the target's radius, margin one radius
site_distance = ["mass", "target"]
bounds = [0.0, 0.015]
margin = 0.015
[[reward.terms]]                  # small_control = (4 + mean of the two controls' tolerances) / 5
control = ["t1", "t2"]
margin = 1.0
value_at_margin = 0.0
sigmoid = "quadratic"
floor = 0.8
"""


def point_mass_reward(physics: object) -> float:
    """dm_control's point_mass get_reward, its distance taken between the two sites."""
    data = physics.data  # type: ignore[attr-defined]
    near = tolerance(float(np.linalg.norm(data.site_xpos[1] - data.site_xpos[0])), bounds=(0, 0.015), margin=0.015)
    small = tolerance(np.asarray(data.ctrl), margin=1, value_at_margin=0, sigmoid="quadratic").mean()
    return float(near * (small + 4) / 5)


def write(tmp_path: Path, task: str = TASK) -> Path:
    (tmp_path / "point_mass.xml").write_text(MODEL)
    (tmp_path / "task.toml").write_text(task)
    return tmp_path / "task.toml"


def test_the_file_gives_point_mass_s_reward_step_by_step(tmp_path: Path) -> None:
    task = get_task(str(write(tmp_path)))
    plant = task.make_plant(0)
    rng = np.random.default_rng(0)
    for _ in range(20):  # near the target (both factors matter) and farther out
        plant.reset(np.r_[0.1, -0.05, 0.0, 0.0] + rng.uniform(-0.03, 0.03, 4))
        for _ in range(3):
            reward = plant.step(rng.uniform(-1.5, 1.5, 2))  # beyond ctrlrange too: the clamped control is judged
            assert reward == pytest.approx(point_mass_reward(plant.physics), abs=1e-12)
    expert = task.make_expert(0, 10)
    trajectory = expert.trajectory(task.initial_state(0, 0), 10)  # the mean term gives the expert its cost too
    assert np.isfinite(trajectory.values).all()


@pytest.mark.parametrize(
    ("old", "new", "words"),
    [
        ('control = ["t1", "t2"]', 'control = ["t1", "t3"]', r"reward.terms\[1\].control: unknown actuator 't3'"),
        ('control = ["t1", "t2"]', "control = []", r"reward.terms\[1\].control: must name at least one actuator"),
        ("floor = 0.8", "floor = 1.0", r"reward.terms\[1\].floor: must lie in \[0, 1\), got 1.0"),
    ],
)
def test_a_bad_mean_or_floor_is_refused_naming_the_key(tmp_path: Path, old: str, new: str, words: str) -> None:
    with pytest.raises(TaskFileError, match=words):
        load_task_file(str(write(tmp_path, TASK.replace(old, new))))
