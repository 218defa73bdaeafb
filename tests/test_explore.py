"""Asking the expert where the policy goes: after a failed check, one more trajectory from the first state of the
policy's own rollout that is farther than the radius from every stored state; counted, stored, resumed."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.run.setup import build_config, build_loop
from npp_ros.run.store import RunStore
from npp_ros.tasks.builtin.lqr import LQRExpert, LQRPlant
from npp_ros.tasks.rollout import rollout

HORIZON = 100
RADIUS = 0.05


def config(explore: float) -> object:
    lipschitz = LipschitzConstant(263.0, "user", "test")
    return build_config("lqr_2_1", 0, lipschitz, 5.0, horizon=HORIZON, policy="open-loop", explore=explore)


def test_a_failed_check_also_asks_where_the_policy_left_the_data(tmp_path: Path) -> None:
    expert = LQRExpert("lqr_2_1", 0, horizon=HORIZON)
    loop = build_loop(config(RADIUS), expert, store_path=tmp_path / "run.sqlite")
    plant = LQRPlant("lqr_2_1", 0)
    checked = []
    for _ in range(8):
        before = loop.dataset.prefix(loop.policy_data.num_trajectories)
        row = loop.run_episode()
        checked.append((row, before))
    explored = [(row, before) for row, before in checked if row.explored]
    assert explored, "no failed check left the data"
    assert loop.oracle_calls == loop.dataset.num_trajectories == sum(row.trajectories_stored for row, _ in checked)
    assert checked[-1][0].oracle_calls == loop.oracle_calls
    for row, before in explored:
        assert row.checked_gap > 5.0 and row.trajectory is not None
        # The extra trajectory starts at the first state of the checked policy's rollout outside the radius.
        policy = loop.policy.__class__(before, 263.0)
        states = rollout(plant, policy.act, np.asarray(row.initial_state), HORIZON).states
        far = np.flatnonzero(cKDTree(before.states).query(states)[0] > RADIUS)
        np.testing.assert_array_equal(loop.dataset.trajectory(row.trajectory + 1).states[0], states[far[0]])
    loop.store.close()
    resumed = build_loop(config(RADIUS), expert, store_path=tmp_path / "run.sqlite")
    assert resumed.rows == loop.rows and resumed.dataset.num_trajectories == loop.dataset.num_trajectories
    resumed.store.close()


def test_a_run_without_exploration_refuses_a_file_made_with_it(tmp_path: Path) -> None:
    expert = LQRExpert("lqr_2_1", 0, horizon=HORIZON)
    build_loop(config(RADIUS), expert, store_path=tmp_path / "run.sqlite").store.close()
    with pytest.raises(Exception, match="explore"):
        build_loop(config(0.0), expert, store_path=tmp_path / "run.sqlite")
    with RunStore.open(tmp_path / "run.sqlite") as store:
        assert store.metadata.explore == RADIUS


def test_the_radius_must_be_a_distance() -> None:
    with pytest.raises(ValueError, match="exploration radius"):
        config(-1.0)
