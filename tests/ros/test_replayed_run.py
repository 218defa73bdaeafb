"""A run's sealed messages, recorded and replayed into a second run with the same key, enter nothing.

Hand-started nodes share a run key by exporting NPP_RUN_KEY, and a user may well reuse one export for
two runs of the same plant. The first run (epsilon 100) is recorded with npp-run --record; the second
(epsilon 50, the same NPP_RUN_KEY, the same plant, its nodes started by hand) runs while npp-replay
publishes the whole first bag onto its domain at once: rollout results for every episode, states,
actions, dataset trajectories, all carrying seals made with the same key. The second run must end
exactly as its uninterrupted in-process run (certificate, decisions, returns, dataset), its supervisor
must have refused the replayed results, and the replayed returns must differ from its own (so that
taking them would have changed the run).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import pytest
from graph import graph_parameters, start_graph
from reference import assert_same_run, uninterrupted_run

from npp_ros.run.records import RunFileError
from npp_ros.run.store import RunStore
from npp_ros_graph.transport.message_seal import KEY_ENV, RunSeal

if TYPE_CHECKING:
    from tests.ros.conftest import Launcher, RosClient

pytestmark = pytest.mark.slow

HORIZON = 50
TIMEOUT = 900


def certified(run_file: Path) -> bool:
    try:
        with RunStore.open(run_file) as store:
            return store.certificate() is not None
    except RunFileError:  # not made yet
        return False


def episodes(run_file: Path) -> int:
    try:
        with RunStore.open(run_file) as store:
            return len(store.episodes())
    except RunFileError:  # not made yet
        return 0


@pytest.mark.long
def test_a_replayed_run_enters_nothing_of_a_second_run_with_the_same_key(
    launch: Launcher, ros_client: Callable[..., RosClient], tmp_path: Path
) -> None:
    key = RunSeal.new_key()
    first = subprocess.run(
        [sys.executable, "-m", "npp_ros_graph.tools.run", "--task", "lqr_2_1", "--horizon", str(HORIZON),
         "--run-dir", str(tmp_path / "first"), "--epsilon", "100", "--record"],
        capture_output=True, text=True, timeout=TIMEOUT, env={**os.environ, KEY_ENV: key},
    )  # fmt: skip
    assert first.returncode == 0, first.stdout[-2000:] + first.stderr[-2000:]
    bag = next((tmp_path / "first").glob("bag*"))

    # The second run, started by hand with the same exported key; once it is under way, the first one's bag is
    # replayed at once (results for episodes it has yet to run wait for them, were they taken).
    client = ros_client("replay_watcher")
    procs = start_graph(launch, graph_parameters("lqr_2_1", 0, HORIZON, tmp_path / "second"), extra_env={KEY_ENV: key})
    client.wait_for(lambda: episodes(tmp_path / "second" / "run.sqlite") >= 3, TIMEOUT, "the second run's episodes")
    replay = subprocess.run(
        [sys.executable, "-m", "npp_ros_graph.tools.replay", str(bag), "--rate", "0", "--delay", "3",
         "--linger", "0"],
        capture_output=True, text=True, timeout=TIMEOUT,
    )  # fmt: skip
    assert replay.returncode == 0, replay.stdout[-2000:] + replay.stderr[-2000:]
    # Its own certificate, in its run file: the replay publishes the first run's certificate too (a viewer's report).
    client.wait_for(lambda: certified(tmp_path / "second" / "run.sqlite"), TIMEOUT, "the second run's certificate")
    for proc in procs.values():
        launch.assert_alive(proc)

    local_loop, local = uninterrupted_run(horizon=HORIZON, max_episodes=1000, certify="rollout", rule="sequential")
    time.sleep(0.5)  # the supervisor's worker has written the episode with the certificate
    _, rows = assert_same_run(tmp_path / "second" / "run.sqlite", local_loop, local)
    supervisor_log = launch.log(procs["supervisor"])
    assert "rollout result of episode" in supervisor_log and "does not carry this run's seal" in supervisor_log

    with RunStore.open(tmp_path / "first" / "run.sqlite") as store:
        recorded = {row.episode: row.policy_return for row in store.episodes()}
    own = {row.episode: row.policy_return for row in rows}
    assert any(recorded[k] != own[k] for k in recorded if k in own), "the replay could not have changed the run"
