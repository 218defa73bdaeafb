"""A paused node catches up by itself: SIGSTOP for longer than the middleware's liveliness limit (Fast
DDS drops a silent participant after its 20 s lease), then SIGCONT.

Reproduced as found: the supervisor stopped right after it handed the policy a new trajectory (the
gap report of an oracle episode comes just after), so that the trajectory is lost on its way; then the
sim stopped in the middle of an episode; then the policy and the expert together. Before, every
episode after the supervisor's pause waited the whole rollout_timeout for a trajectory already stored,
and the sim's lost reset did the same. Here rollout_timeout is long (600 s): an episode that waited it
out would run the test past its deadline. The run must also end exactly as the in-process run does,
with a return for every episode.
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import pytest
from graph import graph_parameters, start_graph
from npp_interfaces.msg import Certificate, GapReport
from reference import ROLLOUT_FREE, assert_stored_run_is_uninterrupted

from npp_ros_graph.transport.seal import KEY_ENV, RunSeal
from npp_ros_graph.transport.topics import CERTIFICATE, GAP, LATCHED_QOS, REPORT_QOS

if TYPE_CHECKING:
    from tests.ros.conftest import Launcher, RosClient

pytestmark = pytest.mark.slow

HORIZON = 50
MAX_EPISODES = 400
PAUSE_S = 25.0  # longer than Fast DDS's default participant lease (20 s)
TIMEOUT = 900.0


def test_paused_nodes_catch_up_by_themselves(
    launch: Launcher, ros_client: Callable[..., RosClient], tmp_path: Path
) -> None:
    run_dir = tmp_path / "run"
    key = {KEY_ENV: RunSeal.new_key()}
    client = ros_client("stall_watcher")
    gaps: list[GapReport] = client.collect(GapReport, GAP, REPORT_QOS)
    certificates = client.collect(Certificate, CERTIFICATE, LATCHED_QOS)
    supervisor = {"max_episodes": MAX_EPISODES, "rollout_timeout": 600.0, **ROLLOUT_FREE}
    procs = start_graph(launch, graph_parameters("lqr_2_1", 0, HORIZON, run_dir, supervisor=supervisor), extra_env=key)

    def pause(names: list[str], when: Callable[[], bool], label: str) -> float:
        """SIGSTOP the nodes once `when` holds, SIGCONT after PAUSE_S; seconds from SIGCONT to the next episode."""
        client.wait_for(when, TIMEOUT, label)
        for name in names:
            os.kill(procs[name].pid, signal.SIGSTOP)
        stopped_at = len(gaps)
        deadline = time.monotonic() + PAUSE_S
        client.wait_for(lambda: time.monotonic() > deadline, PAUSE_S + 10)
        for name in names:
            os.kill(procs[name].pid, signal.SIGCONT)
        resumed = time.monotonic()
        client.wait_for(lambda: len(gaps) > stopped_at + 1 or bool(certificates), TIMEOUT, f"episodes after {label}")
        return time.monotonic() - resumed

    recovery = {
        "supervisor": pause(
            ["supervisor"], lambda: len(gaps) >= 5 and gaps[-1].oracle_called, "an oracle episode after the fifth"
        ),
        "sim": pause(["sim"], lambda: len(gaps) >= 25, "episode 25"),
        "policy and expert": pause(["policy", "expert"], lambda: len(gaps) >= 40, "episode 40"),
    }
    client.wait_for(lambda: bool(certificates), TIMEOUT, "the certificate")
    print(f"\nseconds from SIGCONT to the next episode after a {PAUSE_S:g} s pause: {recovery}")
    for proc in procs.values():
        launch.assert_alive(proc)

    _, rows, _ = assert_stored_run_is_uninterrupted(run_dir / "run.sqlite", HORIZON, MAX_EPISODES)
    missing = [row.episode for row in rows if row.policy_return is None]
    assert not missing, f"episodes without the policy's return: {missing}"
