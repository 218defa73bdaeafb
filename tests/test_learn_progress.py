"""npp-learn's held-out evaluation is never silent: each phase (the policy's rollouts, the expert's returns from
the same s0) prints its count and the seconds since it began, from 0 on."""

from __future__ import annotations

import io
import re
import subprocess
import sys
from pathlib import Path

from npp_ros.certificate.certifier import Certificate, CertificationSpec
from npp_ros.policy.lipschitz import LipschitzConstant
from npp_ros.run.progress import Counter
from npp_ros.run.store import RunStore

ARM = Path(__file__).resolve().parents[1] / "examples" / "two_link_arm" / "task.toml"


def test_a_counter_says_its_count_and_seconds_from_the_start() -> None:
    out = io.StringIO()
    count = Counter("held-out: the expert's returns", out, every=3600.0)
    for done in range(4):
        count(done, 3)
    lines = out.getvalue().splitlines()
    assert lines == ["held-out: the expert's returns 0/3 (0 s)", "held-out: the expert's returns 3/3 (0 s)"]


def test_npp_learn_reports_both_held_out_phases(tmp_path: Path) -> None:
    run = subprocess.run(
        [sys.executable, "-m", "npp_ros.cli.learn", "--task", str(ARM), "--horizon", "20", "--epsilon", "5",
         "--max-episodes", "2", "--evaluate", "3", "--run-dir", str(tmp_path)],
        capture_output=True, text=True,
    )  # fmt: skip
    assert run.returncode == 1, run.stderr  # two episodes certify nothing
    for phase in ("held-out: policy rollouts", "held-out: the expert's returns"):
        assert f"{phase} 0/3 (" in run.stderr and f"{phase} 3/3 (" in run.stderr, run.stderr
    assert run.stderr.index("held-out: policy rollouts 3/3") < run.stderr.index("held-out: the expert's returns 0/3")
    # the task file's task by its name key, not its path and hash
    assert run.stderr.startswith("npp-learn: two_link_arm_reach seed 0, oracle claim, epsilon 5; the policy acts")
    assert "note: two_link_arm_reach states no success criterion" in run.stderr
    assert "NOT CERTIFIED (two_link_arm_reach) after 2 episodes" in run.stdout and "sha256" not in run.stdout
    # oracle mode (the file's): the claim rests on no L, so no L check is printed as if it did
    assert "L check    " not in run.stdout and "oracle mode's claim does not rest on L" in run.stdout


def test_a_certificate_names_its_task_by_label_and_keeps_its_identity() -> None:
    spec = CertificationSpec("i", 5.0, 0.9, 0.1, LipschitzConstant(1.0, "user"), certify="oracle")
    identity = "/robots/arm/task.toml#sha256=ab12"
    certificate = Certificate(
        task=identity, spec=spec, episodes=31, oracle_calls=31, dataset_size=310, policy_trajectories=1, window=30,
        required=30, test=1, delta_spent=0.05, value="V", statement="claim", proven=True, assumptions=(),
    )  # fmt: skip
    lines = certificate.summary("arm_reach").splitlines()
    assert lines[0].startswith("CERTIFICATE (arm_reach, condition (i)") and lines[1] == f"  task            {identity}"
    assert certificate.summary().startswith(f"CERTIFICATE ({identity},")


def certify_lqr(run_dir: Path, evaluate: int) -> subprocess.CompletedProcess[str]:
    """npp-learn on lqr_2_1 at H = 100, oracle checks, the open-loop policy: certified in about 30 episodes, whose
    checks fail now and then."""
    run = subprocess.run(
        [sys.executable, "-m", "npp_ros.cli.learn", "--task", "lqr_2_1", "--horizon", "100", "--epsilon", "2",
         "--certify", "oracle", "--policy", "open-loop", "--lipschitz", "analytic", "--evaluate", str(evaluate),
         "--run-dir", str(run_dir)],
        capture_output=True, text=True,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    return run


def test_npp_learn_says_certified_when_the_certificate_is_issued_before_its_held_out_check(tmp_path: Path) -> None:
    run = certify_lqr(tmp_path, evaluate=5)
    said = run.stderr.index("npp-learn: certified after ")
    assert said < run.stderr.index("held-out: policy rollouts 0/5"), run.stderr
    assert "expert calls (the policy over " in run.stderr


def test_a_logs_progress_lines_count_every_check_and_show_every_failed_one(tmp_path: Path) -> None:
    """Off a terminal, a line per failed check and periodic lines for the passes, each saying how many passed since
    the line before: no check goes uncounted, and a log does not read as if only the failed ones ran."""
    run = certify_lqr(tmp_path, evaluate=0)
    lines = [line for line in run.stderr.splitlines() if line.startswith("episode ")]
    with RunStore.open(tmp_path / "run.sqlite") as store:
        rows = store.episodes()
    failed = [row.episode + 1 for row in rows if not row.checked_gap <= 2.0]
    shown = [int(line.split()[1]) for line in lines]
    assert set(failed) <= set(shown)  # every failed check has its line
    unsaid = [int(m.group(1)) for line in lines if (m := re.search(r"(\d+) more passed since the last line", line))]
    assert len(lines) + sum(unsaid) == len(rows)  # and every check is counted
