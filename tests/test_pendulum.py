"""The pendulum swing-up plant and its iLQR expert on the real dm_control task."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from npp_ros.policy.dataset import DatasetError, Trajectory
from npp_ros.policy.lipschitz import LipschitzConstant, LipschitzWarning
from npp_ros.run.setup import build_config, build_loop, lipschitz_checks
from npp_ros.tasks.builtin.pendulum import (
    PAPER_LIPSCHITZ,
    PendulumExpert,
    PendulumPlant,
    represent,
    sample_initial_state,
    wrap_angle,
)
from npp_ros.trajopt.expert import replay_return_to_go

COS_8 = math.cos(math.radians(8.0))
HANGING = np.array([math.pi, 0.0])


@pytest.fixture(scope="module")
def expert() -> PendulumExpert:
    # A generous budget: the assertions are about what the optimizer finds, not its speed.
    return PendulumExpert(seed=0, time_budget=60.0, values="return-to-go")  # the values test checks this mode


@pytest.fixture(scope="module")
def solutions(expert: PendulumExpert) -> dict[float, object]:
    rng = np.random.default_rng(2024)
    starts = [HANGING] + [sample_initial_state(rng) for _ in range(4)]
    return {float(s0[0]): (s0, expert.solve(s0)) for s0 in starts}


def test_plant_matches_dm_control_task() -> None:
    plant = PendulumPlant()  # sets MUJOCO_GL before dm_control is first imported
    from dm_control import suite

    env = suite.load("pendulum", "swingup")
    assert plant.dt == env.control_timestep() == pytest.approx(0.02)
    assert (plant.state_dim, plant.action_dim) == (2, 1)
    assert plant.joint_names == plant.actuated_joint_names == ["hinge"]
    assert plant.model_sha256() == PendulumPlant(seed=5).model_sha256()
    # dm_control's reward, from the physics after the step: 1 within 8 degrees of upright.
    for angle, expected in ((0.0, 1.0), (math.radians(7.0), 1.0), (math.radians(9.0), 0.0), (math.pi, 0.0)):
        plant.reset([angle, 0.0])
        env.physics.data.qpos[:] = angle
        env.physics.data.qvel[:] = 0.0
        env.physics.forward()
        assert plant.step([0.0]) == expected
        env.physics.step()
        assert env.task.get_reward(env.physics) == expected
        np.testing.assert_array_equal(plant.raw_state(), np.r_[env.physics.data.qpos, env.physics.data.qvel])


def test_actions_are_clamped_as_mujoco_does() -> None:
    a, b = PendulumPlant(), PendulumPlant()
    a.reset([0.3, 0.1])
    b.reset([0.3, 0.1])
    a.step([7.0])
    b.step([1.0])
    np.testing.assert_array_equal(a.raw_state(), b.raw_state())


def test_state_representation_wraps_the_angle() -> None:
    np.testing.assert_allclose(
        wrap_angle([math.pi, -math.pi, 3 * math.pi / 2, 0.1, -7.0]),
        [math.pi, math.pi, -math.pi / 2, 0.1, -7.0 + 2 * math.pi],
    )
    rows = represent(np.array([[4.0, 1.0], [-4.0, -2.0]]))
    np.testing.assert_allclose(rows, [[4.0 - 2 * math.pi, 1.0], [-4.0 + 2 * math.pi, -2.0]])
    # Euclidean distance on stored states is never below the geodesic distance on the cylinder.
    rng = np.random.default_rng(1)
    x, y = represent(rng.uniform(-10, 10, (200, 2))), represent(rng.uniform(-10, 10, (200, 2)))
    geodesic = np.hypot(np.abs(wrap_angle(x[:, 0] - y[:, 0])), x[:, 1] - y[:, 1])
    assert np.all(np.linalg.norm(x - y, axis=1) >= geodesic - 1e-12)
    plant = PendulumPlant()
    plant.reset([3 * math.pi, 0.0])
    assert plant.state()[0] == pytest.approx(math.pi)


def test_initial_states_follow_rho() -> None:
    rng = np.random.default_rng(0)
    starts = np.array([sample_initial_state(rng) for _ in range(500)])
    assert np.all((starts[:, 0] >= -math.pi) & (starts[:, 0] < math.pi)) and np.all(starts[:, 1] == 0.0)
    again = np.array([sample_initial_state(np.random.default_rng(0)) for _ in range(1)])
    np.testing.assert_array_equal(again[0], starts[0])


def test_expert_swings_up_and_holds_within_8_degrees(solutions: dict) -> None:
    """From five seeded s0 (the hanging state among them): upright for the last 500 of 1000 steps."""
    assert any(s0[0] == math.pi for s0, _ in solutions.values())
    for s0, solution in solutions.values():
        traj: Trajectory = solution.trajectory
        assert len(traj) == 1000 and traj.states.shape == (1000, 2) and traj.actions.shape == (1000, 1)
        cos_tail = np.cos(solution.raw_states[500:, 0])
        assert np.all(cos_tail >= COS_8), f"s0 = {s0}: left the 8-degree cone in the last 500 steps"
        assert np.all(np.abs(traj.actions) <= 1.0)
        assert np.all((traj.states[:, 0] > -math.pi) & (traj.states[:, 0] <= math.pi))
        assert solution.expert_return >= 500
        assert solution.optimization.max_value_slope > 0


def test_never_worse_than_the_warm_start(expert: PendulumExpert, solutions: dict) -> None:
    for s0, solution in solutions.values():
        _, warm = expert.optimizer.dynamics.rollout(s0, 1000, policy=expert.warm_start)
        _, warm_values = replay_return_to_go(PendulumPlant(), s0, warm)
        assert solution.expert_return >= warm_values[0]
        if solution.kept_warm_start:
            np.testing.assert_array_equal(solution.trajectory.actions, warm)
            assert solution.optimization.iterations == 0


def test_values_are_the_replayed_true_return_to_go(solutions: dict) -> None:
    plant = PendulumPlant()
    for s0, solution in solutions.values():
        traj = solution.trajectory
        plant.reset(s0)
        rewards = np.array([plant.step(u) for u in traj.actions])
        assert set(np.unique(rewards)) <= {0.0, 1.0}
        np.testing.assert_array_equal(traj.values, np.cumsum(rewards[::-1])[::-1])
        assert solution.expert_return == traj.values[0] == rewards.sum()
        # The stored states are the plant's own, step by step, in the stored representation.
        raw, _ = replay_return_to_go(plant, s0, traj.actions)
        np.testing.assert_array_equal(raw, solution.raw_states)
        np.testing.assert_array_equal(traj.states, represent(raw))
        np.testing.assert_array_equal(raw, solution.optimization.states)


def test_identical_requests_give_identical_arrays() -> None:
    s0 = np.array([2.0, 0.0])
    first = PendulumExpert(time_budget=60.0, max_iterations=5, horizon=400).solve(s0)
    second = PendulumExpert(time_budget=60.0, max_iterations=5, horizon=400).solve(s0)
    for name in ("states", "actions", "values"):
        np.testing.assert_array_equal(getattr(first.trajectory, name), getattr(second.trajectory, name))
    np.testing.assert_array_equal(first.optimization.value_gradient, second.optimization.value_gradient)


def test_bad_requests_and_settings_are_refused(expert: PendulumExpert) -> None:
    with pytest.raises(DatasetError, match=r"^requested state has 3 entries, expected 2 \(hinge angle, .*\)$"):
        expert.trajectory(np.zeros(3))
    with pytest.raises(DatasetError, match=r"^requested state must be finite: requested state\[1\] = nan$"):
        expert.trajectory(np.array([0.0, np.nan]))
    with pytest.raises(ValueError, match=r"^time_budget must be finite and > 0 seconds, got 0$"):
        PendulumExpert(time_budget=0)
    with pytest.raises(ValueError, match=r"^horizon must be an integer >= 1, got -3$"):
        PendulumExpert(horizon=-3)


def test_slope_report_and_paper_constant(expert: PendulumExpert, solutions: dict) -> None:
    assert PAPER_LIPSCHITZ == 4300.0
    seen = max(sol.optimization.max_value_slope for _, sol in solutions.values())
    assert expert.slope_floor() >= seen > 0


def test_window_values_are_h_step_returns_of_each_state() -> None:
    """values="window": Q_t sums H rewards from s_t (continued past H by the hold controller)."""
    horizon = 300
    expert = PendulumExpert(time_budget=60.0, max_iterations=3, horizon=horizon, values="window")
    s0 = np.array([0.5, 0.0])
    solution = expert.solve(s0)
    traj = solution.trajectory
    plant = PendulumPlant()
    plant.reset(s0)
    rewards = [plant.step(u) for u in traj.actions]
    for _ in range(horizon - 1):
        rewards.append(plant.step(expert.warm_start(plant.raw_state())))
    expected = [sum(rewards[t : t + horizon]) for t in range(horizon)]
    np.testing.assert_array_equal(traj.values, expected)
    assert traj.values[0] == solution.expert_return == sum(rewards[:horizon])
    held = np.cos(solution.raw_states[:, 0]) >= COS_8
    assert np.all(traj.values[-50:] == horizon) and held[-50:].all()  # upright states keep the full H-step value
    with pytest.raises(ValueError, match=r"^values must be one of return-to-go, window; got 'tail'$"):
        PendulumExpert(values="tail")


def test_value_basis_and_theorem_34_condition(expert: PendulumExpert, solutions: dict) -> None:
    """The pendulum's step map expands (|A_t| > 1), so with gamma = 1 no L meets Theorem 3.4's condition."""
    holds, text = expert.theorem_34_condition(PAPER_LIPSCHITZ)
    assert not holds and "no L satisfies it" in text
    assert expert.max_transition_norm > 1.0
    basis = expert.value_basis()
    assert basis.tail is None and "time left" in basis.tail_detail
    window = PendulumExpert(values="window").value_basis()
    assert window.tail is not None and window.tail(HANGING) == 0.0


def test_importing_the_plants_loads_no_numba() -> None:
    """A sim node imports a plant; numba loads only with the optimizer."""
    import subprocess
    import sys

    code = (
        "import sys, npp_ros.tasks.builtin.pendulum, npp_ros.tasks.builtin.cartpole; "
        "print(any(m.startswith('numba') for m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "False"


@pytest.mark.parametrize("certify", ["rollout", "oracle"])
def test_certificates_say_that_no_l_bounds_the_pendulum_values(certify: str) -> None:
    """The 0/1 reward makes the expert's value a staircase: an L-based certificate is not proven, an oracle one is.

    The optimizer's own slope floor is among the L checks, and an L below it fails there.
    """
    horizon, lipschitz = 40, LipschitzConstant(1e-3, "user")
    expert = PendulumExpert(seed=0, horizon=horizon, time_budget=60.0, max_iterations=3, values="window")
    config = build_config(
        "pendulum_swingup", 0, lipschitz, 1e6, p=0.5, delta=0.5, horizon=horizon, certify=certify
    )  # fmt: skip
    loop = build_loop(config, expert)
    result = loop.run(50)
    certificate = result.certificate
    assert certificate is not None
    text = "\n".join(certificate.assumptions)
    if certify == "rollout":
        assert not certificate.proven
        assert "it does NOT hold here, with the 0/1 reward every H-step return is a whole number" in text
    else:
        assert certificate.proven and "NOT hold" not in text
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LipschitzWarning)
        floors = [c for c in lipschitz_checks(loop, expert) if c.source.startswith("optimizer's own")]
    assert len(floors) == 1 and floors[0].slope == expert.slope_floor() > lipschitz.value
    assert not floors[0].ok and f"over {expert.requests} requests" in floors[0].source
