"""npp-experiment in a reduced configuration of the same code: files, claims, resume, same loop."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from npp_ros.certificate.certifier import DEFAULT_RULES
from npp_ros.experiment import Arm, ExperimentSettings, default_arms, read_evaluations, verdict
from npp_ros.run.setup import build_config, build_loop, resolve_lipschitz
from npp_ros.run.store import RunStore
from npp_ros.tasks.builtin.lqr import DetunedLQRExpert, LQRExpert, LQRPlant, episode_rng, sample_initial_state
from npp_ros.tasks.rollout import rollout

EXPERIMENT = [sys.executable, "-m", "npp_ros.cli.experiment"]
# The paper's experiment, reduced: its open-loop policy (arms named as the paper's), each certificate checked on
# 50 fresh s0 where npp-experiment's own default is 1,000.
REDUCED = [
    "--tasks",
    "lqr_2_1",
    "--seeds",
    "0",
    "--evaluate",
    "4",
    "--horizon",
    "200",
    "--jobs",
    "1",
    "--policies",
    "open-loop",
    "--held-out",
    "50",
]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def run_experiment(out: Path, max_episodes: int, *extra: str) -> subprocess.CompletedProcess[str]:
    args = [*EXPERIMENT, *REDUCED, "--max-episodes", str(max_episodes), "--checkpoints", "10,20,30", "--out", str(out)]
    return subprocess.run([*args, *extra], capture_output=True, text=True, timeout=600)


def results(out: Path) -> list[dict]:
    return json.loads((out / "results.json").read_text())


def without_wall_time(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in row.items() if k != "wall_time_s"} for row in rows]


@pytest.fixture(scope="module")
def reduced_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("experiment")
    run = run_experiment(out, 30)
    assert run.returncode == 0, run.stderr
    assert "runs done" in run.stderr  # live status
    return out


def test_bad_options_get_a_clear_error(tmp_path: Path) -> None:
    run = subprocess.run([*EXPERIMENT, "--lipschitz", "huge", "--out", str(tmp_path)], capture_output=True, text=True)
    expected = "L setting must be one of paper, analytic, data or a number > 0, got 'huge'"
    assert run.returncode == 2 and expected in run.stderr
    run = subprocess.run([*EXPERIMENT, "--p", "1.2", "--out", str(tmp_path)], capture_output=True, text=True)
    assert run.returncode == 2 and "p and delta must lie in (0, 1)" in run.stderr


def test_help_explains_the_options() -> None:
    out = subprocess.run([*EXPERIMENT, "--help"], capture_output=True, text=True, check=True).stdout
    for option in ("--tasks", "--seeds", "--lipschitz", "--experts", "--max-episodes", "--evaluate", "--out"):
        assert option in out


@pytest.mark.long
def test_writes_figures_and_tables(reduced_run: Path) -> None:
    for arm in ("lqr_2_1-optimal-Lpaper", "lqr_2_1-optimal-Lanalytic", "lqr_2_1-detuned-Lanalytic"):
        for fig in ("fig4", "fig5"):
            assert (reduced_run / f"{fig}-{arm}.png").read_bytes()[:8] == PNG_MAGIC
    rows = results(reduced_run)
    assert [(r["expert"], r["lipschitz_setting"]) for r in rows] == [
        ("detuned", "analytic"),
        ("optimal", "analytic"),
        ("optimal", "paper"),
    ]
    with (reduced_run / "results.csv").open() as fh:
        assert len(list(csv.DictReader(fh))) == 3
    table = (reduced_run / "results.md").read_text()
    certificates, rest = table.split("## Per arm")
    per_arm, per_seed = rest.split("## Per seed")
    assert certificates.count("\n| lqr_2_1 |") == 3
    assert per_arm.count("\n| lqr_2_1 |") == 3 and per_seed.count("\n| lqr_2_1 |") == 3
    assert "**not a bound**" in per_arm and "**not a bound**" in per_seed
    history = json.loads((reduced_run / "experiment.json").read_text())["invocations"]
    assert history[0]["runs"] == 3 and history[0]["failed"] == []


def test_table_claims_follow_from_the_measured_columns(reduced_run: Path) -> None:
    for row in results(reduced_run):
        run_dir = reduced_run / "runs" / f"{row['task']}-{row['expert']}-L{row['lipschitz_setting']}-seed{row['seed']}"
        evaluations = read_evaluations(run_dir / "evaluations.csv")
        final = [e for e in evaluations if e.checkpoint == row["evaluated_at"]]
        gaps = np.array([e.expert_return - e.policy_return for e in final])
        assert row["rollouts"] == len(final) == 4
        assert row["policy_return_q50"] == pytest.approx(np.median([e.policy_return for e in final]))
        assert row["expert_return_q50"] == pytest.approx(np.median([e.expert_return for e in final]))
        assert row["fraction_within_epsilon"] == pytest.approx(np.mean(gaps <= row["epsilon"]))
        assert row["lower_bound_violations"] == sum(e.policy_return < e.v_lb - 1e-9 * abs(e.v_lb) for e in final)
        assert row["l_is_bound"] == (row["lipschitz"] >= row["slope_needed"])
        assert row["dataset_size"] == 200 * row["oracle_calls"]
        expected = verdict(
            row["certified_episode"] is not None,
            row["fraction_within_epsilon"],
            row["rollouts"],
            row["lower_bound_violations"],
            0.9,
            0.1,
        )
        assert row["verdict"] == expected
        if row["lipschitz_setting"] == "analytic":  # Theorem 3.4 / B.1 (i) hold when L bounds the slope
            assert row["l_is_bound"] and row["lower_bound_violations"] == 0 and row["crossed_bounds"] == 0
        else:
            assert not row["l_is_bound"]


def test_repeated_command_recomputes_nothing_and_gives_the_same_numbers(reduced_run: Path) -> None:
    before = results(reduced_run)
    again = run_experiment(reduced_run, 30)
    assert again.returncode == 0, again.stderr
    assert results(reduced_run) == before


def test_resumed_run_matches_an_uninterrupted_one(reduced_run: Path, tmp_path: Path) -> None:
    assert run_experiment(tmp_path, 20, "--lipschitz", "analytic", "--experts", "optimal").returncode == 0
    resumed = run_experiment(tmp_path, 30, "--lipschitz", "analytic", "--experts", "optimal")
    assert resumed.returncode == 0, resumed.stderr
    direct = [r for r in results(reduced_run) if (r["expert"], r["lipschitz_setting"]) == ("optimal", "analytic")]
    assert without_wall_time(results(tmp_path)) == without_wall_time(direct)


def test_experiment_runs_the_same_loop_as_everyone_else(reduced_run: Path) -> None:
    """The same seed through build_loop (what npp-learn and the supervisor node use) gives the same gaps."""
    expert = LQRExpert("lqr_2_1", 0, horizon=200)
    lipschitz = resolve_lipschitz("lqr_2_1", "analytic", expert)
    config = build_config("lqr_2_1", 0, lipschitz, 50.0, horizon=200, certify="surrogate", rule="paper")
    direct = build_loop(config, expert).run(30)
    with RunStore.open(reduced_run / "runs" / "lqr_2_1-optimal-Lanalytic-seed0" / "run.sqlite") as store:
        stored = store.episodes()
        dataset = store.load_dataset()
    assert [row.gap for row in stored] == [row.gap for row in direct.rows]
    assert [row.oracle_called for row in stored] == [row.oracle_called for row in direct.rows]
    assert dataset.num_trajectories == direct.oracle_calls and len(dataset) == direct.dataset_size


def test_detuned_expert_values_are_its_measured_returns() -> None:
    """Appendix B needs Q_i = Q^pi~(s_i, a_i): the detuned controller's own closed-form values."""
    detuned, optimal = DetunedLQRExpert("lqr_2_1", 0), LQRExpert("lqr_2_1", 0)
    plant = LQRPlant("lqr_2_1", 0)
    for episode in range(5):
        s0 = sample_initial_state("lqr_2_1", episode_rng(7, episode))
        measured = rollout(plant, detuned.action, s0, 1000).total_return
        assert measured == pytest.approx(detuned.value(s0), abs=1e-3)
        assert detuned.value(s0) < optimal.value(s0) - 30  # really suboptimal: more than half of epsilon = 50
    assert detuned.analytic_lipschitz().value > optimal.analytic_lipschitz().value
    with pytest.raises(ValueError, match="control_weight must be finite and > 0"):
        DetunedLQRExpert("lqr_2_1", 0, control_weight=-1.0)


def test_verdicts() -> None:
    assert verdict(False, 1.0, 100, 0, 0.9, 0.1) == "no certificate"
    assert verdict(True, 0.95, 100, 0, 0.9, 0.1) == "held"
    assert verdict(True, 0.95, 100, 7, 0.9, 0.1).startswith("held here, but L is not a bound (7")
    assert verdict(True, 0.5, 100, 0, 0.9, 0.1).startswith("FAILED: 50% within eps")
    assert verdict(True, 0.88, 100, 0, 0.9, 0.1).startswith("below p, not significant")


def test_arms_and_settings_reject_unknown_names() -> None:
    with pytest.raises(ValueError, match="unknown task 'lqr_9_9'"):
        Arm("lqr_9_9", "optimal", "paper")
    with pytest.raises(ValueError, match="unknown expert 'ppo'"):
        Arm("lqr_2_1", "ppo", "paper")
    with pytest.raises(ValueError, match="L setting must be one of paper, analytic, data or a number > 0, got '-5'"):
        Arm("lqr_2_1", "optimal", "-5")
    assert Arm("lqr_2_1", "optimal", "300").name == "lqr_2_1-optimal-L300"
    settings = ExperimentSettings(max_episodes={"lqr_2_1": 150}, checkpoints=(10, 100, 200))
    assert settings.checkpoints_for("lqr_2_1") == [10, 100, 150]


def test_expert_stop_reaches_the_optimizer_experts_and_no_other() -> None:
    """--expert-stop is an option of every iLQR expert an experiment makes (its answers depend on it: it is
    part of their identity); closed-form experts take none. Without it each task decides (None)."""
    from npp_ros.cli.experiment import parser, plan
    from npp_ros.experiment.arms import expert_options

    example = str(Path(__file__).resolve().parents[1] / "examples" / "two_link_arm" / "task.toml")
    for flags, wanted in (([], None), (["--expert-stop", "time"], "time")):
        settings, arms = plan(
            parser().parse_args(["--tasks", example, "lqr_2_1", "--epsilon", "5", "--horizon", "50", *flags])
        )
        stops = {arm.task.split("#")[0]: expert_options(arm, settings).stop for arm in arms}  # a file's: path#digest
        assert stops == {example: wanted, "lqr_2_1": None}, stops
        assert all(expert_options(a, settings).answer_identity()["stop"] == stops[a.task.split("#")[0]] for a in arms)


@pytest.mark.long
def test_sound_modes_are_arms_and_every_certificate_is_checked_on_held_out_states(tmp_path: Path) -> None:
    run = run_experiment(
        tmp_path, 60, "--lipschitz", "analytic", "--experts", "optimal", "--certify", "rollout", "oracle",
        "--rules", "sequential",
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    rows = {r["certify"]: r for r in results(tmp_path)}
    assert set(rows) == {"rollout", "oracle"} and all(r["rule"] == "sequential" for r in rows.values())
    oracle = rows["oracle"]
    assert oracle["certified_episode"] is not None  # one failed check, then a streak of 30
    check = json.loads(
        (tmp_path / "runs" / "lqr_2_1-optimal-Lanalytic-oracle-sequential-seed0" / "heldout.json").read_text()
    )
    assert check["states"] == oracle["held_out_states"] == 50
    assert check["fraction"] == oracle["held_out_fraction"] == check["within"] / 50
    assert check["reference"] == "the expert's H-step return" and not check["rejected"]
    assert oracle["held_out_verdict"].startswith("held")
    table = (tmp_path / "results.md").read_text()
    assert "| lqr_2_1 | optimal | analytic | oracle (sequential) | 1/1 |" in table


def test_sound_modes_run_under_their_default_rule_or_the_rules_asked_for() -> None:
    arms = default_arms(["lqr_2_1"], ["analytic"], ["optimal"], ["rollout", "oracle"])
    assert [(a.certify, a.rule) for a in arms] == [(mode, DEFAULT_RULES[mode]) for mode in ("rollout", "oracle")]
    assert DEFAULT_RULES == {
        "rollout": "sequential", "oracle": "sequential", "surrogate": "sequential", "success": "sequential"
    }  # fmt: skip
    both = default_arms(["lqr_2_1"], ["analytic"], ["optimal"], ["oracle", "paper"], ["sequential", "mixture"])
    assert [a.name for a in both] == [
        "lqr_2_1-optimal-Lanalytic-oracle-sequential", "lqr_2_1-optimal-Lanalytic-oracle-mixture",
        "lqr_2_1-optimal-Lanalytic",
    ]  # fmt: skip
