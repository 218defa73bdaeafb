"""npp-experiment on Dask: a local cluster and a scheduler given by address give the in-process numbers.

The reference runs `run_arm_seed` in this process with the settings the command line gives; the
command then runs the same (arm, seed)s on its default local cluster and on a cluster started
here and named by its address. Every stored value must be the same, to the last bit; only the
times a run took may differ.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import sqlite3
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from distributed import Client, LocalCluster

import npp_ros
from npp_ros.cli.experiment import parser, plan, report
from npp_ros.experiment import run_arm_seed

pytestmark = pytest.mark.slow

EXPERIMENT = [sys.executable, "-m", "npp_ros.cli.experiment"]
# the sound oracle mode certifies within 40 episodes here, so the held-out check runs too
REDUCED = [
    "--tasks", "lqr_2_1", "--experts", "optimal", "--lipschitz", "analytic", "--certify", "oracle",
    "--seeds", "0", "1", "--horizon", "50", "--max-episodes", "40", "--checkpoints", "10,40",
    "--evaluate", "4", "--held-out", "10", "--rules", "sequential", "--policies", "open-loop",
]  # fmt: skip
# How long a run took, when, and its random identity: the only values allowed to differ.
TIMES = {"wall_time", "wall_time_s", "created", "run_id"}


def exact(value: Any) -> Any:
    """A value compared bit for bit: floats by repr (which round-trips), NaN equal to NaN."""
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, dict):
        return {k: exact(v) for k, v in value.items() if k not in TIMES}
    if isinstance(value, list | tuple):
        return [exact(v) for v in value]
    return value


def run_files(out: Path) -> dict[str, Any]:
    """Every value a run stored (run.sqlite tables, evaluations.csv, heldout.json), times left out."""
    stored: dict[str, Any] = {}
    for run_dir in sorted((out / "runs").iterdir()):
        conn = sqlite3.connect(f"file:{run_dir / 'run.sqlite'}?mode=ro", uri=True)
        try:
            tables = [name for (name,) in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")]
            for table in sorted(tables):
                cursor = conn.execute(f"SELECT * FROM {table} ORDER BY 1, 2")
                columns = [d[0] for d in cursor.description]
                rows = [dict(zip(columns, row, strict=True)) for row in cursor]
                if table == "meta":
                    rows = [row for row in rows if row["key"] not in TIMES]
                if table == "seal":  # the digests of times and of the run's identity differ; so does the whole run's
                    rows = [row for row in rows if row["part"] != "run" and not any(t in row["part"] for t in TIMES)]
                stored[f"{run_dir.name}/{table}"] = exact(rows)
        finally:
            conn.close()
        header, *lines = (run_dir / "evaluations.csv").read_text().splitlines()
        names = header.split(",")
        stored[f"{run_dir.name}/evaluations.csv"] = [
            {k: v for k, v in zip(names, line.split(","), strict=True) if k not in TIMES} for line in lines
        ]
        stored[f"{run_dir.name}/heldout.json"] = exact(json.loads((run_dir / "heldout.json").read_text()))
    return stored


def stored_results(out: Path) -> list[Any]:
    return exact(json.loads((out / "results.json").read_text()))


@pytest.fixture(scope="module")
def in_process(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The reference: each (arm, seed) run here, one after the other, and the table written from the records."""
    out = tmp_path_factory.mktemp("in-process")
    args = parser().parse_args([*REDUCED, "--out", str(out)])
    settings, arms = plan(args)
    records = [run_arm_seed(arm, seed, settings, out) for arm in arms for seed in args.seeds]
    report(records, settings, out)
    return out


def experiment(out: Path, *extra: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*EXPERIMENT, *REDUCED, "--out", str(out), *extra], capture_output=True, text=True, timeout=timeout
    )


def test_local_cluster_gives_the_in_process_numbers(in_process: Path, tmp_path: Path) -> None:
    run = experiment(tmp_path, "--scheduler", "local", "--jobs", "2")
    assert run.returncode == 0, run.stderr
    assert "Traceback" not in run.stderr
    for seed in (0, 1):  # each finished run names the worker that ran it
        assert f"lqr_2_1-optimal-Lanalytic-oracle-sequential seed {seed} on worker " in run.stderr
    assert "[worker " in run.stderr and ": started" in run.stderr  # the workers' own progress lines
    assert stored_results(tmp_path) == stored_results(in_process)
    assert run_files(tmp_path) == run_files(in_process)
    assert len(run_files(in_process)) == 2 * 7  # both runs: 5 tables (the seal too), evaluations.csv, heldout.json


def test_scheduler_given_by_address_gives_the_in_process_numbers(in_process: Path, tmp_path: Path) -> None:
    with LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address="127.0.0.1:0"
    ) as cluster:
        run = experiment(tmp_path, "--scheduler", cluster.scheduler_address)
    assert run.returncode == 0, run.stderr
    assert "on worker " in run.stderr
    assert stored_results(tmp_path) == stored_results(in_process)
    assert run_files(tmp_path) == run_files(in_process)


def test_unreachable_scheduler_is_one_line_after_the_timeout(tmp_path: Path) -> None:
    with socket.socket() as probe:  # a loopback port nobody listens on
        probe.bind(("127.0.0.1", 0))
        address = f"tcp://127.0.0.1:{probe.getsockname()[1]}"
    run = experiment(tmp_path, "--scheduler", address, "--connect-timeout", "2", timeout=120)
    assert run.returncode == 1
    assert "Traceback" not in run.stderr
    errors = [line for line in run.stderr.splitlines() if "cannot reach" in line]
    assert len(errors) == 1 and errors[0].startswith(f"npp-experiment: cannot reach the Dask scheduler at {address}: ")
    assert not (tmp_path / "results.json").exists()


def test_workers_of_another_npp_ros_are_refused_by_name(tmp_path: Path) -> None:
    """A worker started from another checkout (one changed line) would compute other numbers: refused, named."""
    other = tmp_path / "other"
    shutil.copytree(Path(npp_ros.__file__).parent, other / "npp_ros", ignore=shutil.ignore_patterns("__pycache__"))
    with (other / "npp_ros" / "bounds.py").open("a") as fh:
        fh.write("# another version\n")
    with LocalCluster(
        n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address="127.0.0.1:0"
    ) as cluster:
        stranger = subprocess.Popen(
            [sys.executable, "-m", "distributed.cli.dask_worker", cluster.scheduler_address, "--nthreads", "1",
             "--name", "stranger", "--no-dashboard", "--no-nanny"],
            env={**os.environ, "PYTHONPATH": str(other)}, cwd=other,  # not this checkout's folder: -m puts it first
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        try:
            with Client(cluster) as client:
                client.wait_for_workers(2, timeout=120)
            run = experiment(tmp_path / "out", "--scheduler", cluster.scheduler_address, timeout=300)
        finally:
            stranger.terminate()
            stranger.wait(timeout=30)
    assert run.returncode == 1, run.stderr
    assert "Traceback" not in run.stderr
    refusals = [line for line in run.stderr.splitlines() if "run another npp_ros" in line]
    assert len(refusals) == 1 and "1 of 2 Dask workers" in refusals[0] and "stranger at tcp://" in refusals[0]
    assert not (tmp_path / "out" / "results.json").exists()
