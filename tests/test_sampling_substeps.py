"""The sampling planner scores its plans on the plant's own control step: k MuJoCo steps per action.

With a control_timestep of k model timesteps the plant holds each action for k steps. A sampled plan
scored at one model step per action is scored on a clock k times slower than the plant's (after 50
actions at k = 4 it would stand at 50 model steps, the plant at 200): its rollouts must be the plant's.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from npp_ros.tasks.registry import ExpertOptions
from npp_ros.trajopt.receding import window_costs
from tests.test_task_file_substeps import S0, arm_task

SUBSTEPS = 4
WINDOW = 20
SAMPLING = (
    'warm_start = "zero"\nplanner = "sampling"\n'
    f"window = {WINDOW}\ncommit = 5\nwindow_iterations = 0\nsamples = 4\nrestarts = 0"
)


def test_sampled_plans_are_rolled_out_on_the_plants_control_step(tmp_path: Path) -> None:
    task = arm_task(
        tmp_path,
        **{"control_timestep = 0.01": f"control_timestep = {0.01 * SUBSTEPS:g}", 'warm_start = "zero"': SAMPLING},
    )
    plant = task.make_plant(0)
    assert plant.substeps == SUBSTEPS
    expert = task.make_expert(0, WINDOW, ExpertOptions(max_iterations=0))
    planner = expert.planner
    assert planner is not None and planner.settings.planner == "sampling"
    candidates = np.random.default_rng(0).uniform(-1.0, 1.0, (3, WINDOW, 2))
    batched = planner.rollouts(S0, candidates)
    for plan, states in zip(candidates, batched, strict=True):
        plant.reset(S0)
        stepped = [plant.raw_state()]
        for action in plan:
            plant.step(action)
            stepped.append(plant.raw_state())
        np.testing.assert_allclose(states, np.array(stepped), rtol=0, atol=1e-12)
        assert plant.physics.data.time == pytest.approx(WINDOW * 0.01 * SUBSTEPS)
        # and the sampler's score of the plan is the cost of the optimizer's own rollout of it
        rolled, applied = expert.optimizer.dynamics.rollout(S0, WINDOW, actions=plan)
        np.testing.assert_allclose(
            window_costs(expert.optimizer.cost, states[None], plan[None]),
            window_costs(expert.optimizer.cost, rolled[None], applied[None]),
            rtol=1e-12,
        )
