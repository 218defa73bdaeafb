"""Fault injection: SIGKILL any node at a random, seeded moment of a run and restart it as the README says.

Six runs (lqr_2_1, task seeds 0-5, horizon 50) of four kills each, one per node in a random order:
24 trials, 6 per node. `make test` runs the first (a kill of every node); the other five are long runs, in
`make test-long`. Each kill happens once the run has reached a random episode, after a random
delay; the killed node is started again with the same command. After every restart, once the graph
makes progress again: the run file loads without error, and every expert trajectory acknowledged as
stored (published on /npp/dataset/trajectory, which happens only after its commit) is in it exactly
once. At the end of each run: it reaches its certificate, and its episodes and dataset equal an
uninterrupted in-process run's, so every restarted supervisor resumed instead of starting over.

Outcome counts go to fault-report.json / fault-report.md in the test's tmp folder (and to the folder
NPP_FAULT_REPORT names, if set) and are printed. NPP_FAULT_SEED changes the seed (default below); the
plan and result of every trial is in the JSON report.
"""

from __future__ import annotations

import csv
import json
import os
import re
import signal
import subprocess
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest
from graph import graph_parameters, start_node
from npp_interfaces.msg import Certificate, GapReport
from npp_interfaces.msg import Trajectory as TrajectoryMsg
from reference import ROLLOUT_FREE, decisions, uninterrupted_run

from npp_ros.policy.dataset import Dataset
from npp_ros.run.store import RunStore
from npp_ros.run.trajectory_checksum import trajectory_digest
from npp_ros_graph.graph.description import ROLES
from npp_ros_graph.transport.topics import CERTIFICATE, DATASET_TOPIC, GAP, LATCHED_READER_QOS, REPORT_QOS

if TYPE_CHECKING:
    from tests.ros.conftest import Launcher, RosClient

SEED = int(os.environ.get("NPP_FAULT_SEED", "6021"))
RUNS = 6
NODES = ROLES  # the graph's four nodes, in the order npp-run starts them
HORIZON = 50
EPSILON = 50.0
MAX_EPISODES = 400
RECOVERY_TIMEOUT = 180.0  # hang guards only: a healthy restart takes seconds
RUN_TIMEOUT = 600.0


@dataclass
class Trial:
    run: int
    node: str
    kill_at_episode: int  # the kill waits until the run has reported this episode ...
    delay_s: float  # ... and then this long
    killed_during_episode: int = -1  # the last episode reported when the signal went out
    outcome: str = ""
    detail: str = ""
    checks: list[str] = field(default_factory=list)


@dataclass
class RunRecord:
    run: int
    task_seed: int
    episodes: int = 0
    oracle_calls: int = 0
    certified: bool = False
    wall_s: float = 0.0
    trials: list[Trial] = field(default_factory=list)


def plan(run: int, expected_episodes: int) -> list[Trial]:
    """One kill per node in a random order, at random episodes in the first 80% of the run."""
    rng = np.random.default_rng([SEED, run])
    order = rng.permutation(len(NODES))
    episodes = np.sort(rng.integers(2, int(0.8 * expected_episodes), size=len(NODES)))
    delays = rng.uniform(0.0, 0.3, size=len(NODES))
    return [
        Trial(run, NODES[int(k)], int(e), round(float(d), 3)) for k, e, d in zip(order, episodes, delays, strict=True)
    ]


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> Iterator[list[RunRecord]]:
    """Collects every run; at the end writes and prints the outcome counts."""
    records: list[RunRecord] = []
    yield records
    outs = [tmp_path_factory.mktemp("fault-report")]
    if os.environ.get("NPP_FAULT_REPORT"):
        outs.append(Path(os.environ["NPP_FAULT_REPORT"]))
        outs[-1].mkdir(parents=True, exist_ok=True)
    trials = [t for r in records for t in r.trials]
    summary: dict[str, Any] = {
        "seed": SEED,
        "config": {"task": "lqr_2_1", "horizon": HORIZON, "epsilon": EPSILON, "lipschitz": "analytic", **ROLLOUT_FREE},
        "runs": len(records),
        "runs_certified": sum(r.certified for r in records),
        "trials": len(trials),
        "kills_per_node": dict(Counter(t.node for t in trials)),
        "outcomes": {node: dict(Counter(t.outcome for t in trials if t.node == node)) for node in NODES},
        "checks_passed": dict(Counter(c for t in trials for c in t.checks)),
        "wall_s": round(sum(r.wall_s for r in records), 1),
        "detail": [asdict(r) for r in records],
    }
    for out in outs:
        (out / "fault-report.json").write_text(json.dumps(summary, indent=2))
    lines = [
        f"# Fault injection (seed {SEED})",
        "",
        f"{summary['trials']} kills over {summary['runs']} runs, {summary['runs_certified']} runs certified, "
        f"{summary['wall_s']} s.",
        "",
        "| node | kills | outcome | count |",
        "|---|---|---|---|",
    ]
    for node in NODES:
        kills = summary["kills_per_node"].get(node, 0)
        for outcome, count in sorted(summary["outcomes"][node].items()):
            lines.append(f"| {node} | {kills} | {outcome} | {count} |")
    lines += ["", "Checks passed: " + ", ".join(f"{k} {v}" for k, v in sorted(summary["checks_passed"].items()))]
    for out in outs:
        (out / "fault-report.md").write_text("\n".join(lines) + "\n")
    print("\n" + "\n".join(lines) + f"\n(report: {', '.join(map(str, outs))})")


def expected_run(task_seed: int) -> tuple[list[tuple[Any, ...]], Dataset, int]:
    """The uninterrupted run in process: the numbers every faulted run must end with."""
    loop, result = uninterrupted_run(task_seed, EPSILON, HORIZON, MAX_EPISODES, **ROLLOUT_FREE)
    assert result.certified
    return decisions(result.rows), loop.dataset, result.episodes


class Graph:
    """The four node processes of one run, restartable by name with their original command."""

    def __init__(self, launch: Launcher, params: dict[str, dict[str, Any]]) -> None:
        self.launch, self.params = launch, params
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.history: dict[str, list[subprocess.Popen[bytes]]] = {name: [] for name in NODES}

    def start(self, name: str) -> None:
        self.procs[name] = start_node(self.launch, name, self.params[name])
        self.history[name].append(self.procs[name])

    def kill(self, name: str) -> None:
        proc = self.procs[name]
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)

    def supervisor_logs(self) -> str:
        return "\n".join(self.launch.log(p) for p in self.history["supervisor"])

    def assert_alive(self) -> None:
        for proc in self.procs.values():
            self.launch.assert_alive(proc)


def check_stored(run_file: Path, acked: list[TrajectoryMsg]) -> Dataset:
    """The file loads (every checksum verified) and holds each acknowledged trajectory exactly once."""
    with RunStore.open(run_file) as store:  # the supervisor may commit between the two reads:
        rows = store.episodes()  # so read the log first, and the data it names after it
        data = store.load_dataset()
    held = data.num_trajectories
    digests = [trajectory_digest(data.trajectory(k)) for k in range(held)]
    assert len(set(digests)) == held, "a trajectory is stored twice"
    called = [r.trajectory for r in rows if r.oracle_called]
    assert called == list(range(len(called))) and len(called) <= held, "episode log and data disagree"
    for msg in acked:
        assert msg.index < held, f"acknowledged trajectory {msg.index} is missing (the file holds {held})"
        stored = data.trajectory(msg.index)
        np.testing.assert_array_equal(np.asarray(msg.states).reshape(stored.states.shape), stored.states)
        np.testing.assert_array_equal(np.asarray(msg.values), stored.values)
    return data


def lost_rollouts(run_file: Path, up_to: int) -> int:
    with RunStore.open(run_file) as store:
        return sum(r.policy_return is None for r in store.episodes() if r.episode <= up_to)


@pytest.mark.parametrize("run", [pytest.param(run, marks=[pytest.mark.long] if run else []) for run in range(RUNS)])
def test_sigkill_any_node_mid_run_loses_nothing(
    run: int, launch: Launcher, ros_client: Callable[..., RosClient], tmp_path: Path, report: list[RunRecord]
) -> None:
    started = time.monotonic()
    task_seed = run
    expected_rows, expected_data, expected_episodes = expected_run(task_seed)
    record = RunRecord(run, task_seed, trials=plan(run, expected_episodes))
    report.append(record)
    run_dir = tmp_path / "run"
    run_file = run_dir / "run.sqlite"
    graph = Graph(
        launch,
        graph_parameters("lqr_2_1", task_seed, HORIZON, run_dir, supervisor={
            "epsilon": EPSILON, "max_episodes": MAX_EPISODES, **ROLLOUT_FREE,
            "expert_timeout": 3.0, "expert_retries": 20, "rollout_timeout": 8.0,
        }),
    )  # fmt: skip
    watcher = ros_client(f"fault_watcher_{run}")
    gaps: list[GapReport] = watcher.collect(GapReport, GAP, REPORT_QOS)
    acked: list[TrajectoryMsg] = watcher.collect(TrajectoryMsg, DATASET_TOPIC, REPORT_QOS)
    certificates: list[Certificate] = watcher.collect(Certificate, CERTIFICATE, LATCHED_READER_QOS)
    for name in NODES:
        graph.start(name)

    def last_episode() -> int:
        return gaps[-1].episode if gaps else -1

    for trial in record.trials:
        watcher.wait_for(lambda t=trial: last_episode() >= t.kill_at_episode, RECOVERY_TIMEOUT, f"{trial}")
        assert not certificates, "the run ended before every kill was made"
        deadline = time.monotonic() + trial.delay_s
        watcher.wait_for(lambda d=deadline: time.monotonic() >= d, trial.delay_s + 5)
        trial.killed_during_episode = last_episode()
        expert_failures = graph.supervisor_logs().count("expert call")
        graph.kill(trial.node)

        resume_at = -1
        if trial.node == "supervisor":
            check_stored(run_file, list(acked))  # what the dead supervisor acknowledged survived
            with RunStore.open(run_file) as store:
                resume_at = len(store.episodes())
        graph.start(trial.node)  # the README's restart: the same command again
        seen = last_episode()
        # Two episodes past the restart. After a supervisor's, count from where it resumes: reports the killed
        # one published before it died (all of episodes it had stored) may still be on their way here.
        target = max(seen, resume_at - 1) + 2
        watcher.wait_for(
            lambda t=target: last_episode() >= t or bool(certificates), RECOVERY_TIMEOUT, "progress after a restart"
        )
        graph.assert_alive()
        check_stored(run_file, list(acked))
        trial.checks += ["file loads", "acknowledged trajectories stored exactly once"]

        if trial.node == "supervisor":
            log = graph.launch.log(graph.procs["supervisor"])
            assert f"resuming at episode {resume_at} in" in log, log[-2000:]
            trial.outcome = "resumed from run.sqlite"
            trial.detail = f"resumed at episode {resume_at}"
        elif trial.node == "expert":
            retried = graph.supervisor_logs().count("expert call") > expert_failures
            trial.outcome = "an expert call failed and was retried" if retried else "no expert call was affected"
        else:
            before = lost_rollouts(run_file, trial.killed_during_episode)
            after = lost_rollouts(run_file, last_episode())
            trial.outcome = f"{after - before} rollout(s) lost, run went on" if after > before else "no rollout lost"

    watcher.wait_for(lambda: bool(certificates), RUN_TIMEOUT, "the certificate")
    graph.assert_alive()
    data = check_stored(run_file, list(acked))
    with RunStore.open(run_file) as store:
        rows = store.episodes()
        stored_certificate = store.certificate()
    assert stored_certificate is not None and certificates[-1].episodes == len(rows) == expected_episodes
    # Resumed, never restarted: the same episodes, gaps and data as an uninterrupted run.
    assert decisions(rows) == expected_rows
    np.testing.assert_array_equal(data.states, expected_data.states)
    np.testing.assert_array_equal(data.values, expected_data.values)
    with (run_dir / "gaps.csv").open() as fh:  # each supervisor appended only episodes it ran itself
        logged = [int(row["episode"]) for row in csv.DictReader(fh)]
    assert logged == sorted(set(logged)), "an episode was run twice"
    resumes = re.findall(r"resuming at episode (\d+)", graph.supervisor_logs())
    assert len(resumes) == 1
    for trial in record.trials:
        trial.checks.append("run certified, same numbers as uninterrupted")
    record.episodes, record.oracle_calls, record.certified = len(rows), data.num_trajectories, True
    record.wall_s = round(time.monotonic() - started, 1)
