"""Expert returns asked for in chunks give the one-at-a-time returns: in process, from a run folder's
store, and spread over the workers of a Dask cluster."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import cloudpickle
import numpy as np
import pytest
from distributed import Client, LocalCluster, get_worker, wait

from npp_ros.experiment import run_arm_seed, runs
from npp_ros.experiment.arms import Arm, ExperimentSettings, make_expert
from npp_ros.experiment.evaluation import held_out_states
from npp_ros.experiment.expert_requests import ExpertReturns, StoredReturnsError
from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import Dataset
from npp_ros.run.evaluation import check_policy
from npp_ros.tasks.registry import get_task

ARM = Arm("lqr_2_1", "optimal", "analytic", "oracle", "sequential")  # oracle mode: checked against the expert
SETTINGS = ExperimentSettings(max_episodes={"lqr_2_1": 10}, horizon=200, held_out=40)
PENDULUM = Arm("pendulum_swingup", "ilqr", "5", "oracle", "sequential")
# the iteration cap or convergence decides every answer, never the clock
PENDULUM_SETTINGS = ExperimentSettings(max_episodes={"pendulum_swingup": 10}, horizon=40, time_budget=120.0)


def one_at_a_time(arm: Arm, settings: ExperimentSettings, states: np.ndarray) -> np.ndarray:
    """The reference: one expert, all s0 in one call, as the held-out check asked before chunks."""
    task = get_task(arm.task)
    expert = make_expert(arm, 0, settings)
    return task.expert_returns(expert, task.make_plant(0), states, settings.horizon)


def test_chunks_in_process_are_the_one_call_returns_and_report_progress() -> None:
    states = held_out_states(ARM.task, 0, SETTINGS.held_out)
    seen: list[tuple[int, int]] = []
    asked = ExpertReturns(ARM, 0, SETTINGS, states, make_expert(ARM, 0, SETTINGS), chunk=7)
    assert asked.missing_chunks()[:2] == [(0, 7), (7, 14)] and asked.missing_chunks()[-1] == (35, 40)
    got = asked.start().result(lambda k, n: seen.append((k, n)))
    np.testing.assert_array_equal(got, one_at_a_time(ARM, SETTINGS, states))
    assert seen[-1] == (40, 40) and len(seen) >= 6  # at least once per chunk (lqr answers a chunk in one batch)
    assert asked.budget_stops == 0 and asked.workers == set()


def test_an_optimizer_expert_per_chunk_answers_as_one_expert_for_all() -> None:
    states = held_out_states(PENDULUM.task, 0, 4)
    fresh = ExpertReturns(PENDULUM, 0, PENDULUM_SETTINGS, states, make_expert(PENDULUM, 0, PENDULUM_SETTINGS), chunk=1)
    np.testing.assert_array_equal(fresh.result(), one_at_a_time(PENDULUM, PENDULUM_SETTINGS, states))


def test_a_resumed_run_asks_only_for_what_its_store_lacks(tmp_path: Path) -> None:
    store = tmp_path / "heldout-expert.jsonl"
    states = held_out_states(ARM.task, 0, SETTINGS.held_out)
    expert = make_expert(ARM, 0, SETTINGS)
    first = ExpertReturns(ARM, 0, SETTINGS, states, expert, store, chunk=10).result()
    lines = store.read_text().splitlines()
    assert len(lines) == 1 + 4 and json.loads(lines[0])["task"] == "lqr_2_1"
    again = ExpertReturns(ARM, 0, SETTINGS, states, expert, store, chunk=10)
    assert again.missing_chunks() == []
    np.testing.assert_array_equal(again.result(), first)
    # a crash tore the last line: its chunk is asked again, nothing else
    store.write_text("\n".join(lines[:-1]) + "\n" + lines[-1][: len(lines[-1]) // 2])
    torn = ExpertReturns(ARM, 0, SETTINGS, states, expert, store, chunk=10)
    assert torn.missing_chunks() == [(30, 40)]
    np.testing.assert_array_equal(torn.result(), first)
    # a damaged line (not numbers) is skipped, and only its chunk asked again
    damaged = [lines[0], lines[1], json.dumps({"first": 10, "states": "x", "returns": ["a"]}), *lines[3:]]
    store.write_text("\n".join(damaged) + "\n")
    assert ExpertReturns(ARM, 0, SETTINGS, states, expert, store, chunk=10).missing_chunks() == [(10, 20)]
    # more held-out s0 than before: the first 40 are the same stream's, only the new ones are asked
    more = held_out_states(ARM.task, 0, 55)
    longer = ExpertReturns(ARM, 0, SETTINGS, more, expert, store, chunk=10)
    assert longer.missing_chunks() == [(10, 20), (40, 50), (50, 55)]
    np.testing.assert_array_equal(longer.result(), one_at_a_time(ARM, SETTINGS, more))


def test_a_store_of_another_run_is_refused_in_one_line_and_left_untouched(tmp_path: Path) -> None:
    store = tmp_path / "heldout-expert.jsonl"
    states = held_out_states(ARM.task, 0, 10)
    ExpertReturns(ARM, 0, SETTINGS, states, make_expert(ARM, 0, SETTINGS), store).result()
    before = store.read_bytes()
    with pytest.raises(StoredReturnsError, match="holds expert returns of another run") as refused:
        ExpertReturns(ARM, 1, SETTINGS, held_out_states(ARM.task, 1, 10), make_expert(ARM, 1, SETTINGS), store)
    assert "\n" not in str(refused.value) and store.read_bytes() == before


def test_a_store_made_at_another_thread_count_is_this_runs(tmp_path: Path) -> None:
    """Threads set how fast answers come, not what they are: a header with or without them is the run's."""
    store = tmp_path / "heldout-expert.jsonl"
    states = held_out_states(ARM.task, 0, 10)
    first = ExpertReturns(ARM, 0, SETTINGS, states, make_expert(ARM, 0, SETTINGS), store).result()
    lines = store.read_text().splitlines()
    header = json.loads(lines[0])
    assert "threads" not in header["expert"]
    for threads in (None, 2):  # what earlier versions wrote: the thread count in the expert's options
        header["expert"]["threads"] = threads
        store.write_text("\n".join([json.dumps(header), *lines[1:]]) + "\n")
        resumed = ExpertReturns(ARM, 0, SETTINGS, states, make_expert(ARM, 0, SETTINGS), store)
        assert resumed.missing_chunks() == []
        np.testing.assert_array_equal(resumed.result(), first)


def test_the_held_out_check_counts_the_reference_answers_the_time_budget_cut() -> None:
    """Such answers depend on the machine's speed: heldout.json says how many, asked here or ahead."""
    cut = ExperimentSettings(max_episodes={"pendulum_swingup": 10}, horizon=40, time_budget=1e-9)
    task, states = get_task(PENDULUM.task), held_out_states(PENDULUM.task, 0, 3)
    expert = make_expert(PENDULUM, 0, cut)
    data = Dataset(len(states[0]), 1)
    data.append(expert.trajectory(states[0]))
    policy = NonparametricPolicy(data, 5.0)
    check = dict(epsilon=130.0, p=0.9, delta=0.1, against_expert=True)
    here = check_policy(policy, task, task.make_plant(0), make_expert(PENDULUM, 0, cut), states, 40, **check)
    asked = ExpertReturns(PENDULUM, 0, cut, states, make_expert(PENDULUM, 0, cut), chunk=2)
    ahead = asked.result()
    given = check_policy(policy, task, task.make_plant(0), expert, states, 40, **check,
                         expert_returns=ahead, expert_budget_stops=asked.budget_stops)  # fmt: skip
    assert here.expert_budget_stops == given.expert_budget_stops == asked.budget_stops == 3
    untimed = check_policy(policy, task, task.make_plant(0), make_expert(PENDULUM, 0, PENDULUM_SETTINGS), states, 40,
                           **check)  # fmt: skip
    assert untimed.expert_budget_stops == 0


def ask_in_a_run(
    arm: Arm, settings: ExperimentSettings, states: np.ndarray, store: Path, after_one_elsewhere: bool = False
) -> dict[str, Any]:
    """What a run on a Dask worker does: ask ahead, go on, then wait for the returns.

    ``after_one_elsewhere``: the run goes on until another worker has answered a chunk.
    """
    started = time.monotonic()
    asked = ExpertReturns(arm, 0, settings, states, make_expert(arm, 0, settings), store, chunk=5).start()
    if after_one_elsewhere:
        wait(list(asked._futures.values()), return_when="FIRST_COMPLETED")
    progress: list[int] = []
    returns = asked.result(lambda k, _n: progress.append(k))
    asked.close()
    return {"returns": returns, "workers": sorted(asked.workers), "progress": progress,
            "worker": f"worker {get_worker().name}", "started": started, "ended": time.monotonic()}  # fmt: skip


def another_run() -> float:
    return time.monotonic()


def two_worker_cluster() -> LocalCluster:
    return LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address="127.0.0.1:0"
    )


@pytest.mark.slow
def test_on_a_dask_cluster_the_chunks_spread_over_its_workers_and_give_the_same_returns(tmp_path: Path) -> None:
    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the workers cannot import this test module
    states = held_out_states(ARM.task, 0, SETTINGS.held_out)
    with two_worker_cluster() as cluster, Client(cluster) as client:
        got = client.submit(ask_in_a_run, ARM, SETTINGS, states, tmp_path / "store.jsonl", True).result(timeout=600)
    np.testing.assert_array_equal(got["returns"], one_at_a_time(ARM, SETTINGS, states))
    assert set(got["workers"]) - {got["worker"]}, got  # the other worker answered chunks
    assert got["progress"][-1] == 40 and got["progress"] == sorted(got["progress"])
    assert len((tmp_path / "store.jsonl").read_text().splitlines()) == 1 + 8  # every chunk stored, once


@pytest.mark.slow
def test_a_run_answers_the_chunks_no_worker_started_and_keeps_its_slot(tmp_path: Path) -> None:
    """One slot: the run's chunks cannot start elsewhere, so it answers them all, and the next run waits for it."""
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    states = held_out_states(PENDULUM.task, 0, 10)
    with LocalCluster(
        n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address="127.0.0.1:0"
    ) as cluster, Client(cluster) as client:  # fmt: skip
        first = client.submit(ask_in_a_run, PENDULUM, PENDULUM_SETTINGS, states, tmp_path / "s.jsonl", priority=1)
        second = client.submit(another_run, priority=0)
        got, second_started = first.result(timeout=600), second.result(timeout=600)
    np.testing.assert_array_equal(got["returns"], one_at_a_time(PENDULUM, PENDULUM_SETTINGS, states))
    assert got["workers"] == [got["worker"]] and got["progress"][-1] == 10
    assert second_started > got["ended"]  # the waiting run never gave its slot to the next one


def test_a_run_that_ended_without_a_certificate_asks_for_no_held_out_returns(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """At its budget with no certificate, a resumed run has no held-out check to come: nothing is asked."""
    settings = ExperimentSettings(max_episodes={"lqr_2_1": 3}, horizon=50, held_out=10, checkpoints=(3,))
    first = run_arm_seed(ARM, 0, settings, tmp_path)
    assert first.certified_episode is None
    asked: list[Any] = []
    monkeypatch.setattr(runs, "ExpertReturns", lambda *args, **kw: asked.append(args) or ExpertReturns(*args, **kw))
    again = run_arm_seed(ARM, 0, settings, tmp_path)
    assert asked == [] and again.certified_episode is None
