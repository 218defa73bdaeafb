"""The acrobot expert's parts: the closed-form energy, the pumping controller, a deterministic request."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from npp_ros.tasks.builtin.acrobot import AcrobotExpert, AcrobotPlant, SwingUpController, sample_initial_state
from npp_ros.trajopt.dynamics import MujocoDynamics

HANGING = np.array([np.pi, 0.0, 0.0, 0.0])


def test_closed_form_energy_is_mujocos_own_less_a_constant_and_its_gradient_is_right() -> None:
    plant = AcrobotPlant(0)
    links = SwingUpController(plant).links
    model = plant.physics.model.ptr
    data = mujoco.MjData(model)
    states = np.random.default_rng(3).normal(size=(6, 4)) * [2.0, 2.0, 3.0, 3.0]
    energy, grad = links.energy(states)
    mujoco_energy = []
    for x in states:
        data.qpos[:], data.qvel[:] = x[:2], x[2:]
        mujoco.mj_forward(model, data)
        mujoco_energy.append(float(data.energy.sum()))
    offset = np.asarray(mujoco_energy) - energy
    np.testing.assert_allclose(offset, offset[0], atol=1e-9)  # the shoulder's height times the weight
    step = 1e-6
    for i in range(4):
        shift = np.zeros(4)
        shift[i] = step
        numeric = (links.energy(states + shift)[0] - links.energy(states - shift)[0]) / (2 * step)
        np.testing.assert_allclose(grad[:, i], numeric, atol=1e-6)


def test_the_controller_pumps_the_hanging_acrobot_to_the_energy_of_upright() -> None:
    plant = AcrobotPlant(0)
    controller = SwingUpController(plant)
    states, actions = MujocoDynamics(plant).rollout(HANGING, 400, policy=controller)
    energy, _ = controller.links.energy(states)
    hanging, upright = energy[0], controller.links.upright_energy
    assert energy[-1] - hanging >= 0.95 * (upright - hanging)
    tip_above_shoulder = np.cos(states[:, 0]) + np.cos(states[:, 0] + states[:, 1])
    assert tip_above_shoulder.max() > 0.0  # from 2 m below the shoulder to above it
    assert np.abs(actions).max() <= 1.0


def test_a_request_is_deterministic_and_its_values_are_the_replayed_rewards() -> None:
    s0 = sample_initial_state(np.random.default_rng(0))
    horizon = 60
    first, second = AcrobotExpert(0, horizon=horizon).solve(s0), AcrobotExpert(0, horizon=horizon).solve(s0)
    assert first.optimization.stop_reason != "time budget"
    np.testing.assert_array_equal(first.trajectory.actions, second.trajectory.actions)
    np.testing.assert_array_equal(first.trajectory.values, second.trajectory.values)
    replay = AcrobotPlant(0)
    replay.reset(s0)
    rewards = [replay.step(u) for u in first.trajectory.actions]
    assert first.expert_return == pytest.approx(sum(rewards), rel=1e-12)


def test_a_plan_with_a_handover_is_the_controllers_own_swing_until_it_nears_upright_energy() -> None:
    expert = AcrobotExpert(0, horizon=80)
    pumped, pumping = MujocoDynamics(expert.plant).rollout(HANGING, 80, policy=expert.controller)
    assert expert.controller.links.energy(pumped)[0].max() < expert.controller.links.upright_energy - 2.0
    np.testing.assert_array_equal(expert.planner.plan(HANGING, 80, handover=2.0), pumping)
