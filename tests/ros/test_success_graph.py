"""npp-run over an expert that never meets its task's success criterion: the warning comes before the certificate,
the certificate says it, and the graph judges the expert and the policy exactly as the in-process run does."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

from npp_ros.run.setup import build_config, build_loop
from npp_ros.run.store import RunStore
from npp_ros.tasks.registry import ExpertOptions, get_task

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "examples" / "two_link_arm"
NEVER = '\n[success]\njoint = "elbow"\nwithin = [5.0, 6.0]\ndescription = "the elbow past 5 rad"\n'  # stored wrapped
HORIZON, EPSILON = 20, 100.0  # every check passes (a return is at most 22): certified after 31 episodes


def test_npp_run_warns_before_the_certificate_when_the_expert_never_succeeds(tmp_path: Path, ros_domain: int) -> None:
    shutil.copy(EXAMPLE / "arm.xml", tmp_path / "arm.xml")
    task_file = tmp_path / "task.toml"
    task_file.write_text((EXAMPLE / "task.toml").read_text() + NEVER)
    run_dir = tmp_path / "run"
    command = [
        sys.executable, "-m", "npp_ros_graph.tools.run", "--task", str(task_file), "--horizon", str(HORIZON),
        "--epsilon", str(EPSILON), "--max-episodes", "60", "--time-budget", "60", "--run-dir", str(run_dir),
    ]  # fmt: skip
    run = subprocess.run(command, capture_output=True, text=True, timeout=600, cwd=REPO)
    logs = "\n".join(f"== {p.name}\n{p.read_text()[-3000:]}" for p in sorted((run_dir / "logs").glob("*.log")))
    assert run.returncode == 0, f"{run.stderr[-3000:]}\n{logs}"
    assert "npp-run: WARNING: the expert succeeded on 0 of its 31 answers (0%); success: the elbow past 5 rad" in (
        run.stderr
    )
    assert "the expert succeeded on 0 of 31 answers; the policy on 0 of 30 checked episodes" in run.stdout
    with RunStore.open(run_dir / "run.sqlite") as store:
        rows, certificate = store.episodes(), store.certificate()
    assert certificate is not None and len(rows) == certificate["episodes"] == 31

    task = get_task(str(task_file))
    expert = task.make_expert(0, HORIZON, ExpertOptions(time_budget=60.0))
    lipschitz = task.resolve_lipschitz(task.default_lipschitz_choice(), expert)
    config = build_config(task.name, 0, lipschitz, EPSILON, horizon=HORIZON)
    local = build_loop(config, expert)
    local.run(31)
    assert [(r.expert_success, r.policy_success) for r in rows] == [
        (r.expert_success, r.policy_success) for r in local.rows
    ]
    assert [r.policy_return for r in rows] == [r.policy_return for r in local.rows]
    assert local.certificate is not None and certificate == local.certificate.record()
