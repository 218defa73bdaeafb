"""Shared fixtures: real dm_control plants and LQR experts (built once per session).

Modules that run whole experiments, command lines or thousands of simulated runs are marked
``slow``; `make test-quick` skips them and the ROS graph, `make test` runs everything.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest

from npp_ros.policy.dataset import Dataset
from npp_ros.tasks.builtin.lqr import LQRExpert, episode_rng, sample_initial_state

# The gate remembers runs it derived again in the user's cache folder: each test session gets its own (node processes
# started by the tests inherit it), so no test finds another session's agreements, nor writes the user's.
os.environ["NPP_ROS_CACHE"] = tempfile.mkdtemp(prefix="npp-ros-test-cache-")

SLOW_MODULES = {
    "test_experiment.py",  # npp-experiment end to end, several times
    "test_cli_learn.py",  # npp-learn to a certificate
    "test_cli_args.py",  # command lines as processes
    "test_loop.py",  # Algorithm 1 to a certificate on lqr_2_1
    "test_loop_mixture.py",  # the same under the mixture rule, twice
    "test_expert_pool.py",  # worker processes running iLQR
    "test_soundness.py",  # 2,000 simulated runs per rule
    "test_storage_reliability.py",  # real second processes, tmpfs
    "test_trajopt.py",  # iLQR at H = 1000
    "test_pendulum.py",
    "test_cartpole.py",
    "test_bench.py",
    "test_theorems.py",  # greedy rollouts from 40 s0 per theorem
    "test_deploy.py",  # three runs to a certificate, and the gate on each
}


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if item.path.name in SLOW_MODULES:
            item.add_marker(pytest.mark.slow)


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


@pytest.fixture(scope="session")
def demo_plugin(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The demo plug-in package installed into a temporary folder (tests/plugin_env.py); not on the path yet."""
    from plugin_env import install_demo_plugin

    return install_demo_plugin(tmp_path_factory.mktemp("plugin"))


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    """Print what tests recorded with ``record_property("report", text)``: measured figures a passing test
    states (a chaos test's faults and recoveries), shown by `make test` too, also from xdist workers."""
    for report in terminalreporter.stats.get("passed", []):
        for name, text in getattr(report, "user_properties", ()):
            if name == "report":
                terminalreporter.write_sep("-", report.nodeid)
                terminalreporter.write_line(str(text))
