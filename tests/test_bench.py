"""npp-bench --quick runs end to end, writes its table and JSON, and reports exactness (never speed); the expert
part reports each request and whether it held the pole upright (never how fast)."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest

from npp_ros.bench.measure import UPRIGHT_DEGREES, Progress, machine_info, time_expert
from npp_ros.bench.queries import BOUNDS, LARGE_LIPSCHITZ
from npp_ros.bench.report import expert_label, with_queries
from npp_ros.cli.bench import main
from npp_ros.run.api import learn
from npp_ros.run.read import read_run
from npp_ros.tasks.registry import get_task
from npp_ros.trajopt.batch_steps import default_threads
from npp_ros.trajopt.expert import DEFAULT_GUARD_S


def test_quick_bench_writes_markdown_and_json_with_exactness(tmp_path: Path, capsys) -> None:
    assert main(["--quick", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "bench.json").read_text())
    table = (tmp_path / "bench.md").read_text()
    assert result["all_exact"] is True
    assert {c["name"] for c in result["cases"]} == {
        "12-D lqr_6_2, L analytic", "4-D lqr_2_1, L analytic", "4-D lqr_2_1, L paper"
    }  # fmt: skip
    for case in result["cases"]:
        exact = case["exact"]
        assert exact["exact"] is True and exact["queries"] > 0
        assert exact["lower_same_index"] == exact["upper_same_index"] == exact["queries"]
        assert exact["lower_same_value"] == exact["upper_same_value"] == exact["queries"]
        for key in ("index_lower_batch", "index_upper_single", "pykdtree_batch", "ckdtree_single"):
            timing = case["timings"][key]
            assert timing["min_us"] <= timing["median_us"] <= timing["max_us"]
            assert len(timing["samples_us"]) == result["settings"]["repeats"]
        assert set(case["ratios"]) >= {"lower_vs_1nn_batch", "both_vs_1nn_single"}
    assert result["scaling"] and all(row["exact"]["exact"] for row in result["scaling"])
    assert result["ties"]["exact"] is True and result["ties"]["tied_queries_lower"] > 0
    assert result["compile"]["cold_first_query_s"] > 0
    machine = result["machine"]
    assert machine["cores"] >= 1 and machine["numpy"] and machine["numba"] and machine["python"]
    assert all({"case", "metric", "value", "target", "met"} <= set(row) for row in result["targets"])
    assert "## Targets" in table and "pykdtree" in table and "All exact: **True**" in table
    assert "npp-bench" in capsys.readouterr().out


def test_help_names_the_outputs(capsys) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert "--quick" in out and "bench.json" in out and "results/bench" in out
    assert "--only {experts,throughput,queries}" in out and "--expert-requests" in out and "pendulum_swingup" in out
    assert "--throughput-workers" in out and "--throughput-tasks" in out
    assert "--query-task" in out and "--query-sizes" in out and "--query-run" in out and "--query-lipschitz" in out
    assert "panda_reach" in out and "p99" in out


def test_only_experts_reports_each_request_and_keeps_the_rest_of_the_file(tmp_path: Path, capsys) -> None:
    (tmp_path / "bench.json").write_text(json.dumps({
        "command": "npp-bench", "date": "then", "machine": machine_info(), "load_average_end": None,
        "targets": [{"case": "kept row", "metric": "ratio", "value": 1.0, "target": "<= 2x", "met": True}],
    }))  # fmt: skip
    argv = ["--only", "experts", "--expert-requests", "2", "--expert-horizon", "40", "--out", str(tmp_path)]
    for _ in range(2):  # a second run replaces the first one's section and target rows
        assert main(argv) == 0
    result = json.loads((tmp_path / "bench.json").read_text())
    table = (tmp_path / "bench.md").read_text()
    assert result["command"] == "npp-bench" and result["targets"][0]["case"] == "kept row"
    assert [row["case"] for row in result["targets"]] == [
        "kept row",
        "iLQR expert pendulum_swingup, H = 40, 2 requests",
    ]
    experts = result["experts"]
    assert experts["command"] == "npp-bench " + " ".join(argv)
    assert [t["task"] for t in experts["tasks"]] == ["pendulum_swingup", "cartpole_swingup"]
    for t in experts["tasks"]:
        assert t["horizon"] == 40 and t["requests"] == len(t["detail"]) == 2
        options = t["options"]  # the task's defaults: iterations decide, the time budget a guard
        expected = ("iterations", DEFAULT_GUARD_S, "window")
        assert (options["stop"], options["time_budget_s"], options["values"]) == expected
        s = t["seconds"]
        assert s["min_s"] <= s["q25_s"] <= s["median_s"] <= s["q75_s"] <= s["max_s"] and len(s["samples_s"]) == 2
        assert set(t["phases_s"]) == {"derivatives", "backward", "line_search", "rollout", "optimizer_other",
                                      "warm_start_and_replays"}  # fmt: skip
        assert sum(t["phase_shares"].values()) == pytest.approx(1.0)
        assert t["succeeded"] == sum(r["success"] for r in t["detail"])
        for r in t["detail"]:
            assert r["success"] == (r["worst_angle_deg"] <= UPRIGHT_DEGREES)
            assert r["stop_reason"] in {"converged", "max iterations", "time budget", "regularisation limit",
                                        "no improving step"}  # fmt: skip
    # s0 of episodes 0 and 1 of seed 0: the stream a run with that seed sees
    pendulum = get_task("pendulum_swingup")
    assert experts["tasks"][0]["detail"][1]["s0"] == pendulum.initial_state(0, 1).tolist()
    assert experts["tasks"][0]["met"] is not None and experts["tasks"][1]["target_s"] is None
    assert "## iLQR experts" in table and "kept row" in table and table.count("iLQR expert pendulum_swingup") == 1
    assert "## iLQR experts" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("task", "upright", "hanging"),
    [
        ("pendulum_swingup", [0.02, 0.0], [np.pi, 0.0]),
        ("cartpole_swingup", [0.0, 0.02, 0.0, 0.0], [0.0, np.pi, 0.0, 0.0]),
    ],
)
def test_expert_success_means_the_pole_was_held_upright(task: str, upright: list[float], hanging: list[float]) -> None:
    """Started upright, the expert holds the pole; hanging, 60 steps are too few to swing it up."""
    progress = Progress(2, stream=io.StringIO())
    (report,) = time_expert(task, [np.array(upright), np.array(hanging)], 60, 0, progress)
    assert [r["success"] for r in report["detail"]] == [True, False]
    assert report["detail"][0]["worst_angle_deg"] <= UPRIGHT_DEGREES < report["detail"][1]["worst_angle_deg"]
    assert report["succeeded"] == 1 and report["success_rule"].startswith(get_task(task).success.describe())


def test_both_ilqr_paths_are_timed_on_the_same_s0_and_answer_alike() -> None:
    """--expert-paths batch reference: one result per path, each s0 asked of both, the same answers."""
    progress = Progress(4, stream=io.StringIO())
    starts = [get_task("cartpole_swingup").initial_state(0, k) for k in range(2)]
    batch, reference = time_expert("cartpole_swingup", starts, 60, 0, progress, ("batch", "reference"))
    assert (batch["path"], reference["path"]) == ("batch", "reference")
    assert (expert_label(batch), expert_label(reference)) == ("cartpole_swingup", "cartpole_swingup (reference)")
    assert "mujoco.batch" in batch["derivatives_by"] and "mujoco.rollout" in reference["derivatives_by"]
    for mine, theirs in zip(batch["detail"], reference["detail"], strict=True):
        assert mine["s0"] == theirs["s0"]
        assert (mine["expert_return"], mine["iterations"]) == (theirs["expert_return"], theirs["iterations"])


def test_only_throughput_answers_every_request_at_each_worker_count_alike(tmp_path: Path, capsys) -> None:
    """Figures are sane (positive, every request answered, speed-up 1 at one worker); no speed is asserted."""
    argv = ["--only", "throughput", "--throughput-requests", "3", "--throughput-workers", "2",
            "--expert-horizon", "40", "--out", str(tmp_path)]  # fmt: skip
    assert main(argv) == 0
    result = json.loads((tmp_path / "bench.json").read_text())
    section = result["expert_throughput"]
    assert section["worker_counts"] == [1, 2] and section["command"] == "npp-bench " + " ".join(argv)
    assert [t["task"] for t in section["tasks"]] == ["pendulum_swingup", "cartpole_swingup"]
    for t in section["tasks"]:
        assert [run["workers"] for run in t["runs"]] == [1, 2]
        # each worker's derivative threads: the cores over the workers, so never more threads than cores
        assert [run["threads_per_worker"] for run in t["runs"]] == [default_threads(1), default_threads(2)]
        for run in t["runs"]:
            assert run["seconds"] > 0 and run["requests_per_s"] > 0 and run["speedup"] > 0
            assert run["cpu_seconds"] > 0 and run["cores_used"] > 0
            assert run["answered"] == 3 and sum(run["stop_reasons"].values()) == 3
            assert run["stop_reasons"].get("time budget", 0) == run["budget_stopped"]
        assert t["runs"][0]["speedup"] == 1.0
        cut = set().union(*(run["budget_stopped_requests"] for run in t["runs"]))
        assert t["compared_requests"] == 3 - len(cut)
        assert t["answers_equal"] is True  # where the optimizer stopped by itself, the same answers bit for bit
        for k in range(3):
            if k not in cut:
                assert len({run["expert_returns"][k] for run in t["runs"]}) == 1
    table = (tmp_path / "bench.md").read_text()
    assert "## Expert throughput" in table and "| pendulum_swingup | 40 | 3 | 2 x 1 |" in table
    assert "## Expert throughput" in capsys.readouterr().out


def test_each_expert_is_timed_at_its_tasks_own_horizon_unless_one_is_given(tmp_path: Path) -> None:
    """A user checking their expert before a run sees it at the run's H: a task file's key horizon (the two-link
    arm's 200), not another task's; --expert-horizon sets one H for every task."""
    example = str(Path(__file__).resolve().parents[1] / "examples" / "two_link_arm" / "task.toml")
    for flags, wanted in (([], 200), (["--expert-horizon", "30"], 30)):
        out = tmp_path / str(wanted)
        assert main(["--only", "experts", "--expert-tasks", example, "--expert-requests", "1", *flags,
                     "--out", str(out)]) == 0  # fmt: skip
        (timed,) = json.loads((out / "bench.json").read_text())["experts"]["tasks"]
        assert timed["horizon"] == wanted, timed["horizon"]
        table = (out / "bench.md").read_text()
        assert f"| two_link_arm-task | {wanted} | 1 |" in table
        assert 'window values; planner = "ilqr" (no plan: one iLQR from the warm start))' in table  # the file's planner


EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_only_queries_times_each_query_on_the_arms_state_and_keeps_the_rest_of_the_file(tmp_path: Path, capsys) -> None:
    """The Panda's 20-entry state at 1,000 points (the index's brute-force tail) and 3,000 (one tree): one-call
    percentiles in order, every bound exact, the earlier file's rows kept; no speed is asserted."""
    (tmp_path / "bench.json").write_text(json.dumps({
        "command": "npp-bench", "date": "then", "machine": machine_info(), "load_average_end": None,
        "targets": [{"case": "kept row", "metric": "ratio", "value": 1.0, "target": "<= 2x", "met": True}],
    }))  # fmt: skip
    argv = ["--only", "queries", "--quick", "--query-task", str(EXAMPLES / "panda_reach" / "task.toml"),
            "--query-sizes", "3000", "1000", "--out", str(tmp_path)]  # fmt: skip
    assert main(argv) == 0
    result = json.loads((tmp_path / "bench.json").read_text())
    section = result["queries"]
    assert result["command"] == "npp-bench" and section["command"] == "npp-bench " + " ".join(argv)
    assert (section["task"], section["state_dim"], section["moving_entries"]) == ("panda_reach-task", 20, 17)
    assert section["control_period_s"] == pytest.approx(0.01) and section["run"] is None
    points = section["points"]
    assert points["run_points"] == 0 and points["horizon"] == 150
    assert points["rollout_points"] == 150 * points["rollouts"] >= 3000
    assert section["lipschitz"]["source"] == "data" and section["lipschitz"]["value"] > 0
    queries = section["queries"]
    calls = queries["single"] * queries["repeats"]
    assert section["exact"] is True
    assert [size["points"] for size in section["sizes"]] == [1000, 3000]
    for size in section["sizes"]:
        assert set(size["trees"]) == {"pykdtree", "ckdtree"}
        assert [(e["label"], e["value"]) for e in size["lipschitz"]] == [
            ("policy", section["lipschitz"]["value"]), ("large", LARGE_LIPSCHITZ)
        ]  # fmt: skip
        timed = [size["trees"][tree]["single"] for tree in size["trees"]]
        for entry in size["lipschitz"]:
            exact = entry["exact"]
            assert exact["exact"] is True and exact["queries"] == queries["checked"] > 0
            assert exact["lower_same_index"] == exact["upper_same_index"] == exact["queries"]
            assert exact["lower_same_value"] == exact["upper_same_value"] == exact["queries"]
            assert 0 < entry["kept_lower"] <= size["points"] and 0 < entry["kept_upper"] <= size["points"]
            assert set(entry["single"]) == set(entry["batch"]) == set(entry["ratios"]) == set(BOUNDS)
            timed += list(entry["single"].values())
            for bound in BOUNDS:
                batch = entry["batch"][bound]
                assert batch["min_us"] <= batch["median_us"] <= batch["max_us"]
                assert set(entry["ratios"][bound]) == {"batch", "single_p50", "single_p99"}
        for t in timed:
            assert t["calls"] == calls and 0 < t["p50_us"] <= t["p90_us"] <= t["p99_us"] <= t["max_us"]
            assert 0 < t["cpu_p50_us"] <= t["cpu_p99_us"]
        large = size["lipschitz"][1]  # L = 1e10: V_lb is the nearest point's value
        assert large["same_point_as_1nn"] >= 0.9 * queries["checked"]
    assert [row["case"] for row in result["targets"]] == [
        "kept row",
        f"Query cost panda_reach-task, 1,000 points, L {section['lipschitz']['value']:.4g}",
        f"Query cost panda_reach-task, 3,000 points, L {section['lipschitz']['value']:.4g}",
    ]
    with_queries(result, section)  # a second measurement replaces the first one's rows
    assert len(result["targets"]) == 3
    table = (tmp_path / "bench.md").read_text()
    assert "## Query cost at an arm's scale (panda_reach-task, 20-entry state, 17 of them moving)" in table
    assert "kept row" in table and "| 3,000 | 1e+10 | V_lb |" in table and "| 1,000 | - | pykdtree 1-NN |" in table
    assert "Exact at every size and L: **True**" in table
    assert "### One query per call" in capsys.readouterr().out


def test_only_queries_puts_a_runs_data_first_at_its_l_and_horizon(tmp_path: Path) -> None:
    """--query-run: the run's expert points are the first points, its L is the one measured, its horizon the
    rollouts'; a run of another task is refused."""
    arm = str(EXAMPLES / "two_link_arm" / "task.toml")
    learn(arm, 0, run_dir=tmp_path / "run", horizon=30, max_episodes=2)
    run = read_run(tmp_path / "run")
    out = tmp_path / "bench"
    argv = ["--only", "queries", "--quick", "--query-task", arm, "--query-run", str(tmp_path / "run"),
            "--query-sizes", "500", "--out", str(out)]  # fmt: skip
    assert main(argv) == 0
    section = json.loads((out / "bench.json").read_text())["queries"]
    points = section["points"]
    assert section["run"] == "run" and points["run_points"] == len(run.dataset) > 0
    assert points["run_trajectories"] == run.dataset.num_trajectories and points["horizon"] == 30
    assert points["run_points"] + points["rollout_points"] >= 500
    assert section["lipschitz"]["value"] == run.metadata.lipschitz and section["exact"] is True
    assert f"{points['run_points']:,d} points of run run" in (out / "bench.md").read_text()
    panda = str(EXAMPLES / "panda_reach" / "task.toml")
    refused = ["--only", "queries", "--quick", "--query-task", panda, "--query-run", str(tmp_path / "run"),
               "--out", str(tmp_path / "refused")]  # fmt: skip
    assert main(refused) == 2 and not (tmp_path / "refused" / "bench.json").exists()
