"""Expert returns asked for in chunks give the one-at-a-time returns: in process, from a run folder's
kept answers (npp_ros.run.held_out.KeptAnswers, each chunk appending its s0's lines), and spread over the workers of
a Dask cluster."""

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
from npp_ros.experiment.expert_requests import HELD_OUT_FILE, ExpertReturns
from npp_ros.policy.bounds import NonparametricPolicy
from npp_ros.policy.dataset import Dataset
from npp_ros.run.held_out import (
    EXPERIMENT_HELD_OUT_STREAM,
    KeptAnswers,
    StoredReturnsError,
    check_policy,
    held_out_states,
)
from npp_ros.tasks.registry import get_task

ARM = Arm("lqr_2_1", "optimal", "analytic", "oracle", "sequential")  # oracle mode: checked against the expert
SETTINGS = ExperimentSettings(max_episodes={"lqr_2_1": 10}, horizon=200, held_out=40)
PENDULUM = Arm("pendulum_swingup", "ilqr", "5", "oracle", "sequential")
# the iteration cap or convergence decides every answer, never the clock
PENDULUM_SETTINGS = ExperimentSettings(max_episodes={"pendulum_swingup": 10}, horizon=40, time_budget=120.0)
RUN = "the identity of the run these returns are of"


def fresh(task: str, seed: int, count: int) -> np.ndarray:
    """npp-experiment's held-out s0 of a seed."""
    return held_out_states(task, seed, count, EXPERIMENT_HELD_OUT_STREAM)


def one_at_a_time(arm: Arm, settings: ExperimentSettings, states: np.ndarray) -> np.ndarray:
    """The reference: one expert, all s0 in one call, as the held-out check asked before chunks."""
    task = get_task(arm.task)
    expert = make_expert(arm, 0, settings)
    return task.expert_returns(expert, task.make_plant(0), states, settings.horizon)


def test_chunks_in_process_are_the_one_call_returns_and_report_progress() -> None:
    states = fresh(ARM.task, 0, SETTINGS.held_out)
    seen: list[tuple[int, int]] = []
    asked = ExpertReturns(ARM, 0, SETTINGS, states, make_expert(ARM, 0, SETTINGS), chunk=7)
    assert asked.missing_chunks()[:2] == [(0, 7), (7, 14)] and asked.missing_chunks()[-1] == (35, 40)
    got = asked.start().result(lambda k, n: seen.append((k, n)))
    np.testing.assert_array_equal(got, one_at_a_time(ARM, SETTINGS, states))
    assert seen[-1] == (40, 40) and len(seen) >= 6  # at least once per chunk (lqr answers a chunk in one batch)
    assert asked.budget_stops == 0 and asked.workers == set()


def test_an_optimizer_expert_per_chunk_answers_as_one_expert_for_all() -> None:
    states = fresh(PENDULUM.task, 0, 4)
    asked = ExpertReturns(PENDULUM, 0, PENDULUM_SETTINGS, states, make_expert(PENDULUM, 0, PENDULUM_SETTINGS), chunk=1)
    np.testing.assert_array_equal(asked.result(), one_at_a_time(PENDULUM, PENDULUM_SETTINGS, states))


def test_a_resumed_run_asks_only_for_what_its_kept_answers_lack(tmp_path: Path) -> None:
    store = tmp_path / HELD_OUT_FILE
    states = fresh(ARM.task, 0, SETTINGS.held_out)
    expert = make_expert(ARM, 0, SETTINGS)
    first = ExpertReturns(ARM, 0, SETTINGS, states, expert, KeptAnswers(store, RUN), chunk=10).result()
    lines = store.read_text().splitlines()
    assert len(lines) == 1 + 40 and lines[0] == KeptAnswers(store, RUN).header  # one line per s0, as npp-learn's
    assert [json.loads(line)["k"] for line in lines[1:]] == list(range(40))
    again = ExpertReturns(ARM, 0, SETTINGS, states, expert, KeptAnswers(store, RUN), chunk=10)
    assert again.missing_chunks() == []
    np.testing.assert_array_equal(again.result(), first)
    # a crash tore the last line: its s0 is asked again, nothing else, and the next line starts a line of its own
    store.write_text("\n".join(lines[:-1]) + "\n" + lines[-1][: len(lines[-1]) // 2])
    torn = ExpertReturns(ARM, 0, SETTINGS, states, expert, KeptAnswers(store, RUN), chunk=10)
    assert torn.missing_chunks() == [(39, 40)]
    np.testing.assert_array_equal(torn.result(), first)
    assert ExpertReturns(ARM, 0, SETTINGS, states, expert, KeptAnswers(store, RUN)).missing_chunks() == []
    # a damaged line (not numbers) is skipped, and only its s0 asked again
    damaged = [lines[0], lines[1], json.dumps({"k": 1, "s0": "x", "return": "a", "budget_stop": False}), *lines[3:]]
    store.write_text("\n".join(damaged) + "\n")
    assert ExpertReturns(ARM, 0, SETTINGS, states, expert, KeptAnswers(store, RUN), chunk=10).missing_chunks() == [
        (1, 2)
    ]
    # more held-out s0 than before: the first 40 are the same stream's, only the new ones are asked
    more = fresh(ARM.task, 0, 55)
    longer = ExpertReturns(ARM, 0, SETTINGS, more, expert, KeptAnswers(store, RUN), chunk=10)
    assert longer.missing_chunks() == [(1, 2), (40, 50), (50, 55)]
    np.testing.assert_array_equal(longer.result(), one_at_a_time(ARM, SETTINGS, more))


def test_kept_answers_of_another_run_are_refused_in_one_line_and_left_untouched(tmp_path: Path) -> None:
    store = tmp_path / HELD_OUT_FILE
    states = fresh(ARM.task, 0, 10)
    ExpertReturns(ARM, 0, SETTINGS, states, make_expert(ARM, 0, SETTINGS), KeptAnswers(store, RUN)).result()
    before = store.read_bytes()
    with pytest.raises(StoredReturnsError, match="holds the expert's returns of another run") as refused:
        ExpertReturns(ARM, 1, SETTINGS, fresh(ARM.task, 1, 10), make_expert(ARM, 1, SETTINGS),
                      KeptAnswers(store, "another run"))  # fmt: skip
    assert "\n" not in str(refused.value) and store.read_bytes() == before


def test_a_store_in_the_earlier_per_chunk_format_is_refused_naming_it_and_left_untouched(tmp_path: Path) -> None:
    """npp-experiment's files before its returns were named by the run: a header of its own, a line per chunk."""
    store = tmp_path / HELD_OUT_FILE
    states = fresh(ARM.task, 0, 10)
    header = {"task": "lqr_2_1", "seed": 0, "horizon": 200, "expert": {"kind": "optimal"}}
    chunk = {"first": 0, "states": states.tolist(), "returns": one_at_a_time(ARM, SETTINGS, states).tolist(),
             "budget_stops": 0}  # fmt: skip
    store.write_text(json.dumps(header) + "\n" + json.dumps(chunk) + "\n")
    before = store.read_bytes()
    with pytest.raises(StoredReturnsError, match="in the earlier per-chunk format") as refused:
        ExpertReturns(ARM, 0, SETTINGS, states, make_expert(ARM, 0, SETTINGS), KeptAnswers(store, RUN))
    assert "task lqr_2_1, seed 0, horizon 200" in str(refused.value) and "left untouched" in str(refused.value)
    assert store.read_bytes() == before


def test_a_run_resumed_with_another_thread_count_keeps_its_answers(tmp_path: Path) -> None:
    """Threads set how fast answers come, not what they are: the run's identity, which names the kept answers,
    is the same at any thread count."""
    from npp_ros.experiment.arms import arm_request
    from npp_ros.run.held_out import answers_identity
    from npp_ros.run.request import resolve_run

    identities = {
        answers_identity(resolve_run(arm_request(PENDULUM, 0, PENDULUM_SETTINGS), kind="ilqr", threads=t).config)
        for t in (None, 1, 2)
    }
    assert len(identities) == 1


def test_the_held_out_check_counts_the_reference_answers_the_time_budget_cut() -> None:
    """Such answers depend on the machine's speed: heldout.json says how many, asked here or ahead."""
    cut = ExperimentSettings(max_episodes={"pendulum_swingup": 10}, horizon=40, time_budget=1e-9)
    task, states = get_task(PENDULUM.task), fresh(PENDULUM.task, 0, 3)
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


def test_the_answers_the_time_budget_cut_are_kept_per_s0_and_counted_again_on_resuming(tmp_path: Path) -> None:
    cut = ExperimentSettings(max_episodes={"pendulum_swingup": 10}, horizon=40, time_budget=1e-9)
    states, store = fresh(PENDULUM.task, 0, 3), tmp_path / HELD_OUT_FILE
    ExpertReturns(PENDULUM, 0, cut, states, make_expert(PENDULUM, 0, cut), KeptAnswers(store, RUN), chunk=2).result()
    assert [json.loads(line)["budget_stop"] for line in store.read_text().splitlines()[1:]] == [True, True, True]
    resumed = ExpertReturns(PENDULUM, 0, cut, states, make_expert(PENDULUM, 0, cut), KeptAnswers(store, RUN))
    assert resumed.missing_chunks() == [] and resumed.budget_stops == 3


def ask_in_a_run(
    arm: Arm, settings: ExperimentSettings, states: np.ndarray, store: Path, after_one_elsewhere: bool = False
) -> dict[str, Any]:
    """What a run on a Dask worker does: ask ahead, go on, then wait for the returns.

    ``after_one_elsewhere``: the run goes on until another worker has answered a chunk.
    """
    started = time.monotonic()
    kept = KeptAnswers(store, RUN)
    asked = ExpertReturns(arm, 0, settings, states, make_expert(arm, 0, settings), kept, chunk=5).start()
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
    states = fresh(ARM.task, 0, SETTINGS.held_out)
    with two_worker_cluster() as cluster, Client(cluster) as client:
        got = client.submit(ask_in_a_run, ARM, SETTINGS, states, tmp_path / "store.jsonl", True).result(timeout=600)
    np.testing.assert_array_equal(got["returns"], one_at_a_time(ARM, SETTINGS, states))
    assert set(got["workers"]) - {got["worker"]}, got  # the other worker answered chunks
    assert got["progress"][-1] == 40 and got["progress"] == sorted(got["progress"])
    assert len((tmp_path / "store.jsonl").read_text().splitlines()) == 1 + 40  # every chunk's s0 stored, once


@pytest.mark.slow
def test_a_run_answers_the_chunks_no_worker_started_and_keeps_its_slot(tmp_path: Path) -> None:
    """One slot: the run's chunks cannot start elsewhere, so it answers them all, and the next run waits for it."""
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    states = fresh(PENDULUM.task, 0, 10)
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
