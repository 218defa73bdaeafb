"""Shared fixtures: real dm_control plants and LQR experts (built once per session)."""

from __future__ import annotations

import numpy as np
import pytest

from npp_ros.dataset import Dataset
from npp_ros.lqr import LQRExpert, episode_rng, sample_initial_state


@pytest.fixture(scope="session")
def expert_2_1() -> LQRExpert:
    return LQRExpert("lqr_2_1", seed=0)


@pytest.fixture(scope="session")
def expert_6_2() -> LQRExpert:
    return LQRExpert("lqr_6_2", seed=0)


@pytest.fixture(scope="session")
def expert_dataset_2_1(expert_2_1: LQRExpert) -> Dataset:
    """Twenty expert trajectories from s0 ~ rho on lqr_2_1: a consistent dataset."""
    data = Dataset(4, 1)
    for episode in range(20):
        data.append(expert_2_1.trajectory(sample_initial_state("lqr_2_1", episode_rng(99, episode))))
    return data


def random_dataset(rng: np.random.Generator, size: int, state_dim: int = 3, action_dim: int = 2) -> Dataset:
    """Synthetic data on a coarse grid, so exact ties are frequent."""
    data = Dataset(state_dim, action_dim)
    states = rng.integers(-3, 4, size=(size, state_dim)).astype(float)
    actions = rng.integers(-2, 3, size=(size, action_dim)).astype(float)
    values = rng.integers(0, 5, size=size).astype(float)
    data.append_arrays(states, actions, values)
    return data
