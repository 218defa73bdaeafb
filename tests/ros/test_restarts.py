"""Nodes die mid-run: nothing stored is lost, the run completes, and nothing hangs silently."""

from __future__ import annotations

import signal
import time
from pathlib import Path

import numpy as np
import pytest
from npp_interfaces.msg import Certificate, GapReport
from reference import ROLLOUT_FREE, decisions, uninterrupted_run

from npp_ros.run.store import RunStore
from npp_ros_graph.transport.topics import CERTIFICATE, GAP, LATCHED_READER_QOS, REPORT_QOS

SUPERVISOR = "npp-supervisor"
# A short horizon: the decisions on the surrogate check do not depend on it (lqr_2_1 seed 0 certifies after 178
# episodes and 52 oracle calls at H = 50 as at H = 1000), and every episode the sim runs is 20 times shorter.
HORIZON = 50


def test_unreachable_expert_is_reported_and_the_supervisor_exits(launch, tmp_path: Path) -> None:
    launch("npp-sim", {"horizon": 50})
    launch("npp-policy")
    supervisor = launch(SUPERVISOR, {"run_dir": str(tmp_path / "run"), "expert_timeout": 2.0, "expert_retries": 2})
    supervisor.wait(timeout=120)
    log = launch.log(supervisor)
    assert supervisor.returncode == 1, log
    assert "expert call 1/2 failed: service /npp/expert/trajectory not available after 2 s" in log
    assert "Algorithm 1 stopped: the expert did not deliver after 2 attempts" in log
    with RunStore.open(tmp_path / "run" / "run.sqlite") as store:
        assert store.num_trajectories() == 0 and store.episodes() == []


@pytest.mark.long
def test_killing_policy_then_supervisor_loses_no_expert_data(launch, ros_client, tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    supervisor_params = {"run_dir": str(run_dir), "max_episodes": 400, "rollout_timeout": 30.0, **ROLLOUT_FREE}
    launch("npp-sim", {"horizon": HORIZON})
    launch("npp-expert")
    policy = launch("npp-policy")
    supervisor = launch(SUPERVISOR, supervisor_params)
    watcher = ros_client("restart_watcher")
    gaps: list[GapReport] = watcher.collect(GapReport, GAP, REPORT_QOS)
    certificates: list[Certificate] = watcher.collect(Certificate, CERTIFICATE, LATCHED_READER_QOS)

    def oracle_calls() -> int:
        return gaps[-1].oracle_calls if gaps else 0

    watcher.wait_for(lambda: oracle_calls() >= 8, 300, "8 oracle calls")
    policy.send_signal(signal.SIGKILL)
    policy.wait()
    time.sleep(2.0)  # the sim stalls mid-episode with no policy
    launch("npp-policy")  # restarted: catches up from the supervisor, picks the episode up

    watcher.wait_for(lambda: oracle_calls() >= 20, 300, "20 oracle calls after the policy restart")
    supervisor.send_signal(signal.SIGKILL)
    supervisor.wait()
    with RunStore.open(run_dir / "run.sqlite") as store:  # what was acknowledged as stored
        before = store.load_dataset()
    launch(SUPERVISOR, supervisor_params)  # restarted on the same run folder: resumes

    watcher.wait_for(lambda: bool(certificates), 900, "the certificate")
    with RunStore.open(run_dir / "run.sqlite") as store:
        after = store.load_dataset()
        rows = store.episodes()
    # Every trajectory stored before the kill is still there, unchanged, exactly once.
    assert after.num_trajectories >= before.num_trajectories >= 20
    np.testing.assert_array_equal(after.states[: len(before)], before.states)
    assert [r.trajectory for r in rows if r.oracle_called] == list(range(after.num_trajectories))
    # The resumed run is the same run: same dataset and gap sequence as uninterrupted, in process.
    local, result = uninterrupted_run(horizon=HORIZON, **ROLLOUT_FREE)
    assert decisions(rows) == decisions(result.rows)
    np.testing.assert_array_equal(after.states, local.dataset.states)
    assert certificates[-1].episodes == len(rows) == result.episodes
    # The restarted policy drove the episodes after its restart.
    assert all(r.policy_return is not None for r in rows[-10:])
