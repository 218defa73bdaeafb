"""Shared fixtures: real dm_control plants and LQR experts (built once per session)."""

from __future__ import annotations

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
