"""The supervisor builds its run through resolve_run as npp-learn does, so its run file records the expert's settings
and it refuses a run folder made with others, before it asks the expert for anything."""

from __future__ import annotations

import hashlib
from pathlib import Path

from npp_ros.run.request import RunRequest, resolve_run
from npp_ros.run.setup import build_loop
from npp_ros.run.store import RUN_FILE

SUPERVISOR = "npp-supervisor"


def test_the_supervisor_refuses_a_run_folder_of_other_expert_settings(launch, tmp_path: Path) -> None:
    run_file = tmp_path / "run" / RUN_FILE
    run = resolve_run(RunRequest(task="pendulum_swingup", horizon=50, max_iterations=2), run_file=run_file)
    loop = build_loop(run.config, run.expert, store_path=run_file)
    loop.run(1)
    assert loop.store is not None
    loop.store.close()
    before = hashlib.sha256(run_file.read_bytes()).hexdigest()

    launch("npp-sim", {"task": "pendulum_swingup", "horizon": 50})  # no expert: the refusal comes before any request
    supervisor = launch(SUPERVISOR, {"run_dir": str(run_file.parent), "max_iterations": 9, "values": "return-to-go"})
    supervisor.wait(timeout=120)
    log = launch.log(supervisor)
    assert supervisor.returncode == 1, log
    assert "belongs to another run and was left untouched" in log
    assert "max_iterations: file has 2, this run asks for 9" in log
    assert "values: file has 'window', this run asks for 'return-to-go'" in log
    assert hashlib.sha256(run_file.read_bytes()).hexdigest() == before
